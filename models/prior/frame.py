"""The object-fitted frame: a voxel grid whose centre and size come from what the camera sees.

A prior decodes into a fixed number of voxels; a fixed 26 cm cube leaves a 5 cm object a dozen
voxels wide. So the grid is fitted to the object first, as in canonical-frame reconstruction:

1. the *search grid*, a cube of :data:`SEARCH_EXTENT_M` on the object point, gives a crop in which
   the object's silhouette is found (by the sketch net, or from depth with RGB-D);
2. :func:`fit_object_grid` turns the silhouette into the object's footprint and height, with the
   known table plane (world z = 0) and the camera's pose: the lowest silhouette pixels are the
   object's front base on the table; the silhouette's rays, cut by the vertical plane through
   the object's centre, give its width and height;
3. the prior sees the crop of the fitted grid and decodes the shape in it.

Training data, the service and the benchmarks all compute the frame with these functions, so the
networks learn the frame's own errors. The depth of the object along the line of sight is not
visible in one image; the frame assumes it is as deep as it is wide, and the cube's margin
absorbs the rest.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from models.camera import CameraIntrinsics
from models.geometry import VoxelGrid

SEARCH_EXTENT_M = 0.34
"""Edge of the search grid: holds objects up to 30 cm with a margin."""
FRAME_MARGIN = 1.4
"""The fitted cube's edge over the object's estimated largest extent: room for where the object
may be that one image cannot tell (its depth along the line of sight, its overhang)."""
FRONT_OVERHANG = 0.17
"""The object's front base is where its lowest silhouette pixels meet the table only for upright
sides (a box); a rounded object bulges in front of that point by up to about 0.7 of its radius.
The centre is moved toward the camera by this fraction of the object's height to split the
difference: with :data:`FRAME_MARGIN` the cube holds both a box and a sphere."""
EXTENT_RANGE_M = (0.03, 0.40)
"""The fitted cube's edge is clipped to this range (metres)."""
MIN_SILHOUETTE_PIXELS = 4


class FrameError(ValueError):
    """No object can be found in the image to fit a frame to."""


def search_grid(
    resolution: int, axes_world: ArrayLike, object_point_world: ArrayLike = (0.0, 0.0, 0.0)
) -> VoxelGrid:
    """The cube in which the object is looked for: :data:`SEARCH_EXTENT_M` on the object point."""
    axes = tuple(tuple(float(v) for v in axis) for axis in np.asarray(axes_world, dtype=float))
    origin = tuple(float(v) for v in np.asarray(object_point_world, dtype=float))
    return VoxelGrid(resolution, SEARCH_EXTENT_M, origin, axes)  # type: ignore[arg-type]


def _rays_world(
    pixels_vu: NDArray[np.intp], intrinsics: CameraIntrinsics, pose_world_camera: np.ndarray
) -> NDArray[np.float64]:
    """World directions of the rays through pixel centres (v, u) (not normalised)."""
    v, u = pixels_vu[:, 0].astype(float), pixels_vu[:, 1].astype(float)
    camera = np.column_stack(
        [(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, np.ones_like(u)]
    )
    return camera @ np.asarray(pose_world_camera, dtype=float)[:3, :3].T


def fit_object_grid(
    silhouette: ArrayLike,
    intrinsics: CameraIntrinsics,
    pose_world_camera: np.ndarray,
    axes_world: ArrayLike,
    resolution: int,
) -> VoxelGrid:
    """The cubic grid fitted to the object whose silhouette (H x W, bool) an image shows.

    ``intrinsics`` and ``pose_world_camera`` are those of the image the silhouette is in (a crop
    is a pinhole camera too). ``axes_world`` are the grid's axes (a_x horizontal toward the
    camera, a_z up); the result keeps them, stands on the table (world z = 0) and is centred on
    the estimated footprint, with an edge of :data:`FRAME_MARGIN` times the larger of the
    object's width and height.

    Raises:
        FrameError: the silhouette is (nearly) empty or does not reach down to the table.
    """
    mask = np.asarray(silhouette, dtype=bool)
    pixels = np.argwhere(mask)
    if len(pixels) < MIN_SILHOUETTE_PIXELS:
        raise FrameError("no object found in the camera image (empty silhouette)")
    axes = np.asarray(axes_world, dtype=float)
    toward_camera, lateral = axes[0], axes[1]
    centre_camera = np.asarray(pose_world_camera, dtype=float)[:3, 3]

    # Front base: the lowest silhouette pixel of each column meets the table nearest the camera.
    columns = np.unique(pixels[:, 1])
    lowest_v = np.full(mask.shape[1], -1)
    np.maximum.at(lowest_v, pixels[:, 1], pixels[:, 0])
    bottom = np.column_stack([lowest_v[columns], columns])
    bottom_rays = _rays_world(bottom, intrinsics, pose_world_camera)
    down = bottom_rays[:, 2] < -1e-9
    if not np.any(down):
        raise FrameError("the silhouette does not reach the table: no footprint to fit")
    t_table = -centre_camera[2] / bottom_rays[down, 2]
    base_points = centre_camera + t_table[:, None] * bottom_rays[down]
    front = float(np.percentile(base_points @ toward_camera, 90))
    base_lateral = base_points @ lateral
    width = float(np.ptp(np.percentile(base_lateral, (2, 98))))

    # Width and height where the silhouette's rays cross the vertical plane through the centre;
    # the centre lies half a width behind the front (as deep as wide), so iterate.
    rays = _rays_world(pixels, intrinsics, pose_world_camera)
    along = rays @ toward_camera
    rays, along = rays[along < -1e-9], along[along < -1e-9]
    if len(rays) < MIN_SILHOUETTE_PIXELS:
        raise FrameError("the silhouette lies behind the camera's horizon: no object to fit")
    lateral_centre, height = float(np.median(base_lateral)), 0.0
    for _ in range(3):
        depth = front - 0.5 * width + FRONT_OVERHANG * height
        t_plane = (depth - centre_camera @ toward_camera) / along
        points = centre_camera + t_plane[:, None] * rays
        low, high = np.percentile(points @ lateral, (1, 99))
        width = float(high - low)
        lateral_centre = float(0.5 * (low + high))
        height = float(np.percentile(points[:, 2], 99.5))
    depth = front - 0.5 * width + FRONT_OVERHANG * height
    extent = float(np.clip(FRAME_MARGIN * max(width, height), *EXTENT_RANGE_M))
    origin = depth * toward_camera + lateral_centre * lateral
    origin[2] = 0.0
    return VoxelGrid(
        resolution,
        extent,
        (float(origin[0]), float(origin[1]), 0.0),
        tuple(tuple(float(v) for v in axis) for axis in axes),  # type: ignore[arg-type]
    )


HOLD_MARGIN = 1.1
"""A grid grown to hold the seen points leaves this much room around their extent."""


def grid_holding_points(grid: VoxelGrid, points_world: ArrayLike) -> VoxelGrid:
    """``grid``, grown and moved on the table just enough to hold ``points_world`` (RGB-D: the
    object's depth points) with :data:`HOLD_MARGIN`; unchanged when it already holds them. The
    silhouette's frame takes the object as deep as it is wide: a long object seen end-on (a
    knife, a keyboard) reaches out of it, and its measured surface with it."""
    points = np.asarray(points_world, dtype=float).reshape(-1, 3)
    if len(points) == 0:
        return grid
    coords = grid.world_to_voxel(points)
    if np.all((coords >= 0) & (coords <= grid.resolution)):
        return grid
    axes = np.asarray(grid.axes_world, dtype=float)
    origin = np.asarray(grid.origin_world, dtype=float)
    local = (points - origin) @ axes.T  # along the grid's axes, from its bottom centre
    low = np.minimum(local.min(axis=0), -0.5 * grid.extent_m)
    high = np.maximum(local.max(axis=0), 0.5 * grid.extent_m)
    low[2], high[2] = 0.0, max(float(local[:, 2].max()), grid.extent_m)
    extent = float(np.clip(HOLD_MARGIN * np.max(high - low), grid.extent_m, EXTENT_RANGE_M[1]))
    centre = 0.5 * (low + high)
    centre[2] = 0.0
    moved = origin + centre @ axes
    moved[2] = 0.0
    return VoxelGrid(
        grid.resolution,
        extent,
        (float(moved[0]), float(moved[1]), 0.0),
        grid.axes_world,
    )


def depth_silhouette(
    depth_m: ArrayLike,
    intrinsics: CameraIntrinsics,
    pose_world_camera: np.ndarray,
    grid: VoxelGrid,
    *,
    min_height_m: float = 0.004,
) -> NDArray[np.bool_]:
    """RGB-D: the pixels whose depth point stands above the table inside ``grid``'s box."""
    depth = np.asarray(depth_m, dtype=float)
    v, u = np.indices(depth.shape)
    camera = np.stack(
        [
            (u - intrinsics.cx) / intrinsics.fx * depth,
            (v - intrinsics.cy) / intrinsics.fy * depth,
            depth,
        ],
        axis=-1,
    )
    pose = np.asarray(pose_world_camera, dtype=float)
    world = camera @ pose[:3, :3].T + pose[:3, 3]
    voxel = grid.world_to_voxel(world)
    inside = np.all((voxel >= 0) & (voxel <= grid.resolution), axis=-1)
    return (depth > 0) & inside & (world[..., 2] > min_height_m)
