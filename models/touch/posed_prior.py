"""The prior's signed distance and its pose on the table.

:class:`SignedDistanceGrid` is the distance to the prior's 0.5 surface (exact distances to the
marching-cubes surface near it, trilinear between voxel centres); :func:`fit_pose` moves the
prior's grid by a similarity (translation on the table, yaw, scale) so that the measured surface
lies on it and the free points outside. Both the fused shape (``models.touch.fused``) and the
global fit (``models.touch.global_fit``) start from them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import trimesh
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import distance_transform_edt, map_coordinates
from scipy.optimize import least_squares
from scipy.spatial import cKDTree
from skimage.measure import marching_cubes

from models.geometry import VoxelGrid, rotation_about_axis
from models.touch.observations import SurfaceObservations, thin_to_lattice

FloatArray = NDArray[np.float64]

_BAND_VOXELS = 3.0
"""Exact distances within this many voxels of the prior surface; a Euclidean distance
transform beyond (only the sign matters far from it)."""
_SAMPLES_PER_VOXEL_AREA = 25
"""Surface samples per voxel face area for the exact distances (0.2 voxel apart)."""


# --- the prior's signed distance ------------------------------------------------------------------


@dataclass(frozen=True)
class SignedDistanceGrid:
    """Signed distance to a probability grid's 0.5 surface, in voxels (> 0 outside), at the
    voxel centres of ``grid``; :meth:`__call__` interpolates trilinearly, in metres. Moving
    the grid (:func:`posed_grid`) moves and scales the shape with it."""

    grid: VoxelGrid
    values_voxels: NDArray[np.float32]

    @classmethod
    def from_probabilities(cls, probabilities: ArrayLike, grid: VoxelGrid) -> SignedDistanceGrid:
        volume = np.asarray(probabilities, dtype=np.float32)
        if volume.shape != (grid.resolution,) * 3:
            raise ValueError(f"volume {volume.shape} does not match the {grid.resolution}^3 grid")
        inside = volume >= 0.5
        if not inside.any() or inside.all():
            # Nothing (or everything) predicted: a distance that never crosses zero.
            sign = -1.0 if inside.all() else 1.0
            return cls(grid, np.full(volume.shape, sign * grid.resolution, np.float32))
        # Euclidean distance transform: voxel centre to the nearest centre on the other side,
        # minus half a voxel (the surface lies between them).
        outside_d = distance_transform_edt(~inside) - 0.5
        values = np.where(inside, -(_inside_distance(inside) - 0.5), outside_d)
        band = np.abs(values) <= _BAND_VOXELS
        vertices, faces, _, _ = marching_cubes(np.pad(volume, 1), 0.5)
        mesh = trimesh.Trimesh(vertices - 0.5, faces, process=False)  # voxel coordinates
        # Capped: a 26 cm object's surface is ~6,000 voxel faces; a noisy field's is far more.
        count = int(min(max(mesh.area * _SAMPLES_PER_VOXEL_AREA, 1000), 150_000))
        samples, _ = trimesh.sample.sample_surface(mesh, count, seed=0)
        samples = np.concatenate([samples, mesh.vertices])
        centres = np.argwhere(band) + 0.5
        # An unbalanced tree of uncompacted nodes: the same nearest samples, built and
        # queried in about half the time on these surface samples.
        tree = cKDTree(samples, balanced_tree=False, compact_nodes=False)
        distance, _ = tree.query(centres)
        values[band] = np.where(inside[band], -distance, distance)
        return cls(grid, values.astype(np.float32))

    def moved_to(self, grid: VoxelGrid) -> SignedDistanceGrid:
        """The same shape registered by another grid (a pose fit's)."""
        return replace(self, grid=grid)

    def at_voxel_centres(self, grid: VoxelGrid) -> FloatArray:
        """Signed distance (metres) at ``grid``'s voxel centres, (N, N, N). On this field's own
        grid these are its values, read instead of interpolated at every voxel centre."""
        if grid == self.grid:
            return self.values_voxels.astype(float) * self.grid.voxel_size_m
        return self(grid.voxel_centres_world())

    def __call__(self, points_world: ArrayLike) -> FloatArray:
        """Signed distance (metres) at world points (..., 3); outside the grid's box, plus the
        distance to the box."""
        points = np.asarray(points_world, dtype=float)
        voxel = self.grid.world_to_voxel(points.reshape(-1, 3))
        index = voxel - 0.5
        limit = self.grid.resolution - 1
        clamped = np.clip(index, 0.0, limit)
        values = map_coordinates(self.values_voxels, clamped.T, order=1, mode="nearest")
        # Beyond the grid's box nothing was predicted: empty, the distance growing from its faces.
        outside = np.linalg.norm(index - clamped, axis=1)
        values = np.where(outside > 0, np.maximum(values, 0.0) + outside, values)
        return (values * self.grid.voxel_size_m).reshape(points.shape[:-1])


def _inside_distance(inside: NDArray[np.bool_]) -> NDArray[np.float64]:
    """The Euclidean distance transform of ``inside`` (voxel centres to the nearest outside
    one), computed on the inside voxels' box grown by one voxel within the grid: the grown
    layers are outside, and an outside voxel beyond them is farther from every inside voxel than
    its clamp onto them. The same numbers as on the whole grid, on a fraction of it."""
    occupied = np.argwhere(inside)
    low = np.maximum(occupied.min(axis=0) - 1, 0)
    high = np.minimum(occupied.max(axis=0) + 2, inside.shape)
    box = tuple(slice(lo, hi) for lo, hi in zip(low, high, strict=True))
    distance = np.zeros(inside.shape)
    distance[box] = distance_transform_edt(inside[box])
    return distance


# --- pose fit -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PoseFitSettings:
    """The similarity fit's priors (standard deviations) and robust scale."""

    translation_std_m: float = 0.015
    yaw_std_deg: float = 15.0
    log_scale_std: float = 0.1
    residual_scale_m: float = 0.001
    """Soft-L1 scale: residuals beyond it count linearly (a wrong contact does not dominate)."""


@dataclass(frozen=True)
class Pose:
    """Translation on the table (x, y, metres), yaw about the vertical through the grid's
    object point (radians) and log scale about it: how the prior's shape is moved."""

    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0
    log_scale: float = 0.0

    def as_array(self) -> FloatArray:
        return np.array([self.x_m, self.y_m, self.yaw_rad, self.log_scale])

    def summary(self) -> str:
        return (
            f"x {1000 * self.x_m:+.1f} mm, y {1000 * self.y_m:+.1f} mm, "
            f"yaw {math.degrees(self.yaw_rad):+.1f} deg, scale {math.exp(self.log_scale):.3f}"
        )


def posed_grid(grid: VoxelGrid, pose: Pose) -> VoxelGrid:
    """``grid`` moved by ``pose``: scaled about and yawed around its object point (the bottom
    centre, on the table), then shifted on the table. The object stays on the table."""
    rotation = rotation_about_axis((0, 0, 1), pose.yaw_rad)
    axes = rotation @ np.asarray(grid.axes_world, dtype=float).T
    origin = np.asarray(grid.origin_world, dtype=float) + np.array([pose.x_m, pose.y_m, 0.0])
    return VoxelGrid(
        resolution=grid.resolution,
        extent_m=grid.extent_m * math.exp(pose.log_scale),
        origin_world=tuple(float(v) for v in origin),
        axes_world=tuple(tuple(float(v) for v in column) for column in axes.T),
    )


def _per_touch_weights(source: NDArray[np.int64]) -> FloatArray:
    """1 / sqrt(points of the same touch): every touch weighs the same, however large its patch."""
    _, inverse, counts = np.unique(source, return_inverse=True, return_counts=True)
    return 1.0 / np.sqrt(counts[inverse])


def fit_pose(
    prior: SignedDistanceGrid,
    base_grid: VoxelGrid,
    observations: SurfaceObservations,
    start: Pose = Pose(),
    settings: PoseFitSettings = PoseFitSettings(),
) -> Pose:
    """The pose of the prior's shape (``prior`` values on ``base_grid`` moved by it) that puts
    the measured surface on its surface and the free points outside, with Gaussian priors on
    the pose (robust least squares, scipy's trust region). No surface points: ``start``."""
    surface = observations.surface_points_world
    if len(surface) == 0:
        return start
    weights = _per_touch_weights(observations.surface_source)
    free = observations.free_points_world
    if len(free):
        free = free[thin_to_lattice(free, 0.004)]
    free_weight = 1.0 / math.sqrt(
        max(len(free) / max(len(np.unique(observations.surface_source)), 1), 1.0)
    )
    scale = settings.residual_scale_m
    priors = np.array(
        [
            settings.translation_std_m,
            settings.translation_std_m,
            math.radians(settings.yaw_std_deg),
            settings.log_scale_std,
        ]
    )

    def residuals(q: FloatArray) -> FloatArray:
        field = prior.moved_to(posed_grid(base_grid, Pose(*q)))
        on_surface = weights * field(surface) / scale
        outside = free_weight * np.minimum(field(free), 0.0) / scale if len(free) else []
        return np.concatenate([on_surface, outside, q / priors])

    result = least_squares(
        residuals, start.as_array(), loss="soft_l1", f_scale=1.0, x_scale=priors, max_nfev=60
    )
    return Pose(*(float(v) for v in result.x))
