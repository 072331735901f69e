"""What the touches measured of the surface, as geometry: surface points with outward normals
and points known to be free space, in the world frame (metres).

A contact's height map gives points on the object at the sensor's precision (sub-millimetre);
the gel's uncontacted area, the approach sweep and missed strokes give free space. These are
the observations the fused shape (``models.touch.fused``) passes through and keeps outside of.
They do not depend on any voxel grid. Saved per session as ``observations.npz``.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from models.files import write_atomically
from models.touch.constraints import TouchResult

FloatArray = NDArray[np.float64]

SURFACE_SPACING_M = 0.001
"""Contact points are thinned to one per cell of this lattice (the height map has ~0.03 mm
pixels; the surface between samples 1 mm apart is smooth at the sensor's precision)."""
FREE_SPACING_M = 0.002
"""Free space is sampled along the swept rays and thinned to one point per cell of this lattice."""
NORMAL_RADIUS_M = 0.0015
"""Contact points within this radius fit a point's tangent plane."""
FREE_MARGIN_M = 0.001
"""Free points stop this far in front of a contact along its ray (the gel's own thickness)."""


class ObservationsError(ValueError):
    """An observations file is missing, corrupt or incomplete."""


def thin_to_lattice(points: FloatArray, spacing_m: float) -> NDArray[np.int64]:
    """Indices of one point per occupied cell of a ``spacing_m`` lattice (the first one)."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    cells = np.floor(points / spacing_m).astype(np.int64)
    cells -= cells.min(axis=0)
    # One integer per cell (a row-major index of the cells' box): np.unique on rows sorts
    # them as records, several times slower. Its stable sort keeps each cell's first point.
    key = np.ravel_multi_index(cells.T, tuple(cells.max(axis=0) + 1))
    _, keep = np.unique(key, return_index=True)
    return np.sort(keep)


def _normals(
    points: FloatArray, all_points: FloatArray, approach_direction: FloatArray
) -> FloatArray:
    """Outward unit normals at ``points`` from the tangent plane of the contact points around
    each (principal axes); against the approach where the patch is too small or too thin to
    fit a plane (an edge or a single point)."""
    normals = np.tile(-approach_direction, (len(points), 1))
    if len(all_points) < 3:
        return normals
    tree = cKDTree(all_points)
    for index, neighbours in enumerate(tree.query_ball_point(points, NORMAL_RADIUS_M)):
        if len(neighbours) < 6:
            continue
        local = all_points[neighbours] - all_points[neighbours].mean(axis=0)
        values, vectors = np.linalg.eigh(local.T @ local)
        if values[1] < 1e-3 * values[2]:  # a line of contact (an edge): no plane
            continue
        normal = vectors[:, 0]
        normals[index] = normal if normal @ approach_direction < 0 else -normal
    return normals


@dataclass(frozen=True)
class SurfaceObservations:
    """Measured surface points (with outward unit normals) and free-space points, world metres.

    ``surface_source[i]`` numbers the measurement a surface point came from (the touch index,
    -1 for the camera), so an observer can tell touches apart.
    """

    surface_points_world: FloatArray
    surface_normals_world: FloatArray
    free_points_world: FloatArray
    surface_source: NDArray[np.int64]

    def __post_init__(self) -> None:
        surface = self.surface_points_world
        if surface.shape != self.surface_normals_world.shape or surface.shape[1:] != (3,):
            raise ValueError("surface points and normals must be matching (N, 3) arrays")
        if self.free_points_world.shape[1:] != (3,) or len(self.surface_source) != len(surface):
            raise ValueError("free points must be (M, 3), surface_source one per surface point")
        for name in ("surface_points_world", "surface_normals_world", "free_points_world"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise ValueError(f"{name} holds NaN or infinite values")

    @classmethod
    def none(cls) -> SurfaceObservations:
        empty = np.zeros((0, 3))
        return cls(empty, empty, empty, np.zeros(0, np.int64))

    @property
    def is_empty(self) -> bool:
        return len(self.surface_points_world) == 0 and len(self.free_points_world) == 0

    @classmethod
    def from_touch(cls, touch: TouchResult, source: int = 0) -> SurfaceObservations:
        """A touch's contact points (thinned, with normals from the patch) and the free space its
        rays swept: a free ray all the way, a contact ray up to ``FREE_MARGIN_M`` before its
        contact."""
        direction = np.asarray(touch.approach_direction_world, dtype=float)
        contacts = touch.contact_points_world
        keep = thin_to_lattice(contacts, SURFACE_SPACING_M)
        surface = contacts[keep]
        normals = _normals(surface, contacts, direction)
        starts, ends = touch.ray_starts_world, touch.ray_ends_world.copy()
        ends[touch.ray_hit] -= FREE_MARGIN_M * direction
        free = _points_along(starts, ends, FREE_SPACING_M)
        free = free[thin_to_lattice(free, FREE_SPACING_M)]
        return cls(surface, normals, free, np.full(len(surface), source, np.int64))

    @classmethod
    def merged(cls, parts: Iterable[SurfaceObservations]) -> SurfaceObservations:
        parts = list(parts)
        if not parts:
            return cls.none()
        return cls(
            np.concatenate([p.surface_points_world for p in parts]),
            np.concatenate([p.surface_normals_world for p in parts]),
            np.concatenate([p.free_points_world for p in parts]),
            np.concatenate([p.surface_source for p in parts]),
        )

    def save(self, path: str | Path) -> Path:
        """Write ``observations.npz`` (float32 metres; see docs/touch.md), atomically."""
        arrays = {
            "surface_points_world_m": self.surface_points_world.astype(np.float32),
            "surface_normals_world": self.surface_normals_world.astype(np.float32),
            "free_points_world_m": self.free_points_world.astype(np.float32),
            "surface_source": self.surface_source.astype(np.int32),
        }
        return write_atomically(Path(path), lambda temp: np.savez_compressed(temp, **arrays))

    @classmethod
    def load(cls, path: str | Path) -> SurfaceObservations:
        """Read a file written by :meth:`save`; a corrupt or incomplete one is refused."""
        try:
            with np.load(path) as data:
                return cls(
                    data["surface_points_world_m"].astype(np.float64).reshape(-1, 3),
                    data["surface_normals_world"].astype(np.float64).reshape(-1, 3),
                    data["free_points_world_m"].astype(np.float64).reshape(-1, 3),
                    data["surface_source"].astype(np.int64).reshape(-1),
                )
        except (OSError, KeyError, ValueError, EOFError) as error:
            raise ObservationsError(f"{path}: not a valid observations file ({error})") from error


CAMERA_SPACING_M = 0.006
"""Depth points are thinned to this lattice: the camera's noise (millimetres) is far coarser
than the touches', and the process's cost is cubic in its points."""
MAX_CAMERA_POINTS = 500
"""... and to a coarser one where a large object would leave more (a 30 cm object's visible side
holds ~1,500 points at 6 mm: seconds of fitting; the field varies over the kernel's 35 mm)."""


def thin_to_count(points: FloatArray, spacing_m: float, count: int) -> NDArray[np.int64]:
    """:func:`thin_to_lattice` at ``spacing_m``, coarsened until at most about ``count`` remain."""
    keep = thin_to_lattice(points, spacing_m)
    while len(keep) > count:
        spacing_m *= 1.25
        keep = thin_to_lattice(points, spacing_m)
    return keep


CAMERA_NORMAL_RADIUS_M = 0.008
CAMERA_FREE_OFFSETS_M = (0.005, 0.015)
"""Free points in front of each depth point, toward the camera (beyond the depth noise)."""


def camera_observations(
    points_world: ArrayLike, camera_position_world: ArrayLike
) -> SurfaceObservations:
    """The object's depth points (world, from ``object_bound.object_depth_points``) as
    observations of source -1: thinned surface points with normals toward the camera's side,
    and free space in front of them along the camera's rays."""
    points = np.asarray(points_world, dtype=float).reshape(-1, 3)
    if len(points) == 0:
        return SurfaceObservations.none()
    camera = np.asarray(camera_position_world, dtype=float).reshape(3)
    surface = points[thin_to_count(points, CAMERA_SPACING_M, MAX_CAMERA_POINTS)]
    to_camera = camera - surface
    to_camera /= np.linalg.norm(to_camera, axis=1, keepdims=True)
    normals = to_camera.copy()
    tree = cKDTree(points)
    for index, neighbours in enumerate(tree.query_ball_point(surface, CAMERA_NORMAL_RADIUS_M)):
        if len(neighbours) >= 6:
            local = points[neighbours] - points[neighbours].mean(axis=0)
            normal = np.linalg.eigh(local.T @ local)[1][:, 0]
            normals[index] = normal if normal @ to_camera[index] > 0 else -normal
    free = np.concatenate([surface + offset * to_camera for offset in CAMERA_FREE_OFFSETS_M])
    return SurfaceObservations(surface, normals, free, np.full(len(surface), -1, np.int64))


def observations_of(touches: Iterable[TouchResult]) -> SurfaceObservations:
    """The observations of touches in order (``surface_source`` = their index)."""
    return SurfaceObservations.merged(
        SurfaceObservations.from_touch(touch, index) for index, touch in enumerate(touches)
    )


def _points_along(starts: ArrayLike, ends: ArrayLike, spacing_m: float) -> FloatArray:
    """Points every ``spacing_m`` (at most) along each segment start -> end, ends included."""
    starts = np.asarray(starts, dtype=float).reshape(-1, 3)
    ends = np.asarray(ends, dtype=float).reshape(-1, 3)
    if len(starts) == 0:
        return np.zeros((0, 3))
    lengths = np.linalg.norm(ends - starts, axis=1)
    counts = np.maximum(np.ceil(lengths / spacing_m).astype(int), 0) + 1
    segment = np.repeat(np.arange(len(starts)), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    fraction = offsets / np.maximum(counts[segment] - 1, 1)
    return starts[segment] + fraction[:, None] * (ends[segment] - starts[segment])
