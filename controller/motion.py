"""Motion planning for touches, as in the paper, with every pose checked by ``controller.safety``.

A touch: the arm brings the pad to ``approach_distance_m`` from the target on its approach line
(pad facing the surface), approaches along the line to ``standoff_m`` before the predicted
surface, then the fingers open slowly so the pad makes the final, force-limited contact. Between
touches the arm moves straight when the targets are close around the object's vertical axis and
otherwise detours through a safe height above the shape estimate. Straight-line motions are
checked at poses ``path_check_step_m`` apart (workspace, reach, joint continuity, clearance).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation, Slerp

from controller.config import LimitsConfig, MotionConfig
from controller.safety import Obstacles, SafetyViolation, check_pose, check_speed
from drivers.tool import ToolModel
from models.geometry import (
    frame_from_z_axis,
    invert_transform,
    make_transform,
    radial_angle_about_vertical,
    rotation_angle_between,
)

FloatArray = NDArray[np.float64]

APPROACH_EXEMPT_PARTS = ("gelsight_window", "gelsight_housing", "finger_sensor_side")
"""Parts allowed to come close to the estimate on the approach: they lead into the contact."""
TOOL_REACH_M = 0.17
"""Flange to fingertip: a radian of tool rotation sweeps the tip about this far."""
MIN_LINE_SPEED_M_S = 0.002
"""A line whose joint rates would force the TCP slower than this passes a singularity."""


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
        """The slow straight approach from the start to the stand-off."""
        return self.line(
            touch.pose_world_tcp_start,
            touch.pose_world_tcp_standoff,
            joints_rad,
            obstacles,
            speed_m_s=self.limits.approach_speed_m_s,
            label="approach",
            exempt_parts=APPROACH_EXEMPT_PARTS,
        )

    def plan_retract(
        self, touch: TouchGeometry, joints_rad: FloatArray, obstacles: Obstacles
    ) -> Waypoint:
        """Back out along the approach line from the stand-off to the approach start."""
        return self.line(
            touch.pose_world_tcp_standoff,
            touch.pose_world_tcp_start,
            joints_rad,
            obstacles,
            speed_m_s=self.limits.max_tcp_speed_m_s,
            label="retract",
            exempt_parts=APPROACH_EXEMPT_PARTS,
        )

    def plan_transit(
        self,
        pose_world_tcp: FloatArray,
        joints_rad: FloatArray,
        touch: TouchGeometry,
        obstacles: Obstacles,
    ) -> list[Waypoint]:
        """From the current flange pose to the touch's approach start: straight when the radial
        angle between here and the target is small and the line is clear, else a detour."""
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
        return self.plan_detour(pose_world_tcp, joints_rad, goal, obstacles)

    def plan_detour(
        self,
        pose_world_tcp: FloatArray,
        joints_rad: FloatArray,
        goal_world_tcp: FloatArray,
        obstacles: Obstacles,
    ) -> list[Waypoint]:
        """Up to the safe height, across above the object, down to the goal."""
        top_m = self._estimate_top_m(obstacles)
        safe_z = max(
            pose_world_tcp[2, 3],
            self._flange_height_clearing(pose_world_tcp, top_m),
            self._flange_height_clearing(goal_world_tcp, top_m),
        )
        lift = pose_world_tcp.copy()
        lift[2, 3] = safe_z
        above_goal = goal_world_tcp.copy()
        above_goal[2, 3] = safe_z
        speed = self.limits.max_tcp_speed_m_s
        waypoints = []
        joints = joints_rad
        start = pose_world_tcp
        for pose, label in ((lift, "lift"), (above_goal, "across"), (goal_world_tcp, "descend")):
            if np.allclose(pose, start):
                continue
            waypoint = self.line(start, pose, joints, obstacles, speed_m_s=speed, label=label)
            waypoints.append(waypoint)
            joints = waypoint.joints_rad
            start = pose
        return waypoints

    def plan_retreat(
        self,
        pose_world_tcp: FloatArray,
        joints_rad: FloatArray,
        obstacles: Obstacles,
        *,
        back_to_world_tcp: FloatArray | None = None,
    ) -> list[Waypoint]:
        """Where the arm goes after a fault, an abort or at the end of a session: back to where
        the interrupted motion started (the way it came, known to be clear) or, without one,
        back along the tool's -x (away from what the pad faces); then up to the safe height."""
        if back_to_world_tcp is None:
            back_to_world_tcp = pose_world_tcp.copy()
            back_to_world_tcp[:3, 3] -= self.motion.approach_distance_m * pose_world_tcp[:3, 0]
        speed = self.limits.max_tcp_speed_m_s
        waypoints = []
        joints = joints_rad
        back = back_to_world_tcp
        if not np.allclose(back, pose_world_tcp):
            # Retracing: the shape estimate may be wrong right here, the table is not.
            waypoint = self.line(
                pose_world_tcp, back, joints, Obstacles.none(), speed_m_s=speed, label="retreat"
            )
            waypoints.append(waypoint)
            joints = waypoint.joints_rad
        up = back.copy()
        up[2, 3] = max(
            back[2, 3], self._flange_height_clearing(back, self._estimate_top_m(obstacles))
        )
        if not np.allclose(up, back):
            waypoints.append(self.line(back, up, joints, obstacles, speed_m_s=speed, label="lift"))
        return waypoints

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
    ) -> Waypoint:
        """A checked straight TCP line (slerped orientation, as moveL moves): every pose
        ``path_check_step_m`` apart passes the safety checks, and the speed is lowered where the
        joints would otherwise turn faster than ``max_joint_speed_rad_s``. SafetyViolation on
        the first failing pose, or when the line passes so near a singularity that the TCP
        would have to crawl."""
        check_speed(speed_m_s, self.limits.max_tcp_speed_m_s)
        distance = np.linalg.norm(end_world_tcp[:3, 3] - start_world_tcp[:3, 3])
        angle = rotation_angle_between(start_world_tcp[:3, :3], end_world_tcp[:3, :3])
        length = max(distance, TOOL_REACH_M * angle)
        steps = max(1, int(np.ceil(length / self.motion.path_check_step_m)))
        rotations = Rotation.from_matrix(np.stack([start_world_tcp[:3, :3], end_world_tcp[:3, :3]]))
        slerp = Slerp([0.0, 1.0], rotations)
        joints = np.asarray(joints_rad, dtype=float)
        joint_rad_per_m = 0.0
        pose = start_world_tcp
        for fraction in np.linspace(0.0, 1.0, steps + 1)[1:]:
            pose = make_transform(
                slerp(fraction).as_matrix(),
                start_world_tcp[:3, 3] + fraction * (end_world_tcp[:3, 3] - start_world_tcp[:3, 3]),
            )
            next_joints = check_pose(
                pose,
                self.motion.touch_width_m,
                tool=self.tool,
                obstacles=obstacles,
                limits=self.limits,
                pose_world_base=self.pose_world_base,
                joints_near_rad=joints,
                exempt_parts=exempt_parts,
            )
            if length > 0:
                step_rad = float(np.max(np.abs(next_joints - joints)))
                joint_rad_per_m = max(joint_rad_per_m, step_rad / (length / steps))
            joints = next_joints
        if joint_rad_per_m > 0:
            speed_m_s = min(speed_m_s, self.limits.max_joint_speed_rad_s / joint_rad_per_m)
        if speed_m_s < MIN_LINE_SPEED_M_S:
            raise SafetyViolation(
                f"line to {np.round(end_world_tcp[:3, 3], 3).tolist()} m passes near a "
                "singularity (joints would turn too fast)"
            )
        return Waypoint(end_world_tcp, joints, speed_m_s, label)

    def _estimate_top_m(self, obstacles: Obstacles) -> float:
        points = obstacles.occupied_points_world
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
