"""Touch results -> voxel constraints along the approach rays (the paper's Fig. "loss").

A touch is a bundle of parallel rays along the approach direction ``d`` (unit, world), one per
sampled point of the sensor patch. A ray that ended on the object (a contact point) says: the voxels
it crossed in front of the contact are empty, the voxel holding the contact point is occupied. A
ray that ended without contact (a miss after the whole stroke, or a pad point that never touched)
says: every voxel it crossed is empty. Rays are traversed exactly (Amanatides & Woo 1987) in the
grid's continuous voxel coordinates, for any direction, with segments clipped to the grid first.

Conventions (see docs/conventions.md): world metres, voxel (i, j, k) covers
[i, i+1) x [j, j+1) x [k, k+1) of continuous voxel coordinates. A voxel that some ray calls
occupied and another calls empty stays occupied: a contact proves the surface passes through the
voxel, an empty crossing only proves part of it is free. See docs/touch.md.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from models.geometry import VoxelGrid, invert_transform, transform_points

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]

DEFAULT_OCCUPIED_DEPTH_VOXELS = math.sqrt(3.0) / 2.0
"""How far beyond a contact point (voxels, along the ray) the occupied voxel is taken."""
# Rays of one touch whose end points agree to this fraction of a voxel traverse nearly the same
# voxels; keeping one of them bounds the work when a height map yields 10^5 contact points.
DEFAULT_RAY_SPACING_VOXELS = 0.25


def _unit(vector: ArrayLike) -> FloatArray:
    vector = np.asarray(vector, dtype=float).reshape(3)
    norm = float(np.linalg.norm(vector))
    if norm < 1e-12:
        raise ValueError("approach direction must be non-zero")
    return vector / norm


def _points(points: ArrayLike) -> FloatArray:
    array = np.asarray(points, dtype=float)
    if array.size == 0:
        return np.zeros((0, 3))
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"expected (N, 3) points, got shape {array.shape}")
    return array


@dataclass(frozen=True)
class TouchResult:
    """One touch attempt as parallel rays along the approach direction (world frame, metres).

    Ray r runs from ``ray_starts_world[r]`` to ``ray_ends_world[r]``. ``ray_hit[r]`` is True when
    the ray ended on the object surface (its end is a measured contact point) and False when the
    sensor swept it without contact. Independent of how contacts were measured: build it with
    :meth:`from_contact` or :meth:`from_miss`.
    """

    approach_direction_world: FloatArray
    """Unit direction the sensor moved in (the pad's +z, toward the object)."""
    ray_starts_world: FloatArray
    ray_ends_world: FloatArray
    ray_hit: NDArray[np.bool_]
    stop_points_world: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    """Of a stroke the fingers' force stopped without an imprint: the points of the tool where
    it can have met the object (``drivers.tool.ToolModel.leading_points_pad`` at the stop).
    The object reaches at least one of them; empty for any other touch."""
    stop_directions_world: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    """The direction each of ``stop_points_world`` moved in (unit): the object lies beyond."""

    @property
    def is_miss(self) -> bool:
        """True when no ray met the object (the whole stroke was free)."""
        return not bool(self.ray_hit.any())

    @property
    def contact_points_world(self) -> FloatArray:
        return self.ray_ends_world[self.ray_hit]

    @classmethod
    def from_contact(
        cls,
        contact_points_world: ArrayLike,
        approach_direction_world: ArrayLike,
        approach_start_world: ArrayLike,
        free_points_world: ArrayLike = (),
    ) -> TouchResult:
        """A touch that met the object.

        Args:
            contact_points_world: (M, 3) measured points of the object surface under the pad.
            approach_direction_world: direction the pad moved (normalised here).
            approach_start_world: any point of the plane (normal ``d``) the approach started
                from, e.g. the pad centre at the start of the stroke; every ray starts on it.
            free_points_world: (F, 3) points the gel surface reached without contact (see
                :func:`free_pad_points`); their rays are empty all the way.
        """
        direction = _unit(approach_direction_world)
        contacts = _points(contact_points_world)
        if len(contacts) == 0:
            raise ValueError("a contact touch needs at least one contact point; use from_miss")
        free = _points(free_points_world)
        ends = np.concatenate([contacts, free])
        start = np.asarray(approach_start_world, dtype=float).reshape(3)
        depth = (ends - start) @ direction
        if np.any(depth < 0):
            raise ValueError("contact or free points lie behind the approach start plane")
        starts = ends - depth[:, None] * direction
        hit = np.concatenate([np.ones(len(contacts), bool), np.zeros(len(free), bool)])
        return cls(direction, starts, ends, hit)

    @classmethod
    def from_miss(
        cls,
        segment_starts_world: ArrayLike,
        segment_ends_world: ArrayLike,
        stop_points_world: ArrayLike = (),
        stop_directions_world: ArrayLike = (),
    ) -> TouchResult:
        """A touch whose stroke met nothing under the gel: each swept segment start -> end is
        empty. ``stop_points_world``, ``stop_directions_world``: where a force stopped it, the
        tool's points that can have met the object and the direction each moved in.

        All segments must be parallel (one rigid pad moving straight); see :func:`pad_grid_world`
        for sampling the pad.
        """
        starts = _points(segment_starts_world)
        ends = _points(segment_ends_world)
        if starts.shape != ends.shape or len(starts) == 0:
            raise ValueError("need matching, non-empty (N, 3) segment starts and ends")
        direction = _unit((ends - starts).mean(axis=0))
        stop, stop_directions = _points(stop_points_world), _points(stop_directions_world)
        if stop.shape != stop_directions.shape:
            raise ValueError("need a direction for every stop point")
        return cls(direction, starts, ends, np.zeros(len(starts), bool), stop, stop_directions)


def pad_grid_world(
    pose_world_pad: ArrayLike, pad_size_m: tuple[float, float], spacing_m: float
) -> FloatArray:
    """Points of the undeformed gel surface (pad z = 0) on a grid, in world metres, (M, 3).

    ``pad_size_m`` is (along pad x, along pad y), e.g. (0.019, 0.014); the grid covers the whole
    rectangle with at most ``spacing_m`` between neighbours.
    """
    axes = []
    for size in pad_size_m:
        count = max(2, int(np.ceil(size / spacing_m)) + 1)
        axes.append(np.linspace(-size / 2, size / 2, count))
    x, y = np.meshgrid(*axes, indexing="ij")
    pad_points = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    return transform_points(pose_world_pad, pad_points)


def free_pad_points(
    pose_world_pad: ArrayLike,
    contact_points_world: ArrayLike,
    pad_size_m: tuple[float, float],
    spacing_m: float,
    margin_m: float = 0.002,
) -> FloatArray:
    """Pad points that swept free space during a contact touch, world metres (M, 3).

    Grid points of the pad at its final pose (``pose_world_pad``: +z toward the object) further
    than ``margin_m`` sideways from every contact point, each pulled back by ``margin_m`` along
    -z: next to a contact the soft gel sinks in, so the object may sit slightly behind the
    undeformed gel plane there without being seen as contact.
    """
    pose = np.asarray(pose_world_pad, dtype=float)
    grid = pad_grid_world(pose, pad_size_m, spacing_m)
    contacts = _points(contact_points_world)
    normal = pose[:3, 2]
    if len(contacts):
        # Sideways = in the pad plane: compare pad-frame (x, y) of grid points and contacts.
        contacts_pad = transform_points(invert_transform(pose), contacts)[:, :2]
        grid_pad = transform_points(invert_transform(pose), grid)[:, :2]
        distance, _ = cKDTree(contacts_pad).query(grid_pad, distance_upper_bound=2 * margin_m)
        grid = grid[distance > margin_m]
    return grid - margin_m * normal


# --- exact voxel traversal ----------------------------------------------------------------------


def _clip_to_box(
    starts: FloatArray, ends: FloatArray, upper: float
) -> tuple[FloatArray, FloatArray]:
    """Parameters [t0, t1] of each segment inside [0, upper]^3 (slab method, vectorised);
    t0 > t1 where the segment misses the box."""
    delta = ends - starts
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (0.0 - starts) / delta
        tb = (upper - starts) / delta
    parallel = delta == 0.0
    inside_slab = (starts >= 0.0) & (starts < upper)  # half-open, like the voxels
    lo = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(ta, tb))
    hi = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(ta, tb))
    t0 = np.maximum(lo.max(axis=1), 0.0)
    t1 = np.minimum(hi.min(axis=1), 1.0)
    return t0, t1


def traverse_segments(
    starts_voxel: ArrayLike, ends_voxel: ArrayLike, resolution: int
) -> tuple[IntArray, IntArray]:
    """Voxels each segment passes through, by exact grid traversal (Amanatides-Woo), vectorised.

    Segments are in continuous voxel coordinates and may start or end outside the grid (they
    are clipped to it). A voxel is reported when the segment crosses it over a positive length;
    where a segment passes exactly through an edge or corner, it steps over the touched-only
    voxels. A zero-length segment reports the voxel it lies in.

    Returns:
        (segment index (K,), voxel indices (K, 3)), ordered along each segment from its start.
    """
    starts = np.atleast_2d(np.asarray(starts_voxel, dtype=float))
    ends = np.atleast_2d(np.asarray(ends_voxel, dtype=float))
    t0, t1 = _clip_to_box(starts, ends, float(resolution))
    # A segment that only grazes the box (t0 == t1) crosses no voxel; a zero-length segment
    # inside has t0 = 0 < t1 = 1.
    segment = np.flatnonzero(t0 < t1)
    starts, ends, t0, t1 = starts[segment], ends[segment], t0[segment], t1[segment]
    delta = ends - starts
    step = np.sign(delta).astype(np.int64)
    entry = starts + t0[:, None] * delta
    # The first voxel is the one the segment enters: on a voxel face moving down an axis,
    # that is the voxel below the face (ceil - 1), otherwise the one the floor names.
    voxel = np.where(step < 0, np.ceil(entry) - 1, np.floor(entry)).astype(np.int64)
    voxel = np.clip(voxel, 0, resolution - 1)
    moves = delta != 0.0
    # 1 / delta where the segment moves along an axis; axes it does not move along never exit.
    inverse = np.divide(1.0, delta, out=np.zeros_like(delta), where=moves)
    boundary_offset = (step > 0).astype(np.int64)

    out_segment: list[IntArray] = []
    out_voxel: list[IntArray] = []
    active = np.arange(len(segment))
    while active.size:
        out_segment.append(segment[active])
        out_voxel.append(voxel[active].copy())
        # Parameter where the segment leaves the current voxel along each axis, from the voxel
        # index directly (no accumulated increments, so no drift on long rays).
        boundary = voxel[active] + boundary_offset[active]
        t_exit = np.where(moves[active], (boundary - starts[active]) * inverse[active], np.inf)
        t_next = t_exit.min(axis=1)
        moving = t_next < t1[active]
        # Step every axis whose boundary comes first: ties step together (edge/corner crossing).
        advance = (t_exit == t_next[:, None]) & moving[:, None]
        voxel[active] += np.where(advance, step[active], 0)
        in_grid = np.all((voxel[active] >= 0) & (voxel[active] < resolution), axis=1)
        active = active[moving & in_grid]
    if not out_segment:
        return np.zeros(0, np.int64), np.zeros((0, 3), np.int64)
    seg = np.concatenate(out_segment)
    vox = np.concatenate(out_voxel)
    order = np.argsort(seg, kind="stable")
    return seg[order], vox[order]


# --- constraints -------------------------------------------------------------------------------


@dataclass(frozen=True)
class VoxelConstraints:
    """Voxels a set of touches proved empty or occupied, as sorted flat indices into N^3.

    Flat index = (i * N + j) * N + k, i.e. C order of a [i, j, k] volume. ``empty`` and
    ``occupied`` are disjoint (occupied wins, see the module docstring). ``any_occupied``: groups
    of voxels of which at least one is occupied (a stop by force without an imprint), none of
    them known empty.
    """

    resolution: int
    empty: IntArray
    occupied: IntArray
    any_occupied: tuple[IntArray, ...] = ()

    @classmethod
    def none(cls, resolution: int) -> VoxelConstraints:
        return cls(resolution, np.zeros(0, np.int64), np.zeros(0, np.int64))

    @classmethod
    def from_voxels(
        cls, resolution: int, empty_ijk: ArrayLike, occupied_ijk: ArrayLike
    ) -> VoxelConstraints:
        """From (K, 3) voxel index lists (duplicates and overlaps allowed)."""
        shape = (resolution,) * 3

        def flat(ijk: ArrayLike) -> IntArray:
            ijk = np.asarray(ijk, dtype=np.int64).reshape(-1, 3)
            return np.unique(np.ravel_multi_index(tuple(ijk.T), shape))

        occupied = flat(occupied_ijk)
        empty = np.setdiff1d(flat(empty_ijk), occupied, assume_unique=True)
        return cls(resolution, empty, occupied)

    def merged(self, other: VoxelConstraints) -> VoxelConstraints:
        """Union of two constraint sets (occupied wins over empty)."""
        if other.resolution != self.resolution:
            raise ValueError("cannot merge constraints of different resolutions")
        occupied = np.union1d(self.occupied, other.occupied)
        empty = np.setdiff1d(np.union1d(self.empty, other.empty), occupied, assume_unique=True)
        groups = (np.setdiff1d(g, empty) for g in (*self.any_occupied, *other.any_occupied))
        return VoxelConstraints(
            self.resolution, empty, occupied, tuple(g for g in groups if len(g))
        )

    def empty_ijk(self) -> IntArray:
        return np.stack(np.unravel_index(self.empty, (self.resolution,) * 3), axis=1)

    def occupied_ijk(self) -> IntArray:
        return np.stack(np.unravel_index(self.occupied, (self.resolution,) * 3), axis=1)

    def __len__(self) -> int:
        return len(self.empty) + len(self.occupied) + len(self.any_occupied)


def touch_constraints(
    touch: TouchResult,
    grid: VoxelGrid,
    ray_spacing_voxels: float = DEFAULT_RAY_SPACING_VOXELS,
    occupied_depth_voxels: float = DEFAULT_OCCUPIED_DEPTH_VOXELS,
) -> VoxelConstraints:
    """Constraints of one touch on a grid: every ray of the patch, traversed exactly.

    Contact rays: crossed voxels whose centres lie in front of the contact point are empty; the
    voxel holding the point ``occupied_depth_voxels`` beyond the contact along the ray is
    occupied (when inside the grid). Why beyond: a voxel is occupied when its centre is inside
    the object, and the voxel holding a surface point has its centre outside about half the
    time; a point sqrt(3)/2 voxel deep lies in a voxel whose centre is behind a surface facing
    the ray.
    Voxels between stay unconstrained. Free rays: crossed voxels whose centres lie in front of
    the ray's end are empty (the pad stopped there, or the stroke ended: what lies beyond is
    unknown).
    Rays whose end points fall in the same ``ray_spacing_voxels`` cell are traversed once.
    A stop without an imprint (``TouchResult.stop_points_world``) adds one ``any_occupied``
    group: the voxels holding its points ``occupied_depth_voxels`` beyond them, each along the
    direction it moved.
    """
    starts = grid.world_to_voxel(touch.ray_starts_world)
    ends = grid.world_to_voxel(touch.ray_ends_world)
    hit = touch.ray_hit
    cells = np.floor(ends / ray_spacing_voxels).astype(np.int64)
    _, keep = np.unique(np.column_stack([cells, hit]), axis=0, return_index=True)
    starts, ends, hit = starts[keep], ends[keep], hit[keep]

    resolution = grid.resolution
    ray, voxels = traverse_segments(starts, ends, resolution)
    origin_voxel, ahead_voxel = grid.world_to_voxel(
        np.stack([np.zeros(3), touch.approach_direction_world])
    )
    direction_voxel = (ahead_voxel - origin_voxel) / np.linalg.norm(ahead_voxel - origin_voxel)
    inner_voxel = np.floor(ends[hit] + occupied_depth_voxels * direction_voxel).astype(np.int64)
    inside = np.all((inner_voxel >= 0) & (inner_voxel < resolution), axis=1)
    occupied = inner_voxel[inside]
    # A crossed voxel is empty only if its centre is in front of the ray's end: the last voxel
    # of a ray (and, for an oblique ray, others) can have its centre beyond it, where a stop
    # proves nothing (a thin part under a pad stopped by force had 10 voxels wrongly emptied).
    beyond_end = ((voxels + 0.5) - ends[ray]) @ direction_voxel >= 0
    constraints = VoxelConstraints.from_voxels(resolution, voxels[~beyond_end], occupied)
    if len(touch.stop_points_world) == 0:
        return constraints
    stop = grid.world_to_voxel(touch.stop_points_world)
    beyond = grid.world_to_voxel(touch.stop_points_world + touch.stop_directions_world) - stop
    beyond /= np.linalg.norm(beyond, axis=1, keepdims=True)
    stop_voxels = np.floor(stop + occupied_depth_voxels * beyond).astype(np.int64)
    stop_voxels = stop_voxels[np.all((stop_voxels >= 0) & (stop_voxels < resolution), axis=1)]
    group = VoxelConstraints.from_voxels(resolution, np.zeros((0, 3)), stop_voxels).occupied
    return constraints.merged(
        VoxelConstraints(resolution, np.zeros(0, np.int64), np.zeros(0, np.int64), (group,))
    )


def constraints_from_touches(
    touches: Iterable[TouchResult],
    grid: VoxelGrid,
    ray_spacing_voxels: float = DEFAULT_RAY_SPACING_VOXELS,
) -> VoxelConstraints:
    """Merged constraints of all touches so far (occupied wins over empty)."""
    constraints = VoxelConstraints.none(grid.resolution)
    for touch in touches:
        constraints = constraints.merged(touch_constraints(touch, grid, ray_spacing_voxels))
    return constraints
