"""Where the object may be: a conservative model built from what was measured, not from a prior.

Motions keep their clearance from this model, so a wrong shape estimate cannot lead the tool
into the object. It is a boolean voxel grid (world axes, :data:`VOXEL_SIZE_M` voxels) over a
cube on the object point:

1. **The camera's view** (:meth:`ObjectBound.from_depth`): space in front of the measured depth
   is free; space behind an above-table surface is where the object may be, up to a hidden
   depth (the object may reach that far behind what the camera sees of it). Where a pixel has
   no return (a dropped edge pixel, grazing incidence), the nearest return around it stands in,
   so a silhouette's edge is widened, never narrowed. A pixel with no return around it saw
   nothing in the sensor's range: free (a surface the sensor cannot see at all, black or
   transparent, is left to the shape estimate). Space outside the image is possible.
   With no depth at all (an RGB camera), the object-fitted cube stands in
   (:meth:`ObjectBound.from_box`).
2. **Touches carve it**: the volume the gel's window swept without meeting anything is free
   (:meth:`ObjectBound.carve`).
3. **The shape estimate can only add to it** (:meth:`ObjectBound.with_points`), never remove.

Its **hidden** part (``hidden``) is what the camera did not see: the possible voxels behind the
measured surface (the voxel's centre over half its diagonal behind the nearest return) or out of
the image, less what touches carved. The rest of the bound is the band the depth noise keeps in
front of the measured surface, where the surface points themselves tell where the object is.
The tool parts behind the gel keep their clearance from the hidden part on an approach: an
under-estimated limb out of the camera's sight is there.

A voxel is marked possible when any part of it may hold the object, so distances measured to
possible voxel centres under-estimate clearance by at most half a voxel diagonal.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from models.camera import CameraIntrinsics
from models.geometry import VoxelGrid

FloatArray = NDArray[np.float64]

EXTENT_M = 0.40
"""Edge of the modelled cube on the object point: objects up to 30 cm with their margins."""
VOXEL_SIZE_M = 0.004
DEPTH_NOISE_MARGIN_M = 0.005
"""A voxel counts as seen free only this far (plus half its diagonal) in front of the measured
surface: about 3 sigma of the Kinect v2's depth noise at 1 m."""
NEIGHBOURHOOD_PX = 7
"""Depth is taken as the nearest and farthest return in this window around a voxel's pixel:
covers the voxel's footprint and the pixels a depth edge drops."""
HOLE_NEIGHBOURHOOD_PX = 21
"""At a pixel with no return this wider window is used: a thin part (a mug's handle) or a face at
grazing incidence can vanish from a time-of-flight image over a few millimetres (about 1.3 mm
per pixel at 0.7 m)."""
OCCLUDER_MIN_HEIGHT_M = 0.004
"""Only surfaces this far above the table cast a shadow where the object may be (the table
itself does not; the tool keeps its table clearance below that anyway)."""
HIDDEN_DEPTH_FACTOR = 1.0
"""The object may reach this many times its larger seen extent (width or height) behind what
the camera sees of it (one view cannot tell its depth); capped by :data:`MAX_HIDDEN_DEPTH_M`."""
SURFACE_SPACING_M = 0.002
MIN_HIDDEN_DEPTH_M = 0.03
MAX_HIDDEN_DEPTH_M = 0.30


@dataclass(frozen=True)
class ObjectBound:
    """Possible-object voxels (``possible[i, j, k]``) on ``grid`` (world axes, bottom centre on
    the table) and the voxels touches proved free (``free``: never possible again)."""

    grid: VoxelGrid
    possible: NDArray[np.bool_]
    free: NDArray[np.bool_]
    surface_points_world: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    """The object's measured surface: its depth points above the table in the cube, one per
    :data:`SURFACE_SPACING_M` cell (none without depth)."""
    hidden: NDArray[np.bool_] | None = None
    """The possible voxels the camera did not see (module docstring); None: all of them."""

    # --- construction ---------------------------------------------------------------------------

    @staticmethod
    def cube(object_point_world: ArrayLike) -> VoxelGrid:
        """The modelled cube: :data:`EXTENT_M` on the object point, world axes."""
        origin = tuple(float(v) for v in np.asarray(object_point_world, dtype=float))
        resolution = round(EXTENT_M / VOXEL_SIZE_M)
        axes = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
        return VoxelGrid(resolution, EXTENT_M, (origin[0], origin[1], 0.0), axes)

    @classmethod
    def from_depth(
        cls,
        depth_m: ArrayLike,
        intrinsics: CameraIntrinsics,
        pose_world_camera: ArrayLike,
        object_point_world: ArrayLike,
    ) -> ObjectBound:
        """The single-view bound from a depth image (z-depth, 0 = no return) of the scene."""
        grid = cls.cube(object_point_world)
        depth = np.asarray(depth_m, dtype=float)
        returned = depth > 0
        if not np.any(returned):
            raise ValueError("the depth image has no returns")
        nearest = _filled(ndimage.minimum_filter, np.where(returned, depth, np.inf), np.inf)
        farthest = _filled(ndimage.maximum_filter, depth, 0.0)  # 0 (no return) never wins

        pose = np.asarray(pose_world_camera, dtype=float)
        centres = grid.voxel_centres_world().reshape(-1, 3)
        camera = (centres - pose[:3, 3]) @ pose[:3, :3]  # world -> camera frame
        z = camera[:, 2]
        in_front = z > 1e-6
        u = np.full(len(z), -1, dtype=np.int64)
        v = np.full(len(z), -1, dtype=np.int64)
        # Pixel (u, v) is centred on integer coordinates (the OpenCV convention).
        u[in_front] = np.round(intrinsics.fx * camera[in_front, 0] / z[in_front] + intrinsics.cx)
        v[in_front] = np.round(intrinsics.fy * camera[in_front, 1] / z[in_front] + intrinsics.cy)
        seen = in_front & (u >= 0) & (u < depth.shape[1]) & (v >= 0) & (v < depth.shape[0])
        near = np.full(len(z), np.inf)
        far = np.zeros(len(z))
        near[seen] = nearest[v[seen], u[seen]]
        far[seen] = farthest[v[seen], u[seen]]

        half_diagonal = 0.5 * np.sqrt(3.0) * grid.voxel_size_m
        seen_free = z < near - DEPTH_NOISE_MARGIN_M - half_diagonal
        # What casts the shadow must stand above the table: the highest return around the
        # pixel, after a median filter (a single return would lift the table by its noise).
        heights = _filled(
            ndimage.maximum_filter,
            _height_image(ndimage.median_filter(depth, 3), intrinsics, pose),
            -np.inf,
        )
        occluder_z = np.full(len(z), -np.inf)
        occluder_z[seen] = heights[v[seen], u[seen]]
        surface = object_depth_points(depth, intrinsics, pose, grid)
        hidden_depth_m = _hidden_depth_m(surface)
        shadow = (occluder_z > OCCLUDER_MIN_HEIGHT_M) & (z <= far + hidden_depth_m + half_diagonal)
        possible = ~seen | (~seen_free & shadow)
        above_table = centres[:, 2] > -0.5 * grid.voxel_size_m
        possible &= above_table
        shape = (grid.resolution,) * 3
        hidden = possible & ~(seen & (z <= near + half_diagonal))
        cells = np.unique(np.floor(surface / SURFACE_SPACING_M), axis=0)
        surface_points = (cells + 0.5) * SURFACE_SPACING_M
        return cls(
            grid,
            possible.reshape(shape),
            np.zeros(shape, dtype=bool),
            surface_points,
            hidden.reshape(shape),
        )

    @classmethod
    def from_box(cls, box: VoxelGrid, object_point_world: ArrayLike) -> ObjectBound:
        """With no depth: everything inside the object-fitted cube ``box`` may be object."""
        grid = cls.cube(object_point_world)
        inside = _inside_grid(box, grid.voxel_centres_world(), margin_voxels=0.5)
        return cls(grid, inside, np.zeros_like(inside))

    # --- updates --------------------------------------------------------------------------------

    def with_points(self, points_world: ArrayLike) -> ObjectBound:
        """Add the voxels holding these points (a shape estimate's), except proven-free ones."""
        ijk = self._voxels_of(points_world)
        possible = self.possible.copy()
        possible[tuple(ijk.T)] = True
        return replace(self, possible=possible & ~self.free)

    def carve(self, free_voxels_ijk: ArrayLike) -> ObjectBound:
        """Mark voxels a touch swept through without contact as free. The swept set is eroded by
        one voxel first: a voxel on its rim was only partly swept."""
        ijk = np.asarray(free_voxels_ijk, dtype=np.int64).reshape(-1, 3)
        swept = np.zeros_like(self.free)
        if len(ijk):
            swept[tuple(ijk.T)] = True
        swept = ndimage.binary_erosion(swept, iterations=1)
        free = self.free | swept
        hidden = None if self.hidden is None else self.hidden & ~free
        return replace(self, possible=self.possible & ~free, free=free, hidden=hidden)

    # --- queries --------------------------------------------------------------------------------

    @cached_property
    def boundary_points_world(self) -> FloatArray:
        """Centres of the possible voxels on the model's surface (a possible voxel with a
        non-possible face neighbour, or on the cube's side): what clearance is measured to."""
        return self._boundary_points(self.possible)

    @cached_property
    def hidden_boundary_points_world(self) -> FloatArray:
        """Centres of the hidden voxels on the hidden part's surface."""
        return self._boundary_points(self.possible if self.hidden is None else self.hidden)

    def _boundary_points(self, voxels: NDArray[np.bool_]) -> FloatArray:
        interior = ndimage.binary_erosion(voxels, border_value=0)
        return self.grid.voxel_to_world(np.argwhere(voxels & ~interior) + 0.5)

    def contains(self, points_world: ArrayLike, *, hidden: bool = False) -> NDArray[np.bool_]:
        """Whether each point lies in a possible voxel, or with ``hidden`` in a hidden one
        (points outside the cube: False)."""
        voxels = self.possible if not hidden or self.hidden is None else self.hidden
        ijk, inside = self.grid.voxel_index(points_world)
        result = np.zeros(len(ijk), dtype=bool)
        result[inside] = voxels[tuple(ijk[inside].T)]
        return result

    def first_along(
        self, start_world: ArrayLike, direction_world: ArrayLike, length_m: float
    ) -> float | None:
        """Distance from ``start_world`` along the (unit) direction to the first possible voxel
        within ``length_m`` (sampled every half voxel), or None when the line misses."""
        distances, inside = self._along_lines(start_world, direction_world, length_m)
        hits = np.flatnonzero(inside[0])
        return float(distances[hits[0]]) if len(hits) else None

    def lines_meet(
        self, starts_world: ArrayLike, direction_world: ArrayLike, length_m: float
    ) -> NDArray[np.bool_]:
        """Whether each line from ``starts_world`` (M, 3) along the (unit) direction meets a
        possible voxel within ``length_m`` (sampled every half voxel)."""
        return self._along_lines(starts_world, direction_world, length_m)[1].any(axis=1)

    def _along_lines(
        self, starts_world: ArrayLike, direction_world: ArrayLike, length_m: float
    ) -> tuple[FloatArray, NDArray[np.bool_]]:
        """The sample distances along the lines (every half voxel) and, per line (M rows),
        whether each sample lies in a possible voxel."""
        starts = np.asarray(starts_world, dtype=float).reshape(-1, 3)
        step = 0.5 * self.grid.voxel_size_m
        distances = np.arange(0.0, length_m + step, step)
        offsets = distances[:, None] * np.asarray(direction_world, dtype=float)
        points = starts[:, None, :] + offsets[None, :, :]
        return distances, self.contains(points.reshape(-1, 3)).reshape(len(starts), -1)

    @property
    def top_m(self) -> float:
        """Height of the highest possible voxel's top (0 when empty)."""
        levels = np.flatnonzero(self.possible.any(axis=(0, 1)))
        return float((levels[-1] + 1) * self.grid.voxel_size_m) if len(levels) else 0.0

    def _voxels_of(self, points_world: ArrayLike) -> NDArray[np.int64]:
        ijk, inside = self.grid.voxel_index(points_world)
        return ijk[inside]


def _filled(filter_: Callable[..., FloatArray], image: FloatArray, none: float) -> FloatArray:
    """``filter_`` (a min or max filter) over :data:`NEIGHBOURHOOD_PX` at pixels with a return,
    over :data:`HOLE_NEIGHBOURHOOD_PX` at pixels without (``none``): a thin part (a handle) or a
    face at grazing incidence can vanish from the depth image over a few pixels."""
    near = filter_(image, NEIGHBOURHOOD_PX)
    hole = image == none
    if np.any(hole):
        near[hole] = filter_(image, HOLE_NEIGHBOURHOOD_PX)[hole]
    return near


def _height_image(
    depth_m: FloatArray, intrinsics: CameraIntrinsics, pose_world_camera: FloatArray
) -> FloatArray:
    """World height of each pixel's depth point (-inf where there is no return)."""
    v, u = np.indices(depth_m.shape)
    x = (u - intrinsics.cx) / intrinsics.fx
    y = (v - intrinsics.cy) / intrinsics.fy
    rotation_z = pose_world_camera[2, :3]
    heights = depth_m * (rotation_z[0] * x + rotation_z[1] * y + rotation_z[2])
    heights = heights + pose_world_camera[2, 3]
    return np.where(depth_m > 0, heights, -np.inf)


def object_depth_points(
    depth_m: FloatArray,
    intrinsics: CameraIntrinsics,
    pose_world_camera: FloatArray,
    grid: VoxelGrid,
) -> FloatArray:
    """The depth points (world) standing above the table inside ``grid``'s cube."""
    v, u = np.nonzero(depth_m > 0)
    d = depth_m[v, u]
    camera = np.column_stack(
        [(u - intrinsics.cx) / intrinsics.fx * d, (v - intrinsics.cy) / intrinsics.fy * d, d]
    )
    points = camera @ pose_world_camera[:3, :3].T + pose_world_camera[:3, 3]
    above = (points[:, 2] > OCCLUDER_MIN_HEIGHT_M) & _inside_grid(grid, points, margin_voxels=0.0)
    return points[above]


def _hidden_depth_m(object_points_world: FloatArray) -> float:
    """How far behind its seen surface the object may reach: :data:`HIDDEN_DEPTH_FACTOR` times
    the larger of the seen object's width and height (from its depth points), in
    [:data:`MIN_HIDDEN_DEPTH_M`, :data:`MAX_HIDDEN_DEPTH_M`]."""
    if len(object_points_world) == 0:
        return MIN_HIDDEN_DEPTH_M
    extent = np.ptp(object_points_world, axis=0)
    seen = max(float(np.hypot(extent[0], extent[1])), float(object_points_world[:, 2].max()))
    return float(np.clip(HIDDEN_DEPTH_FACTOR * seen, MIN_HIDDEN_DEPTH_M, MAX_HIDDEN_DEPTH_M))


def _inside_grid(grid: VoxelGrid, points_world: ArrayLike, *, margin_voxels: float) -> NDArray:
    """Whether points lie inside ``grid``'s cube (grown by ``margin_voxels``), any shape."""
    coords = grid.world_to_voxel(points_world)
    return np.all((coords >= -margin_voxels) & (coords <= grid.resolution + margin_voxels), axis=-1)
