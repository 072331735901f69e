"""The "virtual camera": a square crop of the camera image around the registered voxel grid.

The networks see a square crop around the projection of the voxel grid's 3D box, resized to the
preset's resolution. A crop of a pinhole image is itself a pinhole camera with a shifted principal
point and a scaled focal length, so one :class:`GridCrop` serves both sides:

* training data: :func:`models.render.render` renders directly with ``crop.intrinsics``;
* inference: :func:`crop_image` resamples a real or bench frame to the same pixels.

Pixel coordinates follow the renderer (pixel centres at integers, the image edge at -0.5). Crop
pixel u' covers full-image coordinates [e + u' s, e + (u' + 1) s) with e the crop's left edge and s
full-image pixels per crop pixel, so ``fx' = fx / s`` and ``cx' = (cx - e) / s - 0.5``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage

from models.camera import CameraIntrinsics
from models.geometry import VoxelGrid, invert_transform, transform_points

CROP_MARGIN = 0.04
"""Fraction of the grid box's projected size added on each side of the crop."""


@dataclass(frozen=True)
class GridCrop:
    """A square crop of a full camera image around a voxel grid, as a pinhole camera.

    ``left_px``/``top_px`` are the crop's outer edge in full-image pixel coordinates,
    ``scale`` full-image pixels per crop pixel. ``z_ref_m`` is the camera z-depth (metres) of the
    grid's centre, used to normalise depth to "nearness" ``1 + (z_ref - z) / extent_m``.
    """

    intrinsics: CameraIntrinsics
    left_px: float
    top_px: float
    scale: float
    z_ref_m: float
    extent_m: float

    def nearness(self, depth_m: np.ndarray) -> np.ndarray:
        """z-depth (metres, 0 = no return) -> float32 nearness; 0 stays 0 (no return)."""
        depth = np.asarray(depth_m, dtype=np.float32)
        near = 1.0 + (self.z_ref_m - depth) / self.extent_m
        return np.where(depth > 0, near, 0.0).astype(np.float32)

    def depth_m(self, nearness: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`nearness` (metres); nearness 0 stays 0."""
        near = np.asarray(nearness, dtype=np.float32)
        depth = self.z_ref_m - (near - 1.0) * self.extent_m
        return np.where(near != 0, depth, 0.0).astype(np.float32)


def grid_crop(
    full_intrinsics: CameraIntrinsics,
    pose_world_camera: np.ndarray,
    grid: VoxelGrid,
    size_px: int,
    *,
    margin: float = CROP_MARGIN,
) -> GridCrop:
    """The crop (``size_px`` square) around the projection of ``grid``'s box in the full image.

    The crop may extend past the full image; :func:`crop_image` pads such pixels.
    """
    n = grid.resolution
    corners_voxel = np.array([[i, j, k] for i in (0, n) for j in (0, n) for k in (0, n)], float)
    pose_camera_world = invert_transform(pose_world_camera)
    corners_camera = transform_points(pose_camera_world, grid.voxel_to_world(corners_voxel))
    if np.any(corners_camera[:, 2] <= 0.0):
        raise ValueError("the voxel grid is not entirely in front of the camera")
    u = full_intrinsics.fx * corners_camera[:, 0] / corners_camera[:, 2] + full_intrinsics.cx
    v = full_intrinsics.fy * corners_camera[:, 1] / corners_camera[:, 2] + full_intrinsics.cy
    side = max(np.ptp(u), np.ptp(v)) * (1.0 + 2.0 * margin)
    left = 0.5 * (u.min() + u.max()) - 0.5 * side
    top = 0.5 * (v.min() + v.max()) - 0.5 * side
    scale = side / size_px
    intrinsics = CameraIntrinsics(
        width=size_px,
        height=size_px,
        fx=full_intrinsics.fx / scale,
        fy=full_intrinsics.fy / scale,
        cx=(full_intrinsics.cx - left) / scale - 0.5,
        cy=(full_intrinsics.cy - top) / scale - 0.5,
    )
    centre_camera = transform_points(
        pose_camera_world, grid.voxel_to_world(np.array([n / 2.0, n / 2.0, n / 2.0]))
    )
    return GridCrop(
        intrinsics, float(left), float(top), float(scale), float(centre_camera[2]), grid.extent_m
    )


def crop_image(image: np.ndarray, crop: GridCrop, *, nearest: bool = False) -> np.ndarray:
    """Resample a full image (H, W) or (H, W, C) to the crop's pixels; same dtype as the input.

    Colour uses area averaging down to about the crop's scale then bilinear sampling (no
    aliasing); ``nearest`` samples the nearest pixel without mixing (for depth, where averaging
    across an edge would invent surfaces). Outside the image: edge colour, or 0 with ``nearest``.
    """
    array = np.asarray(image)
    squeeze = array.ndim == 2
    tensor = torch.from_numpy(np.ascontiguousarray(array if not squeeze else array[..., None]))
    tensor = tensor.permute(2, 0, 1)[None].float()
    factor = 1 if nearest else max(1, math.floor(crop.scale))
    if factor > 1:
        tensor = F.avg_pool2d(tensor, factor)
    size = crop.intrinsics.width
    centres = (np.arange(size) + 0.5) * crop.scale  # crop pixel centres from the crop's edge
    # Full-image coordinates -> pooled coordinates (pooled pixel p is centred at p f + (f-1)/2).
    x = (crop.left_px + centres - (factor - 1) / 2.0) / factor
    y = (crop.top_px + centres - (factor - 1) / 2.0) / factor
    height, width = tensor.shape[-2:]
    gx = torch.as_tensor((2.0 * x + 1.0) / width - 1.0, dtype=torch.float32)
    gy = torch.as_tensor((2.0 * y + 1.0) / height - 1.0, dtype=torch.float32)
    grid = torch.stack(torch.meshgrid(gx, gy, indexing="xy"), dim=-1)[None]
    sampled = F.grid_sample(
        tensor,
        grid,
        mode="nearest" if nearest else "bilinear",
        padding_mode="zeros" if nearest else "border",
        align_corners=False,
    )[0].permute(1, 2, 0)
    result = sampled.numpy()
    if squeeze:
        result = result[..., 0]
    if np.issubdtype(array.dtype, np.integer):
        result = np.clip(np.rint(result), np.iinfo(array.dtype).min, np.iinfo(array.dtype).max)
    return result.astype(array.dtype)


SENSOR_NORMALS_SMOOTH_PX = 1.0
"""Gaussian smoothing (crop pixels) of the sensor's depth before its normals are taken: a crop
pixel spans ~2.5 mm, about the Kinect's noise, so unsmoothed normals would be mostly noise."""
SENSOR_NORMALS_EDGE_BEND = 0.02
"""A return further than this fraction of the grid's extent (5 mm of the 26 cm cube) from the
line through its two neighbours (along a row or a column) sits on a depth edge (a rim, the
object against the table), where a slope alone bends nothing: it is left out of the smoothing and
gets no normal, so no normal mixes two surfaces."""
_CROSS = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], dtype=bool)


def sensor_normals_camera(depth_m: np.ndarray, crop: GridCrop) -> tuple[np.ndarray, np.ndarray]:
    """Unit camera-frame normals (H, W, 3), turned toward the camera as the sketches' are, from
    the crop's sensor depth (z metres, 0 = no return), and where they are known (H, W): away
    from depth edges, with returns on all four sides."""
    depth = np.asarray(depth_m, dtype=np.float64)
    returned = depth > 0
    padded_depth = np.pad(depth, 1)
    bend_u = np.abs(padded_depth[1:-1, 2:] + padded_depth[1:-1, :-2] - 2.0 * depth)
    bend_v = np.abs(padded_depth[2:, 1:-1] + padded_depth[:-2, 1:-1] - 2.0 * depth)
    edge = np.maximum(bend_u, bend_v) > 2.0 * SENSOR_NORMALS_EDGE_BEND * crop.extent_m
    smooth_support = returned & ~edge
    # Normalised convolution over the support: holes and edges neither pull the depth nor spread.
    weight = ndimage.gaussian_filter(smooth_support.astype(float), SENSOR_NORMALS_SMOOTH_PX)
    total = ndimage.gaussian_filter(np.where(smooth_support, depth, 0.0), SENSOR_NORMALS_SMOOTH_PX)
    smooth = np.where(smooth_support, total / np.maximum(weight, 1e-6), 0.0)
    k = crop.intrinsics
    v, u = np.mgrid[0 : depth.shape[0], 0 : depth.shape[1]].astype(float)
    points = np.stack([(u - k.cx) / k.fx * smooth, (v - k.cy) / k.fy * smooth, smooth], axis=-1)
    padded = np.pad(points, ((1, 1), (1, 1), (0, 0)))
    along_u = padded[1:-1, 2:] - padded[1:-1, :-2]
    along_v = padded[2:, 1:-1] - padded[:-2, 1:-1]
    # x right, y down, z forward: u x v points away from the camera; v x u toward it.
    normals = np.cross(along_v, along_u)
    length = np.linalg.norm(normals, axis=-1)
    known = ndimage.minimum_filter(smooth_support.astype(np.uint8), footprint=_CROSS) > 0
    known &= length > 0
    normals = np.where(known[..., None], normals / np.maximum(length, 1e-12)[..., None], 0.0)
    return normals.astype(np.float32), known
