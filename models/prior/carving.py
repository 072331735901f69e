"""Space the camera saw empty: the voxels a prediction may never fill.

One image already rules out most of the grid. A voxel whose centre projects outside the
object's silhouette lies on a ray that met nothing but background (the visual hull's
complement); with depth, a voxel in front of the surface the sensor measured along its ray is
empty too. The shape net never sees these rays directly, and its calibration lifted voxels it was
unsure of (the grid's corners, docs/prior.md), so every prediction is capped by them: space seen
empty stays empty whatever the network or its calibration says.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from models.camera import CameraIntrinsics
from models.geometry import VoxelGrid, invert_transform, transform_points
from models.prior.frame import depth_silhouette
from models.prior.virtual_camera import GridCrop

FloatArray = NDArray[np.float64]

SEEN_EMPTY_PROBABILITY = 0.02
"""What a voxel the camera saw empty is capped at (confidently empty, as the policy reads it)."""
SILHOUETTE_DILATION_PX = 2
"""The seen silhouette is grown by this many pixels (about one voxel in a crop) before carving:
a predicted silhouette's edge may be off by a pixel or two."""
DEPTH_MARGIN_M = 0.006
"""A point counts as in front of (or behind) the measured surface when it is this much nearer
(farther) than the nearest depth return around its pixel: Kinect noise and a voxel's
half-diagonal."""


@dataclass(frozen=True)
class SeenPoints:
    """What one image says of some points (each array shaped as the points, less the last axis).
    Points that project outside the image or lie behind the camera are hidden, not empty."""

    empty: NDArray[np.bool_]
    """Seen empty: on a background ray, or more than :data:`DEPTH_MARGIN_M` in front of the
    nearest return around their pixel."""
    hidden: NDArray[np.bool_]
    """Out of sight: more than :data:`DEPTH_MARGIN_M` behind the nearest return around their
    pixel, on a pixel with no return near that is not a background ray, or outside the image."""
    in_front_m: FloatArray
    """How far (metres, >= 0) they lie in front of the nearest return around their pixel: 0
    behind it, off the image, or where no return is near."""


@dataclass(frozen=True)
class CameraView:
    """What one image says of space: per pixel, whether its ray met only background (off the
    grown silhouette, no depth return around it) and the nearest depth return around it (metres,
    inf where none). Built once per image; queried for any number of points."""

    intrinsics: CameraIntrinsics
    pose_world_camera: np.ndarray
    empty_ray: NDArray[np.bool_]
    nearest_depth_m: NDArray[np.float64]

    @classmethod
    def from_image(
        cls,
        intrinsics: CameraIntrinsics,
        pose_world_camera: np.ndarray,
        *,
        silhouette: NDArray[np.bool_] | None = None,
        depth_m: NDArray[np.floating] | None = None,
    ) -> CameraView:
        """``silhouette`` (bool, the image's pixels) is where the object is seen (None: not
        known; with depth, :func:`seen_silhouette` makes it), ``depth_m`` (metres, 0 = no
        return) the sensor's depth (None: no sensor)."""
        shape = (intrinsics.height, intrinsics.width)
        empty_ray = np.zeros(shape, bool)
        if silhouette is not None:
            grown = ndimage.binary_dilation(
                np.asarray(silhouette, dtype=bool), iterations=SILHOUETTE_DILATION_PX
            )
            empty_ray = ~grown
        nearest = np.full(shape, np.inf)
        if depth_m is not None:
            depth = np.asarray(depth_m, dtype=np.float64)
            returned = depth > 0
            # The nearest return around each pixel: a mixed pixel at an edge never carves the
            # object's side in front of it.
            nearest = -ndimage.maximum_filter(np.where(returned, -depth, -np.inf), size=3)
        return cls(intrinsics, np.asarray(pose_world_camera, float), empty_ray, nearest)

    def _project(self, points_world: ArrayLike) -> tuple[NDArray, NDArray, NDArray, NDArray]:
        """Camera z of each point, whether it projects into the image, and its pixel (v, u)."""
        flat = np.asarray(points_world, dtype=float).reshape(-1, 3)
        camera = transform_points(invert_transform(self.pose_world_camera), flat)
        z = camera[:, 2]
        k = self.intrinsics
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.rint(k.fx * camera[:, 0] / z + k.cx)
            v = np.rint(k.fy * camera[:, 1] / z + k.cy)
        inside = (z > 0) & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
        return z, inside, v[inside].astype(np.intp), u[inside].astype(np.intp)

    def judge(self, points_world: ArrayLike) -> SeenPoints:
        """What the camera saw of points (..., 3), from one projection (:class:`SeenPoints`)."""
        shape = np.shape(points_world)[:-1]
        z, inside, v, u = self._project(points_world)
        nearest = self.nearest_depth_m[v, u]  # inf where no return: nothing is in front of it
        returned, z_seen = np.isfinite(nearest), z[inside]
        empty = np.zeros(len(z), bool)
        empty[inside] = self.empty_ray[v, u] | (returned & (z_seen < nearest - DEPTH_MARGIN_M))
        hidden = ~inside
        hidden[inside] = np.where(
            returned, z_seen > nearest + DEPTH_MARGIN_M, ~self.empty_ray[v, u]
        )
        ahead = np.zeros(len(z))
        ahead[inside] = np.where(returned, np.maximum(nearest - z_seen, 0.0), 0.0)
        return SeenPoints(empty.reshape(shape), hidden.reshape(shape), ahead.reshape(shape))

    def empty(self, points_world: ArrayLike) -> NDArray[np.bool_]:
        """:attr:`SeenPoints.empty` of the points."""
        return self.judge(points_world).empty

    def hidden(self, points_world: ArrayLike) -> NDArray[np.bool_]:
        """:attr:`SeenPoints.hidden` of the points."""
        return self.judge(points_world).hidden


def seen_silhouette(
    predicted: NDArray[np.bool_],
    depth_m: NDArray[np.floating] | None,
    intrinsics: CameraIntrinsics,
    pose_world_camera: np.ndarray,
    grid: VoxelGrid,
) -> NDArray[np.bool_]:
    """Where the object is seen: the sketch net's silhouette ``predicted``; with depth, the
    pixels whose return stands above the table in ``grid``'s box, and the predicted silhouette
    only where no return is near (a return on the table shows no object there)."""
    if depth_m is None:
        return np.asarray(predicted, dtype=bool)
    returned = ndimage.maximum_filter(np.asarray(depth_m) > 0, size=3)
    above = depth_silhouette(depth_m, intrinsics, pose_world_camera, grid)
    return above | (np.asarray(predicted, dtype=bool) & ~returned)


def seen_empty_voxels(
    grid: VoxelGrid,
    crop: GridCrop,
    pose_world_camera: np.ndarray,
    silhouette: NDArray[np.bool_],
    depth_m: NDArray[np.floating] | None = None,
) -> NDArray[np.bool_]:
    """(N, N, N) True where the camera saw ``grid``'s voxel (its centre) empty, from the
    silhouette and depth on the crop's pixels (:class:`CameraView`)."""
    view = CameraView.from_image(
        crop.intrinsics, pose_world_camera, silhouette=silhouette, depth_m=depth_m
    )
    return view.empty(grid.voxel_centres_world())


def carve(probabilities: np.ndarray, seen_empty: NDArray[np.bool_]) -> np.ndarray:
    """``probabilities`` capped at :data:`SEEN_EMPTY_PROBABILITY` where the camera saw empty."""
    return np.where(
        seen_empty, np.minimum(probabilities, SEEN_EMPTY_PROBABILITY), probabilities
    ).astype(np.float32)
