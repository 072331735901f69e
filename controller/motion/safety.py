"""Safety checks every commanded motion passes: small pure functions, tested directly.

A check raises ``SafetyViolation`` (a ``MotionRejectedError``) naming the limit and the value, so
a rejected motion is an explainable error, not a fault: nothing moved.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from controller.config import LimitsConfig
from drivers.base import MotionRejectedError
from drivers.tool import ToolBox, ToolModel
from drivers.ur5.kinematics import inverse_kinematics
from models.geometry import invert_transform, transform_points
from models.object_bound import ObjectBound

if TYPE_CHECKING:
    from controller.perception.protocol import ShapeEstimate

NEAR_PARTS_CLEARANCE_FRACTION = 0.25
"""``near_parts`` keep this fraction of ``shape_clearance_m`` from where the object may be."""
PRISM_GROWTH_M = 0.004
"""The prism ahead of the gel's window is grown by this much (a voxel of the object bound): a
bound voxel whose centre lies just outside the window's footprint may hold surface inside it."""
POSSIBLE_OCCUPANCY = 0.1
"""Voxels above this probability are where the object may be: transits, and the tool parts that
do not lead into a touch, keep their clearance from them. The vision estimate (v > 0.5) is too
small in places, so a lower threshold is used (docs/controller.md)."""


HIDDEN = "where the object may be out of the camera's sight"


class SafetyViolation(MotionRejectedError):
    """A planned pose or command breaks a configured limit."""


@dataclass(frozen=True)
class Obstacles:
    """What the tool must keep clear of, in the world frame: the table top at z = 0, the current
    shape estimate as points (voxel centres, metres) at two levels of belief, and where the
    object may be whatever the estimate says (``bound``, built from measurements).

    - ``occupied_points_world``: the estimate itself (v > 0.5); the gel's window approaches it.
    - ``possible_points_world``: the estimate at a lower probability (the occupied points when
      not given); the parts behind the window keep a little clearance from it on an approach.
    - ``bound``: where the object may be (``models.object_bound``): every other part, and every
      part on a transit, keeps the full clearance from it. Without one the possible points
      stand in (tests, and the next session's way home before it has measured anything).
    """

    occupied_points_world: NDArray[np.float64]
    possible_points_world: NDArray[np.float64] | None = None
    bound: ObjectBound | None = None
    measured_bound: ObjectBound | None = None
    """The bound from measurements alone (without the estimate's additions): what a lift from
    a pose the estimate has since spread over still keeps clear of."""

    @classmethod
    def none(cls) -> Obstacles:
        return cls(np.zeros((0, 3)))

    @classmethod
    def of_estimate(
        cls,
        estimate: ShapeEstimate | None,
        bound: ObjectBound | None = None,
        measured_bound: ObjectBound | None = None,
    ) -> Obstacles:
        """A shape estimate as obstacles (none without an estimate), with the bounds given."""
        if estimate is None:
            return cls(np.zeros((0, 3)), bound=bound, measured_bound=measured_bound)
        return cls(
            estimate.occupied_points_world(),
            estimate.occupied_points_world(POSSIBLE_OCCUPANCY),
            bound,
            measured_bound,
        )

    @property
    def possible(self) -> NDArray[np.float64]:
        points = self.possible_points_world
        return self.occupied_points_world if points is None else points

    @property
    def keep_out(self) -> NDArray[np.float64]:
        """The points every part keeps the full clearance from: the bound's surface, or the
        possible points without a bound."""
        return self.possible if self.bound is None else self.bound.boundary_points_world

    @property
    def measured_surface(self) -> NDArray[np.float64]:
        """The object's surface as the camera measured it (none without a bound)."""
        return np.zeros((0, 3)) if self.bound is None else self.bound.surface_points_world

    @property
    def hidden(self) -> NDArray[np.float64]:
        """The surface of the bound's part the camera did not see (none without a bound)."""
        return np.zeros((0, 3)) if self.bound is None else self.bound.hidden_boundary_points_world

    def inside(self, point_world: NDArray[np.float64], *, hidden: bool = False) -> bool:
        """Whether a point lies inside the bound, or with ``hidden`` inside its hidden part
        (where no surface point is near to tell)."""
        if self.bound is None:
            return False
        return bool(self.bound.contains(point_world, hidden=hidden)[0])

    @cached_property
    def _trees(self) -> dict[str, cKDTree]:
        return {}

    def near(
        self, centre_world: NDArray[np.float64], radius_m: float, *, level: str = "keep_out"
    ) -> NDArray[np.float64]:
        """The points of a level ("occupied", "possible", "keep_out", "surface" or "hidden")
        within ``radius_m`` of a point (a cheap pre-filter)."""
        points = {
            "occupied": self.occupied_points_world,
            "possible": self.possible,
            "keep_out": self.keep_out,
            "surface": self.measured_surface,
            "hidden": self.hidden,
        }[level]
        if len(points) == 0:
            return points
        if level not in self._trees:
            self._trees[level] = cKDTree(points)
        return points[self._trees[level].query_ball_point(centre_world, radius_m)]


def check_speed(speed_m_s: float, limit_m_s: float, *, what: str = "TCP speed") -> None:
    if not 0.0 < speed_m_s <= limit_m_s:
        raise SafetyViolation(f"{what} {speed_m_s} m/s outside (0, {limit_m_s}] m/s")


def check_force(force_n: float, limits: LimitsConfig) -> None:
    """Raise when a measured force means a collision rather than a touch."""
    if force_n > limits.max_force_n:
        raise SafetyViolation(f"force {force_n:.1f} N over the limit {limits.max_force_n} N")


def check_workspace(pose_world_tcp: NDArray[np.float64], limits: LimitsConfig) -> None:
    """The TCP (flange) position must lie in the configured workspace box."""
    position = pose_world_tcp[:3, 3]
    low, high = np.asarray(limits.workspace_min_world), np.asarray(limits.workspace_max_world)
    if np.any(position < low) or np.any(position > high):
        raise SafetyViolation(
            f"TCP {np.round(position, 3).tolist()} m outside the workspace box "
            f"{list(limits.workspace_min_world)}..{list(limits.workspace_max_world)}"
        )


def check_reachable(
    pose_world_tcp: NDArray[np.float64],
    pose_world_base: NDArray[np.float64],
    joints_near_rad: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Joint solution (rad) nearest the given joints, or SafetyViolation when out of reach."""
    joints = inverse_kinematics(invert_transform(pose_world_base) @ pose_world_tcp, joints_near_rad)
    if joints is None:
        position = np.round(pose_world_tcp[:3, 3], 3).tolist()
        raise SafetyViolation(f"pose at {position} m is out of the arm's reach (no IK solution)")
    return joints


def check_clearance(
    pose_world_tcp: NDArray[np.float64],
    width_m: float,
    tool: ToolModel,
    obstacles: Obstacles,
    limits: LimitsConfig,
    *,
    exempt_parts: Sequence[str] = (),
    near_parts: Sequence[str] = (),
) -> None:
    """Every rigid tool part keeps ``table_clearance_m`` above the table and
    ``shape_clearance_m`` from where the object may be (``Obstacles.keep_out``, and not inside
    the bound), except on the last stretch of an approach, where the sensor must come close to
    the surface it is about to touch: ``near_parts`` keep a quarter of the margin from the
    estimate's possible points, from the measured surface and from the bound's hidden part
    (where the object may be out of the camera's sight; their centres never inside it)
    outside the prism ahead of the ``exempt_parts``, which (the part carrying the gel) may
    come up to the estimate itself."""
    boxes = tool.rigid_boxes(width_m)
    leading = [
        (pose_world_tcp @ box.pose_tcp_box, box.half_extents_m)
        for box in boxes
        if box.name in exempt_parts
    ]
    for box in boxes:
        pose_world_box = pose_world_tcp @ box.pose_tcp_box
        lowest_m = box.lowest_world_z_m(pose_world_tcp)
        if lowest_m < limits.table_clearance_m:
            raise SafetyViolation(
                f"{box.name} would be {lowest_m * 1e3:.1f} mm above the table, "
                f"clearance is {limits.table_clearance_m * 1e3:.0f} mm"
            )
        centre = pose_world_box[:3, 3]
        if box.name in exempt_parts:
            checks = [("occupied", 0.0, "the shape estimate")]
        elif box.name in near_parts:
            # Behind the gel, no force reading guards these: they keep a little clearance from
            # the estimate, from the surface the camera measured and from where the object may
            # be out of the camera's sight (an under-estimated limb), except ahead of the gel's
            # window, whose contact the approach feels first. The hidden part's voxel centres
            # are half a voxel diagonal further from the object than its surface may be.
            clearance = NEAR_PARTS_CLEARANCE_FRACTION * limits.shape_clearance_m
            checks = [
                ("possible", clearance, "the shape estimate"),
                ("surface", clearance, "the measured surface beside the gel"),
                ("hidden", clearance + _half_voxel_diagonal(obstacles), HIDDEN),
            ]
            if obstacles.inside(centre, hidden=True):
                raise SafetyViolation(f"{box.name} would be inside {HIDDEN}")
        else:
            where = "where the object may be"
            checks = [("keep_out", limits.shape_clearance_m, where)]
            if obstacles.inside(centre):
                raise SafetyViolation(f"{box.name} would be inside {where}")
        for level, clearance, where in checks:
            reach = float(np.linalg.norm(box.half_extents_m)) + clearance
            nearby = obstacles.near(centre, reach, level=level)
            if level in ("surface", "hidden"):
                nearby = _not_ahead_of(nearby, leading)
            if _box_near_points(pose_world_box, box, nearby, clearance):
                raise SafetyViolation(
                    f"{box.name} would come within {clearance * 1e3:.0f} mm of {where}"
                )


def _half_voxel_diagonal(obstacles: Obstacles) -> float:
    return (
        0.0 if obstacles.bound is None else 0.5 * np.sqrt(3.0) * obstacles.bound.grid.voxel_size_m
    )


def _not_ahead_of(
    points_world: NDArray[np.float64],
    leading: list[tuple[NDArray[np.float64], NDArray[np.float64]]],
) -> NDArray[np.float64]:
    """The points not in the prism a leading part (pose, half extents: the gel's window)
    sweeps ahead of itself along the tool's +x (the pad's normal), grown by
    :data:`PRISM_GROWTH_M`."""
    if len(points_world) == 0 or not leading:
        return points_world
    keep = np.ones(len(points_world), dtype=bool)
    grow = PRISM_GROWTH_M
    for pose_world_box, half in leading:
        local = transform_points(invert_transform(pose_world_box), points_world)
        ahead = (
            (local[:, 0] >= -half[0])
            & (np.abs(local[:, 1]) <= half[1] + grow)
            & (np.abs(local[:, 2]) <= half[2] + grow)
        )
        keep &= ~ahead
    return points_world[keep]


def check_pose(
    pose_world_tcp: NDArray[np.float64],
    width_m: float,
    *,
    tool: ToolModel,
    obstacles: Obstacles,
    limits: LimitsConfig,
    pose_world_base: NDArray[np.float64],
    joints_near_rad: NDArray[np.float64],
    exempt_parts: Sequence[str] = (),
    near_parts: Sequence[str] = (),
) -> NDArray[np.float64]:
    """All pose checks (workspace, reach, clearance); returns the joint solution."""
    check_workspace(pose_world_tcp, limits)
    joints = check_reachable(pose_world_tcp, pose_world_base, joints_near_rad)
    check_clearance(
        pose_world_tcp,
        width_m,
        tool,
        obstacles,
        limits,
        exempt_parts=exempt_parts,
        near_parts=near_parts,
    )
    return joints


def _box_near_points(
    pose_world_box: NDArray[np.float64],
    box: ToolBox,
    points_world: NDArray[np.float64],
    clearance_m: float,
) -> bool:
    if len(points_world) == 0:
        return False
    points_box = transform_points(invert_transform(pose_world_box), points_world)
    outside = np.maximum(np.abs(points_box) - box.half_extents_m, 0.0)
    return bool(np.any(np.linalg.norm(outside, axis=1) <= clearance_m))
