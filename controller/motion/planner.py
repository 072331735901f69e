"""Motion planning for touches, as in the paper; every pose is checked by ``motion.safety``.

A touch: the arm brings the pad to ``approach_distance_m`` from the target on its approach line
(pad facing the surface), approaches along the line to ``standoff_m`` before the predicted
surface, then the fingers open slowly so the pad makes the final, force-limited contact. Between
touches the arm moves straight when the targets are close around the object's vertical axis and
otherwise detours through a safe height above the shape estimate. Straight-line motions are
checked at poses ``path_check_step_m`` apart (workspace, reach, joint continuity, clearance:
``motion.lines``). Singularities are planned around: a touch may roll the tool about its
approach line, and a transit or retract line that passes too near one becomes a checked joint
move to the same pose.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np
from numpy.typing import ArrayLike, NDArray

from controller.config import Config, LimitsConfig, MotionConfig
from controller.motion.lines import TOOL_REACH_M as TOOL_REACH_M
from controller.motion.lines import (
    CheckedMotions,
    SingularityViolation,
    Waypoint,
    duration_s,
    first_allowed,
    tool_reach_along,
)
from controller.motion.poses import TOUCH_ROLLS_RAD, at_pose, pad_pose_facing, tcp_pose_for_pad
from controller.motion.safety import Obstacles, SafetyViolation, check_pose, check_reachable
from drivers.tool import ToolModel
from models.geometry import (
    radial_angle_about_vertical,
)

FloatArray = NDArray[np.float64]

APPROACH_EXEMPT_PARTS = ("gelsight_window",)
"""The part carrying the gel leads into the contact: on the approach it may come up to the
estimate itself (the force readings guard it)."""
APPROACH_NEAR_PARTS = ("gelsight_housing", "finger_sensor_side")
"""On the approach these may come up to where the object may be, without the margin: they sit
behind the gel, but no force reading guards them (an edge can meet the housing first)."""
DETOUR_BACK_OFFS_M = (0.0, 0.05, 0.1)
"""How much further back along the approach line a detour may come down before moving in."""
APPROACH_EXTENSIONS_M = (0.0, 0.03, 0.06, 0.1)
"""How much further back than ``approach_distance_m`` an approach may start when where the object
may be (seen from one view, its hidden back is a deep shadow) reaches the usual start."""


@dataclass(frozen=True)
class TouchGeometry:
    """Where a touch happens. ``direction_world`` is the approach direction (the pad's +z);
    the pad centre sweeps from ``pad_start_world`` up to ``pad_reach_world`` at the most.
    ``roll_rad``: how far the tool is turned about the approach line."""

    target_world: FloatArray
    direction_world: FloatArray
    pose_world_tcp_start: FloatArray
    pose_world_tcp_standoff: FloatArray
    pad_start_world: FloatArray
    pad_reach_world: FloatArray
    roll_rad: float = 0.0


@dataclass(frozen=True)
class TouchPlan:
    """A touch's checked motions: the transit to the approach start (empty when the arm is
    there) and the approach, at the tool roll ``roll_rad`` (``touch.roll_rad``) whose transit,
    approach and retract were all accepted."""

    touch: TouchGeometry
    transit: list[Waypoint]
    approach: Waypoint
    roll_rad: float


class MotionPlanner(CheckedMotions):
    """Plans checked waypoints for touches and transits; holds no robot state."""

    @classmethod
    def for_config(
        cls, config: Config, tool: ToolModel, pose_world_base: FloatArray
    ) -> MotionPlanner:
        """The planner of a session under ``config``."""
        return cls(
            tool=tool,
            limits=config.limits,
            motion=config.motion,
            pose_world_base=pose_world_base,
            stroke_m=config.gripper.stroke_m,
            object_point_world=config.voxel_grid.object_point_world,
        )

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
        super().__init__(tool=tool, limits=limits, motion=motion, pose_world_base=pose_world_base)
        self.stroke_m = stroke_m
        self.object_point_world = np.asarray(object_point_world, dtype=float)

    def touch_geometry(
        self,
        target_world: ArrayLike,
        direction_world: ArrayLike,
        roll_rad: float = 0.0,
        approach_distance_m: float | None = None,
    ) -> TouchGeometry:
        """Approach start and stand-off for a target approached along ``direction_world``, the
        pad (and so the whole tool) turned by ``roll_rad`` about the approach line, the start
        ``approach_distance_m`` from the target (the configured distance by default)."""
        target = np.asarray(target_world, dtype=float)
        direction = np.asarray(direction_world, dtype=float)
        direction = direction / np.linalg.norm(direction)
        motion = self.motion
        width = motion.touch_width_m
        if approach_distance_m is None:
            approach_distance_m = motion.approach_distance_m
        pad_start = pad_pose_facing(target, -direction, approach_distance_m, roll_rad)
        pad_standoff = pad_pose_facing(target, -direction, motion.standoff_m, roll_rad)
        finger_travel_m = (self.stroke_m - width) / 2
        return TouchGeometry(
            target_world=target,
            direction_world=direction,
            pose_world_tcp_start=tcp_pose_for_pad(pad_start, self.tool, width),
            pose_world_tcp_standoff=tcp_pose_for_pad(pad_standoff, self.tool, width),
            pad_start_world=pad_start[:3, 3],
            pad_reach_world=pad_standoff[:3, 3] + finger_travel_m * direction,
            roll_rad=float(roll_rad),
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
        table is checked. When that line passes too near a singularity (the arm's joints are not
        those the approach was planned with), a checked joint move back to the approach start
        instead. That need not follow the line, and a wrist turning over near the surface would
        sweep the tool into it: no part of the tool may come further along the approach
        direction than the tool reaches where it starts (so it never nears the touched surface
        and, on a convex object, stays clear of it); the table is checked as for the line."""
        direction = touch.direction_world
        width = self.motion.touch_width_m
        limit = tool_reach_along(pose_world_tcp, width, self.tool, direction)

        def no_nearer(pose: FloatArray) -> None:
            ahead = tool_reach_along(pose, width, self.tool, direction) - limit
            if ahead > 1e-9:
                raise SafetyViolation(
                    f"the tool would come {ahead * 1e3:.1f} mm nearer the touched surface"
                )

        return self.line_or_joints(
            pose_world_tcp,
            touch.pose_world_tcp_start,
            joints_rad,
            Obstacles.none(),
            speed_m_s=self.limits.max_tcp_speed_m_s,
            label="retract",
            exempt_parts=APPROACH_EXEMPT_PARTS,
            near_parts=APPROACH_NEAR_PARTS,
            joint_move_check=no_nearer,
        )

    def plan_touch(
        self,
        pose_world_tcp: FloatArray,
        joints_rad: FloatArray,
        target_world: ArrayLike,
        direction_world: ArrayLike,
        obstacles: Obstacles,
        *,
        came_from: Sequence[FloatArray] = (),
        rolls_rad: Sequence[float] = TOUCH_ROLLS_RAD,
    ) -> TouchPlan:
        """A touch's transit (``plan_transit``) and approach from the current flange pose and
        joints, at the first roll of ``rolls_rad`` whose transit, approach and retract (the
        approach line reversed) are all accepted. SafetyViolation with the first roll's
        refusal when every roll is refused."""
        refusals: list[SafetyViolation] = []
        for roll in rolls_rad:
            try:
                touch = self._clear_start(
                    target_world, direction_world, roll, joints_rad, obstacles
                )
                # Cheap first: only a singularity depends on the joints the transit ends with.
                self._approach_and_retract(touch, joints_rad, obstacles)
            except SingularityViolation:
                pass
            except SafetyViolation as violation:
                refusals.append(violation)
                continue
            try:
                transit = self.plan_transit(
                    pose_world_tcp, joints_rad, touch, obstacles, came_from=came_from
                )
                joints = transit[-1].joints_rad if transit else joints_rad
                approach = self._approach_and_retract(touch, joints, obstacles)
            except SafetyViolation as violation:
                refusals.append(violation)
                continue
            return TouchPlan(touch, transit, approach, float(roll))
        raise _refused_at_every_roll(refusals, rolls_rad)

    def seconds_to_touch(
        self,
        pose_world_tcp: FloatArray,
        joints_rad: FloatArray,
        obstacles: Obstacles,
        came_from: Sequence[FloatArray],
        target_world: ArrayLike,
        direction_world: ArrayLike,
    ) -> float | None:
        """The robot time (``touch_seconds``) of the touch ``plan_touch`` plans from the arm's
        pose and joints (reached through ``came_from``), or None when the planner refuses it."""
        try:
            plan = self.plan_touch(
                pose_world_tcp,
                joints_rad,
                target_world,
                direction_world,
                obstacles,
                came_from=came_from,
            )
        except SafetyViolation:
            return None
        return self.touch_seconds(plan, pose_world_tcp, joints_rad)

    def touch_seconds(
        self, plan: TouchPlan, pose_world_tcp: FloatArray, joints_rad: FloatArray
    ) -> float:
        """The robot time a planned touch takes from the arm's pose and joints, at the planned
        speeds without acceleration ramps: the transit, the approach, the fingers opening the
        pad across the stand-off onto the surface and back (the pad moves at half the finger
        speed), and the retract along the approach line at the TCP speed limit."""
        seconds, pose, joints = 0.0, pose_world_tcp, joints_rad
        for move in (*plan.transit, plan.approach):
            seconds += duration_s(pose, joints, move)
            pose, joints = move.pose_world_tcp, move.joints_rad
        press_s = 2.0 * self.motion.standoff_m / (0.5 * self.motion.finger_speed_m_s)
        line_m = float(np.linalg.norm(plan.touch.pad_start_world - plan.touch.target_world))
        return seconds + press_s + line_m / self.limits.max_tcp_speed_m_s

    def check_touch(
        self,
        target_world: ArrayLike,
        direction_world: ArrayLike,
        joints_near_rad: FloatArray,
        obstacles: Obstacles,
        *,
        rolls_rad: Sequence[float] = TOUCH_ROLLS_RAD,
    ) -> float:
        """The cheap check of a touch before choosing it: the first roll of ``rolls_rad`` whose
        approach (from the approach start's joints nearest ``joints_near_rad``) and retract
        are accepted; the transit is not planned. SafetyViolation with the first roll's
        refusal when every roll is refused."""
        refusals: list[SafetyViolation] = []
        for roll in rolls_rad:
            try:
                touch = self._clear_start(
                    target_world, direction_world, roll, joints_near_rad, obstacles
                )
                self._approach_and_retract(touch, joints_near_rad, obstacles)
            except SafetyViolation as violation:
                refusals.append(violation)
                continue
            return float(roll)
        raise _refused_at_every_roll(refusals, rolls_rad)

    def _clear_start(
        self,
        target_world: ArrayLike,
        direction_world: ArrayLike,
        roll_rad: float,
        joints_near_rad: FloatArray,
        obstacles: Obstacles,
    ) -> TouchGeometry:
        """The touch geometry at the configured approach distance or, when its start is not
        clear of where the object may be, the nearest of ``APPROACH_EXTENSIONS_M`` further back
        whose start is: the approach then crosses that region in its force-checked steps."""
        refusal: SafetyViolation | None = None
        for extension_m in APPROACH_EXTENSIONS_M:
            touch = self.touch_geometry(
                target_world,
                direction_world,
                roll_rad,
                self.motion.approach_distance_m + extension_m,
            )
            try:
                check_pose(
                    touch.pose_world_tcp_start,
                    self.motion.touch_width_m,
                    tool=self.tool,
                    obstacles=obstacles,
                    limits=self.limits,
                    pose_world_base=self.pose_world_base,
                    joints_near_rad=joints_near_rad,
                )
                return touch
            except SafetyViolation as violation:
                refusal = refusal or violation
        assert refusal is not None
        raise refusal

    def _approach_and_retract(
        self, touch: TouchGeometry, joints_near_rad: FloatArray, obstacles: Obstacles
    ) -> Waypoint:
        """The approach from the approach start's joints nearest those given, once its retract
        from the stand-off is accepted too."""
        joints = check_reachable(touch.pose_world_tcp_start, self.pose_world_base, joints_near_rad)
        approach = self.plan_approach(touch, joints, obstacles)
        self.plan_retract(touch, touch.pose_world_tcp_standoff, approach.joints_rad)
        return approach

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
        angle between here and the target is small and the line is clear, else a detour (a line
        of either that passes too near a singularity is a joint move to its end instead).
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
                    self.line_or_joints(
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

        return waypoints + first_allowed(partial(via, b) for b in DETOUR_BACK_OFFS_M)

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

        return first_allowed(partial(via, b) for b in DETOUR_BACK_OFFS_M)

    def plan_retreat(
        self,
        pose_world_tcp: FloatArray,
        joints_rad: FloatArray,
        *,
        back_to_world_tcp: FloatArray | None,
        back_to_joints_rad: FloatArray | None = None,
    ) -> list[Waypoint]:
        """Where the arm goes after a fault, an abort or at the end of a session: back to where
        the interrupted motion started (the way it came, known to be clear) or, with no motion
        interrupted (None), nowhere: the arm stays. Never to a pose relative to where the arm
        is, so repeated faults cannot walk it away step by step. Then ``plan_lift``. An
        interrupted joint move gives its start joints, ``back_to_joints_rad``: the way back is
        then a joint move to them, the same joint path reversed."""
        if back_to_world_tcp is None or np.allclose(back_to_world_tcp, pose_world_tcp):
            return []
        # Retracing: the shape estimate may be wrong right here, the table is not.
        if back_to_joints_rad is not None:
            return [self.joint_move(joints_rad, back_to_joints_rad, Obstacles.none(), "retreat")]
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
        it: a lift from a pose inside that margin keeps the margin from the estimate itself and
        from the measured bound (which only touches have changed since: the arm was clear of
        it), else the arm could never leave."""
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
            return Obstacles(obstacles.occupied_points_world, bound=obstacles.measured_bound)
        return obstacles

    def _estimate_top_m(self, obstacles: Obstacles) -> float:
        points = obstacles.keep_out
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


def _refused_at_every_roll(
    refusals: Sequence[SafetyViolation], rolls_rad: Sequence[float]
) -> SafetyViolation:
    """The first (preferred) roll's refusal, saying that the other rolls were refused too."""
    if not refusals:
        raise ValueError("no rolls to try")
    others = ", ".join(f"{np.degrees(roll):+.0f}" for roll in rolls_rad[1:])
    tried = f" (rolled {others} degrees about the approach: refused too)" if others else ""
    return type(refusals[0])(f"{refusals[0]}{tried}")
