"""Checked arm motions: straight TCP lines (moveL) and joint-space moves (moveJ).

Every motion is checked at poses ``path_check_step_m`` of tool travel apart (workspace, reach,
clearance: ``motion.safety``) and timed so that no joint turns faster than
``max_joint_speed_rad_s``. A straight line that passes so near a singularity that the TCP would
have to crawl is refused with ``SingularityViolation``; ``line_or_joints`` then moves the joints
instead, to the same pose.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from functools import partial
from typing import Literal

import numpy as np
import ur_analytic_ik
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from controller.config import LimitsConfig, MotionConfig
from controller.motion.safety import (
    Obstacles,
    SafetyViolation,
    check_clearance,
    check_pose,
    check_reachable,
    check_speed,
    check_workspace,
)
from drivers.tool import ToolModel
from drivers.ur5.kinematics import forward_kinematics
from models.geometry import invert_transform, make_transform, rotation_angle_between

FloatArray = NDArray[np.float64]
MotionKind = Literal["line", "joints"]
PoseCheck = Callable[[FloatArray], None]
"""A further check of a flange pose (world): raises SafetyViolation."""

TOOL_REACH_M = 0.17
"""Flange to fingertip: a radian of tool rotation sweeps the tip about this far."""
MIN_LINE_SPEED_M_S = 0.002
"""A line whose joint rates would force the TCP slower than this passes a singularity."""
JOINT_STEP_RESOLUTION_RAD = 0.02
"""Between two checked poses whose joints differ by more than this, the line is bisected (IK
only) to find the fastest joint rate: near a wrist singularity the rate peaks between poses.
A joint move is first sampled this finely, then as finely as its tool travel needs."""
MAX_BISECTIONS = 10
PURE_TURN_M = 0.001
"""A line moving the TCP less than this is timed by its rotation."""
JOINT_LIMIT_RAD = 2 * np.pi
"""Every UR5 joint turns within +-2 pi."""
MAX_LINE_ROTATION_RAD = np.pi / 2
"""Detours turn the tool at most this much per straight line: a half-turn has no unique
shortest rotation, so the planner and the arm could interpolate it differently."""


class SingularityViolation(SafetyViolation):
    """A straight line passes so near a singularity that its joints would turn too fast. Every
    pose on it passed the checks: only the joint rates refuse it (and, where a joint move to
    the same pose was tried instead, that was refused too)."""


@dataclass(frozen=True)
class Waypoint:
    """A checked motion's target: flange pose, its joints, the speed to use and how the arm
    gets there. ``kind`` "line": a straight TCP line (moveL), ``speed_m_s`` in m/s. ``kind``
    "joints": a joint-space move to ``joints_rad`` (moveJ, all joints arriving together), and
    ``speed_m_s`` is then the fastest joint's speed in rad/s, and ``start_joints_rad`` the
    joints its path was checked from: the arm must be there when it starts."""

    pose_world_tcp: FloatArray
    joints_rad: FloatArray
    speed_m_s: float
    label: str
    kind: MotionKind = "line"
    start_joints_rad: FloatArray | None = None


def duration_s(start_world_tcp: FloatArray, start_joints_rad: FloatArray, move: Waypoint) -> float:
    """How long a move takes at its speed, without the acceleration ramps: a line its TCP travel
    (or, for a turn in place, the tool's reach times the angle) over its speed; a joint move its
    largest joint turn over its joint speed."""
    if move.kind == "joints":
        start = start_joints_rad if move.start_joints_rad is None else move.start_joints_rad
        return float(np.max(np.abs(move.joints_rad - start))) / move.speed_m_s
    distance = float(np.linalg.norm(move.pose_world_tcp[:3, 3] - start_world_tcp[:3, 3]))
    angle = rotation_angle_between(start_world_tcp[:3, :3], move.pose_world_tcp[:3, :3])
    travel = distance if distance >= PURE_TURN_M else max(distance, TOOL_REACH_M * angle)
    return travel / move.speed_m_s


class CheckedMotions:
    """Plans single checked motions for the arm; holds no robot state."""

    def __init__(
        self,
        *,
        tool: ToolModel,
        limits: LimitsConfig,
        motion: MotionConfig,
        pose_world_base: FloatArray,
    ) -> None:
        self.tool = tool
        self.limits = limits
        self.motion = motion
        self.pose_world_base = pose_world_base

    def _turning_line(
        self,
        start_world_tcp: FloatArray,
        end_world_tcp: FloatArray,
        joints_rad: FloatArray,
        obstacles: Obstacles,
        *,
        label: str,
    ) -> list[Waypoint]:
        """A straight TCP line that may turn the tool a lot, as lines of at most
        ``MAX_LINE_ROTATION_RAD`` each: turning one way round and, if that is refused, the
        other (e.g. past a wrist singularity one way)."""
        if np.allclose(start_world_tcp, end_world_tcp):
            return []
        start = Rotation.from_matrix(start_world_tcp[:3, :3])
        turn = Rotation.from_matrix(end_world_tcp[:3, :3]) * start.inv()
        rotvec = turn.as_rotvec()
        angle = float(np.linalg.norm(rotvec))
        ways = [rotvec]
        if angle > MAX_LINE_ROTATION_RAD:
            ways.append(rotvec - 2 * np.pi * rotvec / angle)  # the same turn the other way round

        def turning(way: FloatArray) -> list[Waypoint]:
            pieces = max(1, int(np.ceil(np.linalg.norm(way) / MAX_LINE_ROTATION_RAD - 1e-9)))
            stops = []
            for piece in range(1, pieces + 1):
                fraction = piece / pieces
                rotation = (Rotation.from_rotvec(fraction * way) * start).as_matrix()
                position = start_world_tcp[:3, 3] + fraction * (
                    end_world_tcp[:3, 3] - start_world_tcp[:3, 3]
                )
                end = end_world_tcp if piece == pieces else make_transform(rotation, position)
                stops.append((end, label))
            return self._lines(start_world_tcp, joints_rad, stops, obstacles)

        return first_allowed(partial(turning, way) for way in ways)

    def _lines(
        self,
        start_world_tcp: FloatArray,
        joints_rad: FloatArray,
        stops: Sequence[tuple[FloatArray, str]],
        obstacles: Obstacles,
    ) -> list[Waypoint]:
        """Checked straight lines at the TCP speed limit from the start through each
        (pose, label) stop in turn, a joint move where a line passes too near a singularity;
        a stop where the arm already is adds none."""
        waypoints: list[Waypoint] = []
        pose, joints = start_world_tcp, joints_rad
        speed = self.limits.max_tcp_speed_m_s
        for end, label in stops:
            if not np.allclose(pose, end):
                waypoints.append(
                    self.line_or_joints(pose, end, joints, obstacles, speed_m_s=speed, label=label)
                )
                pose, joints = end, waypoints[-1].joints_rad
        return waypoints

    def line_or_joints(
        self,
        start_world_tcp: FloatArray,
        end_world_tcp: FloatArray,
        joints_rad: FloatArray,
        obstacles: Obstacles,
        *,
        speed_m_s: float,
        label: str,
        exempt_parts: tuple[str, ...] = (),
        near_parts: tuple[str, ...] = (),
        joint_move_check: PoseCheck | None = None,
    ) -> Waypoint:
        """A checked straight line or a checked joint move to the same pose, its poses passing
        ``joint_move_check`` too: the joint move when the line passes too near a singularity
        (only then: a line refused by an obstacle stays refused), or when the joint rates slow
        the line so much that the joint move arrives sooner (near a wrist singularity a line
        may crawl at a few mm/s for tens of seconds)."""
        start_joints = check_reachable(start_world_tcp, self.pose_world_base, joints_rad)
        try:
            line = self.line(
                start_world_tcp,
                end_world_tcp,
                joints_rad,
                obstacles,
                speed_m_s=speed_m_s,
                label=label,
                exempt_parts=exempt_parts,
                near_parts=near_parts,
            )
        except SingularityViolation as violation:
            singular = violation
        else:
            if line.speed_m_s >= speed_m_s:
                return line
            try:
                joints = self.joint_move_to(
                    start_joints,
                    end_world_tcp,
                    obstacles,
                    label,
                    exempt_parts=exempt_parts,
                    near_parts=near_parts,
                    pose_check=joint_move_check,
                )
            except SafetyViolation:
                return line
            line_s = duration_s(start_world_tcp, start_joints, line)
            return joints if duration_s(start_world_tcp, start_joints, joints) < line_s else line
        try:
            return self.joint_move_to(
                start_joints,
                end_world_tcp,
                obstacles,
                label,
                exempt_parts=exempt_parts,
                near_parts=near_parts,
                pose_check=joint_move_check,
            )
        except SafetyViolation as refusal:
            raise SingularityViolation(f"{singular}; as a joint move: {refusal}") from None

    def joint_move_to(
        self,
        start_joints_rad: FloatArray,
        end_world_tcp: FloatArray,
        obstacles: Obstacles,
        label: str,
        exempt_parts: Sequence[str] = (),
        near_parts: Sequence[str] = (),
        *,
        pose_check: PoseCheck | None = None,
    ) -> Waypoint:
        """A checked joint move to a pose: to its joint solution that turns the joints least
        (the one nearest the start, or the wrist turned over) among those whose path passes
        the checks. SafetyViolation with the nearest solution's refusal when none does."""
        solutions = self.joint_solutions(end_world_tcp, start_joints_rad)
        if not solutions:
            check_reachable(end_world_tcp, self.pose_world_base, start_joints_rad)  # raises
        refusal: SafetyViolation | None = None
        for joints in solutions:
            try:
                move = self.joint_move(
                    start_joints_rad,
                    joints,
                    obstacles,
                    label,
                    exempt_parts,
                    near_parts,
                    pose_check=pose_check,
                )
            except SafetyViolation as violation:
                refusal = refusal or violation
                continue
            return replace(move, pose_world_tcp=end_world_tcp)
        assert refusal is not None
        raise refusal

    def joint_solutions(
        self, pose_world_tcp: FloatArray, joints_near_rad: FloatArray
    ) -> list[FloatArray]:
        """The arm's joint solutions (rad) for a flange pose that keep its shoulder and elbow
        on the side ``joints_near_rad`` has them, each joint the turn nearest it within +-2 pi;
        least largest joint turn first. The other sides are left out: the checks see only the
        tool, and those would swing the links (the elbow down toward the table)."""
        near = np.asarray(joints_near_rad, dtype=float)
        pose_base = np.ascontiguousarray(invert_transform(self.pose_world_base) @ pose_world_tcp)
        found: list[FloatArray] = []
        for solution in ur_analytic_ik.ur5.inverse_kinematics(pose_base):
            joints = np.asarray(solution, dtype=float)
            if not np.all(np.isfinite(joints)):
                continue
            joints = near + _wrapped(joints - near)
            joints = np.where(
                np.abs(joints) > JOINT_LIMIT_RAD, joints - np.sign(joints) * 2 * np.pi, joints
            )
            same_shoulder = abs(_wrapped(joints[0] - near[0])) < np.pi / 2
            same_elbow = _wrapped(joints[2]) * _wrapped(near[2]) >= 0.0
            if same_shoulder and same_elbow and not any(np.allclose(joints, q) for q in found):
                found.append(joints)
        return sorted(found, key=lambda joints: float(np.max(np.abs(joints - near))))

    def joint_move(
        self,
        start_joints_rad: FloatArray,
        end_joints_rad: FloatArray,
        obstacles: Obstacles,
        label: str,
        exempt_parts: Sequence[str] = (),
        near_parts: Sequence[str] = (),
        *,
        pose_check: PoseCheck | None = None,
    ) -> Waypoint:
        """A checked joint-space move (moveJ: the joints interpolated linearly, all arriving
        together). The tool poses (forward kinematics) along it, at most ``path_check_step_m``
        of tool travel apart, pass the workspace and clearance checks (and ``pose_check``);
        the speed (rad/s, of the fastest joint) keeps every joint within
        ``max_joint_speed_rad_s`` and the tool within ``max_tcp_speed_m_s``. SafetyViolation
        on the first failing pose."""
        start = np.asarray(start_joints_rad, dtype=float)
        end = np.asarray(end_joints_rad, dtype=float)
        if np.any(np.abs(end) > JOINT_LIMIT_RAD):
            raise SafetyViolation(f"{label}: joints {np.round(end, 3).tolist()} beyond +-2 pi")
        poses, travel_per_fraction = self._joint_path(start, end)
        for pose in poses[1:]:
            try:
                check_workspace(pose, self.limits)
                check_clearance(
                    pose,
                    self.motion.touch_width_m,
                    self.tool,
                    obstacles,
                    self.limits,
                    exempt_parts=exempt_parts,
                    near_parts=near_parts,
                )
                if pose_check is not None:
                    pose_check(pose)
            except SafetyViolation as violation:
                raise SafetyViolation(f"{label} (joint move): {violation}") from None
        speed_rad_s = self.limits.max_joint_speed_rad_s
        largest_turn = float(np.max(np.abs(end - start)))
        # A move of no turn at all (start and end the same joints, to rounding) keeps the
        # joint speed: the ratio below would be 0, a speed the arm refuses.
        if travel_per_fraction > 0 and largest_turn > 1e-9:
            # At s (fraction per second) = speed / largest turn the tool travels
            # travel_per_fraction * s metres per second.
            tool_speed_limit = self.limits.max_tcp_speed_m_s * largest_turn / travel_per_fraction
            speed_rad_s = min(speed_rad_s, tool_speed_limit)
        return Waypoint(poses[-1], end, speed_rad_s, label, kind="joints", start_joints_rad=start)

    def _joint_path(self, start: FloatArray, end: FloatArray) -> tuple[list[FloatArray], float]:
        """Flange poses along a joint move, from the start, at most ``path_check_step_m`` of
        tool travel (flange travel plus ``TOOL_REACH_M`` per radian turned) apart; and the most
        tool travel per unit of the move. Over a ``JOINT_STEP_RESOLUTION_RAD`` stretch the tool
        moves nearly straight, so the travel between its ends measures it."""
        turn = end - start
        coarse = max(1, int(np.ceil(float(np.max(np.abs(turn))) / JOINT_STEP_RESOLUTION_RAD)))
        fractions = np.linspace(0.0, 1.0, coarse + 1)
        coarse_poses = [self._flange_pose(start + f * turn) for f in fractions]
        poses = [coarse_poses[0]]
        travel_per_fraction = 0.0
        for index in range(coarse):
            before, after = coarse_poses[index], coarse_poses[index + 1]
            travel = float(np.linalg.norm(after[:3, 3] - before[:3, 3])) + (
                TOOL_REACH_M * rotation_angle_between(before[:3, :3], after[:3, :3])
            )
            travel_per_fraction = max(travel_per_fraction, travel * coarse)
            pieces = max(1, int(np.ceil(travel / self.motion.path_check_step_m)))
            for piece in range(1, pieces):
                fraction = fractions[index] + piece / pieces / coarse
                poses.append(self._flange_pose(start + fraction * turn))
            poses.append(after)
        return poses, travel_per_fraction

    def _flange_pose(self, joints_rad: FloatArray) -> FloatArray:
        return self.pose_world_base @ forward_kinematics(joints_rad)

    def line(
        self,
        start_world_tcp: FloatArray,
        end_world_tcp: FloatArray,
        joints_rad: FloatArray,
        obstacles: Obstacles,
        *,
        speed_m_s: float,
        label: str,
        exempt_parts: tuple[str, ...] = (),
        near_parts: tuple[str, ...] = (),
    ) -> Waypoint:
        """A checked straight TCP line (slerped orientation, as moveL moves): every pose
        ``path_check_step_m`` apart passes the safety checks, and the speed is lowered so that
        no joint turns faster than ``max_joint_speed_rad_s`` (the fastest joint rate is found by
        bisecting where the joints turn fast). SafetyViolation on the first failing pose;
        SingularityViolation when the line passes so near a singularity that the TCP would
        have to crawl."""
        check_speed(speed_m_s, self.limits.max_tcp_speed_m_s)
        distance = float(np.linalg.norm(end_world_tcp[:3, 3] - start_world_tcp[:3, 3]))
        angle = rotation_angle_between(start_world_tcp[:3, :3], end_world_tcp[:3, :3])
        length = max(distance, TOOL_REACH_M * angle)
        steps = max(1, int(np.ceil(length / self.motion.path_check_step_m)))
        rotations = Rotation.from_matrix(np.stack([start_world_tcp[:3, :3], end_world_tcp[:3, :3]]))
        slerp = Slerp([0.0, 1.0], rotations)

        def pose_at(fraction: float) -> FloatArray:
            return make_transform(
                slerp(fraction).as_matrix(),
                start_world_tcp[:3, 3] + fraction * (end_world_tcp[:3, 3] - start_world_tcp[:3, 3]),
            )

        # The joints at the start pose (nearest those given): rates are measured from there.
        joints = check_reachable(start_world_tcp, self.pose_world_base, joints_rad)
        joint_rad_per_fraction = 0.0
        previous = 0.0
        for fraction in np.linspace(0.0, 1.0, steps + 1)[1:]:
            try:
                next_joints = check_pose(
                    pose_at(fraction),
                    self.motion.touch_width_m,
                    tool=self.tool,
                    obstacles=obstacles,
                    limits=self.limits,
                    pose_world_base=self.pose_world_base,
                    joints_near_rad=joints,
                    exempt_parts=exempt_parts,
                    near_parts=near_parts,
                )
            except SafetyViolation as violation:
                raise SafetyViolation(f"{label}: {violation}") from None
            joint_rad_per_fraction = max(
                joint_rad_per_fraction,
                self._peak_joint_rate(pose_at, previous, fraction, joints, next_joints),
            )
            joints, previous = next_joints, fraction
        if joint_rad_per_fraction > 0:
            # The line must last at least (largest joint turn per unit of the line) / (joint
            # speed limit); at the TCP speed it lasts at least distance / speed. (A pure turn is
            # timed by the tool's reach instead.)
            seconds = joint_rad_per_fraction / self.limits.max_joint_speed_rad_s
            # (A line shorter than PURE_TURN_M without a turn, as a retreat of one approach
            # step, is timed by its distance.)
            travel = distance if distance >= PURE_TURN_M else max(distance, TOOL_REACH_M * angle)
            speed_m_s = min(speed_m_s, travel / seconds)
        if speed_m_s < MIN_LINE_SPEED_M_S:
            raise SingularityViolation(
                f"{label}: line to {np.round(end_world_tcp[:3, 3], 3).tolist()} m passes near a "
                "singularity (joints would turn too fast)"
            )
        return Waypoint(end_world_tcp, joints, speed_m_s, label)

    def _peak_joint_rate(
        self,
        pose_at: Callable[[float], FloatArray],
        start: float,
        end: float,
        start_joints: FloatArray,
        end_joints: FloatArray,
        bisections: int = MAX_BISECTIONS,
    ) -> float:
        """The largest joint turn per unit of line fraction between two fractions, bisecting
        (IK only) while the joints between them differ by more than the resolution."""
        turn = float(np.max(np.abs(end_joints - start_joints)))
        if turn <= JOINT_STEP_RESOLUTION_RAD or bisections == 0:
            return turn / (end - start)
        middle = (start + end) / 2
        middle_joints = check_reachable(pose_at(middle), self.pose_world_base, start_joints)
        left = self._peak_joint_rate(
            pose_at, start, middle, start_joints, middle_joints, bisections - 1
        )
        right = self._peak_joint_rate(
            pose_at, middle, end, middle_joints, end_joints, bisections - 1
        )
        return max(left, right)


def tool_reach_along(
    pose_world_tcp: FloatArray, width_m: float, tool: ToolModel, direction_world: FloatArray
) -> float:
    """How far the tool's rigid parts reach along a unit direction (world): the largest
    projection of any of their corners."""
    reach = -np.inf
    for box in tool.rigid_boxes(width_m):
        pose_world_box = pose_world_tcp @ box.pose_tcp_box
        corner = np.abs(direction_world @ pose_world_box[:3, :3]) @ box.half_extents_m
        reach = max(reach, float(direction_world @ pose_world_box[:3, 3] + corner))
    return reach


def first_allowed(candidates: Iterable[Callable[[], list[Waypoint]]]) -> list[Waypoint]:
    """The first candidate path the safety checks accept, tried in order; when all are
    refused, the first refusal (the preferred path's reason)."""
    refusal: SafetyViolation | None = None
    for plan in candidates:
        try:
            return plan()
        except SafetyViolation as violation:
            refusal = refusal or violation
    if refusal is None:
        raise ValueError("no candidate paths to try")
    raise refusal


def _wrapped(angles_rad: FloatArray | float) -> FloatArray:
    """Angles wrapped into [-pi, pi)."""
    return (np.asarray(angles_rad, dtype=float) + np.pi) % (2 * np.pi) - np.pi
