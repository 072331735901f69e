"""Motion planning for touches, as in the paper; every pose is checked by ``motion.safety``.

A touch: the arm brings the pad to ``approach_distance_m`` from the target on its approach line
(pad facing the surface), approaches along the line to ``standoff_m`` before the predicted
surface, then the fingers open slowly so the pad makes the final, force-limited contact. Between
touches the arm moves straight when the targets are close around the object's vertical axis and
otherwise detours through a safe height above the shape estimate. Straight-line motions are
checked at poses ``path_check_step_m`` apart (workspace, reach, joint continuity, clearance).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation, Slerp

from controller.config import LimitsConfig, MotionConfig
from controller.motion.safety import (
    Obstacles,
    SafetyViolation,
    check_pose,
    check_reachable,
    check_speed,
)
from drivers.config import ArmConfig
from drivers.tool import ToolModel
from drivers.ur5.kinematics import forward_kinematics
from models.geometry import (
    frame_from_z_axis,
    invert_transform,
    make_transform,
    radial_angle_about_vertical,
    rotation_angle_between,
    ur_pose_to_matrix,
)

FloatArray = NDArray[np.float64]

APPROACH_EXEMPT_PARTS = ("gelsight_window",)
"""The part carrying the gel leads into the contact: on the approach it may come up to the
estimate itself (the force readings guard it)."""
APPROACH_NEAR_PARTS = ("gelsight_housing", "finger_sensor_side")
"""On the approach these may come up to where the object may be, without the margin: they sit
behind the gel, but no force reading guards them (an edge can meet the housing first)."""
TOOL_REACH_M = 0.17
"""Flange to fingertip: a radian of tool rotation sweeps the tip about this far."""
MIN_LINE_SPEED_M_S = 0.002
"""A line whose joint rates would force the TCP slower than this passes a singularity."""
JOINT_STEP_RESOLUTION_RAD = 0.02
"""Between two checked poses whose joints differ by more than this, the line is bisected (IK
only) to find the fastest joint rate: near a wrist singularity the rate peaks between poses."""
MAX_BISECTIONS = 10
PURE_TURN_M = 0.001
"""A line moving the TCP less than this is timed by its rotation."""
DETOUR_BACK_OFFS_M = (0.0, 0.05, 0.1)
"""How much further back along the approach line a detour may come down before moving in."""
AT_POSE_TOLERANCE_M = 0.001
AT_POSE_TOLERANCE_RAD = 0.01
"""The arm counts as at a pose (home) this near it: well above the arm's repeatability, well
below anything that changes what the camera sees or where a path starts."""
MAX_LINE_ROTATION_RAD = np.pi / 2
"""Detours turn the tool at most this much per straight line: a half-turn has no unique
shortest rotation, so the planner and the arm could interpolate it differently."""


def pad_pose_facing(
    point_world: ArrayLike, normal_world: ArrayLike, standoff_m: float
) -> FloatArray:
    """Pad pose with the gel facing a surface point from ``standoff_m`` along its normal.

    The pad's +z (gel normal) points against the surface normal. Its +x (along the finger,
    toward the tip) points as far down as the surface allows, so that on a side touch the
    gripper body stays above the pad, and on a top touch the fingers lie horizontal.
    """
    normal = np.asarray(normal_world, dtype=float)
    normal = normal / np.linalg.norm(normal)
    pad_z = -normal
    down = np.array([0.0, 0.0, -1.0])
    x_hint = down if abs(np.dot(down, pad_z)) < 0.95 else np.cross(pad_z, [0.0, 1.0, 0.0])
    rotation = frame_from_z_axis(pad_z, x_hint)
    return make_transform(rotation, np.asarray(point_world, dtype=float) + standoff_m * normal)


def tcp_pose_for_pad(pose_world_pad: FloatArray, tool: ToolModel, width_m: float) -> FloatArray:
    """Flange pose that puts the pad at ``pose_world_pad`` with the fingers open ``width_m``."""
    return pose_world_pad @ invert_transform(tool.pose_tcp_pad(width_m))


@dataclass(frozen=True)
class Waypoint:
    """A checked straight-line motion target: flange pose, its joints, and the speed to use."""

    pose_world_tcp: FloatArray
    joints_rad: FloatArray
    speed_m_s: float
    label: str


@dataclass(frozen=True)
class TouchGeometry:
    """Where a touch happens. ``direction_world`` is the approach direction (the pad's +z);
    the pad centre sweeps from ``pad_start_world`` up to ``pad_reach_world`` at the most."""

    target_world: FloatArray
    direction_world: FloatArray
    pose_world_tcp_start: FloatArray
    pose_world_tcp_standoff: FloatArray
    pad_start_world: FloatArray
    pad_reach_world: FloatArray


class MotionPlanner:
    """Plans checked waypoints for touches and transits; holds no robot state."""

    def __init__(
        self,
        *,
        tool: ToolModel,
        limits: LimitsConfig,
        motion: MotionConfig,
        pose_world_base: FloatArray,
        stroke_m: float,
        object_point_world: ArrayLike = (0.0, 0.0, 0.0),
    ) -> None:
        self.tool = tool
        self.limits = limits
        self.motion = motion
        self.pose_world_base = pose_world_base
        self.stroke_m = stroke_m
        self.object_point_world = np.asarray(object_point_world, dtype=float)

    def touch_geometry(self, target_world: ArrayLike, direction_world: ArrayLike) -> TouchGeometry:
        """Approach start and stand-off for a target approached along ``direction_world``."""
        target = np.asarray(target_world, dtype=float)
        direction = np.asarray(direction_world, dtype=float)
        direction = direction / np.linalg.norm(direction)
        motion = self.motion
        width = motion.touch_width_m
        pad_start = pad_pose_facing(target, -direction, motion.approach_distance_m)
        pad_standoff = pad_pose_facing(target, -direction, motion.standoff_m)
        finger_travel_m = (self.stroke_m - width) / 2
        return TouchGeometry(
            target_world=target,
            direction_world=direction,
            pose_world_tcp_start=tcp_pose_for_pad(pad_start, self.tool, width),
            pose_world_tcp_standoff=tcp_pose_for_pad(pad_standoff, self.tool, width),
            pad_start_world=pad_start[:3, 3],
            pad_reach_world=pad_standoff[:3, 3] + finger_travel_m * direction,
        )

    def plan_approach(
        self, touch: TouchGeometry, joints_rad: FloatArray, obstacles: Obstacles
    ) -> Waypoint:
        """The slow straight approach from the start to the stand-off. The start itself must
        be clear as a transit's end is (every part with the full margin)."""
        check_pose(
            touch.pose_world_tcp_start,
            self.motion.touch_width_m,
            tool=self.tool,
            obstacles=obstacles,
            limits=self.limits,
            pose_world_base=self.pose_world_base,
            joints_near_rad=joints_rad,
        )
        return self.line(
            touch.pose_world_tcp_start,
            touch.pose_world_tcp_standoff,
            joints_rad,
            obstacles,
            speed_m_s=self.limits.approach_speed_m_s,
            label="approach",
            exempt_parts=APPROACH_EXEMPT_PARTS,
            near_parts=APPROACH_NEAR_PARTS,
        )

    def plan_retract(
        self, touch: TouchGeometry, pose_world_tcp: FloatArray, joints_rad: FloatArray
    ) -> Waypoint:
        """Back out along the approach line, from where the arm is on it (at the stand-off, or
        where the pad touched on the way) to the approach start: the way it came, so only the
        table is checked."""
        return self.line(
            pose_world_tcp,
            touch.pose_world_tcp_start,
            joints_rad,
            Obstacles.none(),
            speed_m_s=self.limits.max_tcp_speed_m_s,
            label="retract",
            exempt_parts=APPROACH_EXEMPT_PARTS,
            near_parts=APPROACH_NEAR_PARTS,
        )

    def plan_transit(
        self,
        pose_world_tcp: FloatArray,
        joints_rad: FloatArray,
        touch: TouchGeometry,
        obstacles: Obstacles,
        *,
        came_from: Sequence[FloatArray] = (),
    ) -> list[Waypoint]:
        """From the current flange pose to the touch's approach start: straight when the radial
        angle between here and the target is small and the line is clear, else a detour.
        ``came_from`` lists the poses the arm passed through to get here (oldest first): when
        the estimate, refined since, blocks every way out, the arm goes back along them (it
        has been there, so only the table is checked) until a detour is possible."""
        angle = radial_angle_about_vertical(
            pose_world_tcp[:3, 3], touch.target_world, self.object_point_world
        )
        goal = touch.pose_world_tcp_start
        speed = self.limits.max_tcp_speed_m_s
        if angle <= np.radians(self.motion.direct_move_max_angle_deg):
            try:
                return [
                    self.line(
                        pose_world_tcp, goal, joints_rad, obstacles, speed_m_s=speed, label="direct"
                    )
                ]
            except SafetyViolation:
                pass  # blocked by the shape or out of reach on the way: go around above
        try:
            return self.plan_detour(pose_world_tcp, joints_rad, goal, obstacles)
        except SafetyViolation as violation:
            refusal = violation
        retrace: list[Waypoint] = []
        pose, joints = pose_world_tcp, joints_rad
        for earlier in reversed(came_from):
            if not np.allclose(earlier, pose):
                try:
                    retrace.append(
                        self.line(
                            pose,
                            earlier,
                            joints,
                            Obstacles.none(),
                            speed_m_s=speed,
                            label="retrace",
                        )
                    )
                except SafetyViolation:
                    break  # not the way the arm came after all (reach, speed): stop here
                pose, joints = earlier, retrace[-1].joints_rad
            try:
                return retrace + self.plan_detour(pose, joints, goal, obstacles)
            except SafetyViolation:
                continue
        raise refusal

    def plan_detour(
        self,
        pose_world_tcp: FloatArray,
        joints_rad: FloatArray,
        goal_world_tcp: FloatArray,
        obstacles: Obstacles,
    ) -> list[Waypoint]:
        """Up to the safe height, across above the object, down to the goal. When the way down
        is blocked (a wider part of the object above a side touch), down to a point further back
        along the approach line and in along it to the goal."""
        top_m = self._estimate_top_m(obstacles)
        safe_z = max(
            pose_world_tcp[2, 3],
            self._flange_height_clearing(pose_world_tcp, top_m),
            self._flange_height_clearing(goal_world_tcp, top_m),
        )
        waypoints = self._leave_upward(pose_world_tcp, joints_rad, safe_z, obstacles)
        lift = waypoints[-1].pose_world_tcp if waypoints else pose_world_tcp
        joints = waypoints[-1].joints_rad if waypoints else joints_rad

        def via(back_m: float) -> list[Waypoint]:
            # The tool's +x is the approach direction (the pad faces along it).
            down_to = goal_world_tcp.copy()
            down_to[:3, 3] -= back_m * goal_world_tcp[:3, 0]
            above = down_to.copy()
            above[2, 3] = max(safe_z, down_to[2, 3])
            way = self._turning_line(lift, above, joints, obstacles, label="across")
            end_joints = way[-1].joints_rad if way else joints
            stops = [(down_to, "descend"), (goal_world_tcp, "in")]
            return way + self._lines(above, end_joints, stops, obstacles)

        return waypoints + _first_allowed(partial(via, b) for b in DETOUR_BACK_OFFS_M)

    def _leave_upward(
        self, pose_world_tcp: FloatArray, joints_rad: FloatArray, z_m: float, obstacles: Obstacles
    ) -> list[Waypoint]:
        """Straight up to the flange height ``z_m`` or, when something above blocks the way,
        first further back along the approach line the tool faces (tool -x), then up."""
        leaving = self._leaving(pose_world_tcp, joints_rad, obstacles)

        def via(back_m: float) -> list[Waypoint]:
            back = pose_world_tcp.copy()
            back[:3, 3] -= back_m * pose_world_tcp[:3, 0]
            up = back.copy()
            up[2, 3] = max(z_m, back[2, 3])
            return self._lines(pose_world_tcp, joints_rad, [(back, "back"), (up, "lift")], leaving)

        return _first_allowed(partial(via, b) for b in DETOUR_BACK_OFFS_M)

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

        return _first_allowed(partial(turning, way) for way in ways)

    def _lines(
        self,
        start_world_tcp: FloatArray,
        joints_rad: FloatArray,
        stops: Sequence[tuple[FloatArray, str]],
        obstacles: Obstacles,
    ) -> list[Waypoint]:
        """Checked straight lines at the TCP speed limit from the start through each
        (pose, label) stop in turn; a stop where the arm already is adds none."""
        waypoints: list[Waypoint] = []
        pose, joints = start_world_tcp, joints_rad
        speed = self.limits.max_tcp_speed_m_s
        for end, label in stops:
            if not np.allclose(pose, end):
                waypoints.append(
                    self.line(pose, end, joints, obstacles, speed_m_s=speed, label=label)
                )
                pose, joints = end, waypoints[-1].joints_rad
        return waypoints

    def plan_retreat(
        self,
        pose_world_tcp: FloatArray,
        joints_rad: FloatArray,
        *,
        back_to_world_tcp: FloatArray | None,
    ) -> list[Waypoint]:
        """Where the arm goes after a fault, an abort or at the end of a session: back to where
        the interrupted motion started (the way it came, known to be clear) or, with no motion
        interrupted (None), nowhere: the arm stays. Never to a pose relative to where the arm
        is, so repeated faults cannot walk it away step by step. Then ``plan_lift``."""
        if back_to_world_tcp is None or np.allclose(back_to_world_tcp, pose_world_tcp):
            return []
        # Retracing: the shape estimate may be wrong right here, the table is not.
        return [
            self.line(
                pose_world_tcp,
                back_to_world_tcp,
                joints_rad,
                Obstacles.none(),
                speed_m_s=self.limits.max_tcp_speed_m_s,
                label="retreat",
            )
        ]

    def plan_home(
        self,
        pose_world_tcp: FloatArray,
        joints_rad: FloatArray,
        home_world_tcp: FloatArray,
        obstacles: Obstacles,
    ) -> list[Waypoint]:
        """To the home pose (none when the arm is there): up to the safe height above
        ``obstacles``, across and down, as a detour between touches goes."""
        if at_pose(pose_world_tcp, home_world_tcp):
            return []
        return self.plan_detour(pose_world_tcp, joints_rad, home_world_tcp, obstacles)

    def plan_lift(
        self, pose_world_tcp: FloatArray, joints_rad: FloatArray, obstacles: Obstacles
    ) -> list[Waypoint]:
        """Up to the safe height above the shape estimate (none when already there), backing
        out along the approach line first if the way up is blocked."""
        z_m = self._flange_height_clearing(pose_world_tcp, self._estimate_top_m(obstacles))
        return self._leave_upward(pose_world_tcp, joints_rad, z_m, obstacles)

    def _leaving(
        self, pose_world_tcp: FloatArray, joints_rad: FloatArray, obstacles: Obstacles
    ) -> Obstacles:
        """The obstacles for a lift from where the arm is. The arm got here without touching
        anything, but a refined estimate may since have spread where the object may be up to
        it: a lift from a pose inside that margin keeps the margin from the estimate itself
        (else the arm could never leave)."""
        try:
            check_pose(
                pose_world_tcp,
                self.motion.touch_width_m,
                tool=self.tool,
                obstacles=obstacles,
                limits=self.limits,
                pose_world_base=self.pose_world_base,
                joints_near_rad=joints_rad,
            )
        except SafetyViolation:
            return Obstacles(obstacles.occupied_points_world)
        return obstacles

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
        bisecting where the joints turn fast). SafetyViolation on the first failing pose, or
        when the line passes so near a singularity that the TCP would have to crawl."""
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
            travel = distance if distance >= PURE_TURN_M else TOOL_REACH_M * angle
            speed_m_s = min(speed_m_s, travel / seconds)
        if speed_m_s < MIN_LINE_SPEED_M_S:
            raise SafetyViolation(
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

    def _estimate_top_m(self, obstacles: Obstacles) -> float:
        points = obstacles.possible
        return float(points[:, 2].max()) if len(points) else 0.0

    def _flange_height_clearing(self, pose_world_tcp: FloatArray, top_m: float) -> float:
        """Flange height at which every tool part of this orientation is above ``top_m`` plus
        the safe margin."""
        rotation = pose_world_tcp[:3, :3]
        lowest_below_flange = min(
            (rotation @ box.pose_tcp_box[:3, 3])[2]
            - np.abs(rotation[2, :] @ box.pose_tcp_box[:3, :3]) @ box.half_extents_m
            for box in self.tool.rigid_boxes(self.motion.touch_width_m)
        )
        return top_m + self.motion.safe_height_margin_m - lowest_below_flange


def home_pose_world_tcp(arm: ArmConfig) -> FloatArray:
    """The TCP pose (world frame) at the arm's configured home joints."""
    joints = np.asarray(arm.home_joints_rad, dtype=float)
    pose_base_tcp = forward_kinematics(joints) @ ur_pose_to_matrix(arm.tcp_offset)
    return ur_pose_to_matrix(arm.pose_world_base) @ pose_base_tcp


def at_pose(pose_world_tcp: FloatArray, goal_world_tcp: FloatArray) -> bool:
    """Whether a flange pose is at a goal within ``AT_POSE_TOLERANCE_M`` and ``_RAD``."""
    distance = float(np.linalg.norm(pose_world_tcp[:3, 3] - goal_world_tcp[:3, 3]))
    angle = rotation_angle_between(pose_world_tcp[:3, :3], goal_world_tcp[:3, :3])
    return distance <= AT_POSE_TOLERANCE_M and angle <= AT_POSE_TOLERANCE_RAD


def _first_allowed(candidates: Iterable[Callable[[], list[Waypoint]]]) -> list[Waypoint]:
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
