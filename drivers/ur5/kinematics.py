"""UR5 kinematics (analytic, ur-analytic-ik) shared by the simulated arm and the planner.

Frames: the UR base frame as the controller reports it and flange = tool0.
"""

from __future__ import annotations

import numpy as np
import ur_analytic_ik
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def forward_kinematics(joints_rad: ArrayLike) -> FloatArray:
    """UR5 flange pose in the base frame (4x4) for six joint angles (rad)."""
    return np.asarray(ur_analytic_ik.ur5.forward_kinematics(*np.asarray(joints_rad, dtype=float)))


def inverse_kinematics(
    pose_base_flange: ArrayLike, joints_near_rad: ArrayLike
) -> FloatArray | None:
    """The UR5 joint solution (rad) for a flange pose closest to ``joints_near_rad``, each
    joint taken as the turn nearest to it within the +-2 pi limits; None when unreachable."""
    pose = np.ascontiguousarray(pose_base_flange, dtype=float)
    near = np.asarray(joints_near_rad, dtype=float)
    solutions = ur_analytic_ik.ur5.inverse_kinematics_closest(pose, *near)
    finite = [np.asarray(q) for q in solutions if np.all(np.isfinite(q))]
    return finite[0] if finite else None
