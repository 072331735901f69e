"""Touch geometry: where the tool must be for the gel pad to face a surface point."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from drivers.tool import ToolModel
from models.geometry import frame_from_z_axis, invert_transform, make_transform


def pad_pose_facing(
    point_world: ArrayLike, normal_world: ArrayLike, standoff_m: float
) -> NDArray[np.float64]:
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


def tcp_pose_for_pad(
    pose_world_pad: NDArray[np.float64], tool: ToolModel, width_m: float
) -> NDArray[np.float64]:
    """Flange pose that puts the pad at ``pose_world_pad`` with the fingers open ``width_m``."""
    return pose_world_pad @ invert_transform(tool.pose_tcp_pad(width_m))
