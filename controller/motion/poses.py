"""Tool poses for touches and the arm's home: where the pad faces a surface, the flange pose
that puts it there, the rolls a touch tries, and whether the arm is at a pose."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from drivers.config import ArmConfig
from drivers.tool import ToolModel
from drivers.ur5.kinematics import forward_kinematics
from models.geometry import (
    frame_from_z_axis,
    invert_transform,
    make_transform,
    rotation_angle_between,
    ur_pose_to_matrix,
)

FloatArray = NDArray[np.float64]

AT_POSE_TOLERANCE_M = 0.001
AT_POSE_TOLERANCE_RAD = 0.01
"""The arm counts as at a pose (home) this near it: well above the arm's repeatability, well
below anything that changes what the camera sees or where a path starts."""
TOUCH_ROLLS_RAD = tuple(np.radians(d) for d in (0.0, 30.0, -30.0, 60.0, -60.0))
"""Rolls of the tool about the approach line a touch tries, preferred first: rolled, the wrist
is away from a singularity the unrolled tool meets. Never a half-turn: the gripper body would
then hang below the pad, toward the table."""


def rolls_preferring(roll_rad: float) -> tuple[float, ...]:
    """``TOUCH_ROLLS_RAD`` with ``roll_rad`` (a target's preferred roll) tried first."""
    return (roll_rad, *(r for r in TOUCH_ROLLS_RAD if abs(r - roll_rad) > 1e-9))


def pad_pose_facing(
    point_world: ArrayLike, normal_world: ArrayLike, standoff_m: float, roll_rad: float = 0.0
) -> FloatArray:
    """Pad pose with the gel facing a surface point from ``standoff_m`` along its normal.

    The pad's +z (gel normal) points against the surface normal. Its +x (along the finger,
    toward the tip) points as far down as the surface allows, so that on a side touch the
    gripper body stays above the pad, and on a top touch the fingers lie horizontal; then
    turned by ``roll_rad`` about the gel normal.
    """
    normal = np.asarray(normal_world, dtype=float)
    normal = normal / np.linalg.norm(normal)
    pad_z = -normal
    down = np.array([0.0, 0.0, -1.0])
    x_hint = down if abs(np.dot(down, pad_z)) < 0.95 else np.cross(pad_z, [0.0, 1.0, 0.0])
    rotation = frame_from_z_axis(pad_z, x_hint) @ Rotation.from_rotvec([0, 0, roll_rad]).as_matrix()
    return make_transform(rotation, np.asarray(point_world, dtype=float) + standoff_m * normal)


def tcp_pose_for_pad(pose_world_pad: FloatArray, tool: ToolModel, width_m: float) -> FloatArray:
    """Flange pose that puts the pad at ``pose_world_pad`` with the fingers open ``width_m``."""
    return pose_world_pad @ invert_transform(tool.pose_tcp_pad(width_m))


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
