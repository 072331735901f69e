"""GelSight reconstruction: raw image + reference -> gradients -> height map -> contact geometry.

Per frame (:class:`TactileReconstructor`): the colour change image - reference selects, per
pixel, an entry of the position-aware table of :mod:`models.tactile.lut` (surface
gradients), and a Poisson solver by the discrete sine transform integrates the gradients into
the indentation height map. :func:`contact_geometry` turns the height map into points and the
mean contact normal in the pad frame, and in the world given ``pose_world_pad``.

Frames and units (docs/conventions.md): height maps are float32 millimetres of indentation,
>= 0, on the image grid. The pad frame has its origin at the undeformed gel centre, +z the
gel's outward normal toward the object, +x along image columns, +y along image rows; pixel
(r, c) sits at x = (c - (W-1)/2) * mm_per_px, y = (r - (H-1)/2) * mm_per_px, and an
indentation h means the object surface is at pad z = -h. World points are metres.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import scipy.fft
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from models.geometry import transform_directions, transform_points
from models.tactile.lut import (
    GelSightLUT,
    ImageBGR,
    check_image,
    colour_level_luts,
    tile_grid,
)

FloatImage = NDArray[np.float32]

# Contact = pixels indented at least this fraction of the frame's peak (and MIN_CONTACT_MM): on
# real ball presses the reconstructed gel at the annotated contact circle lies a little above
# this fraction of the peak, and the skirt outside falls off steeply.
CONTACT_FRACTION = 0.3
# Below this peak indentation a frame has no contact: above the height that the far field of
# real no-contact regions reconstructs to.
MIN_CONTACT_MM = 0.1
# An imprint reaching the border is solved with a free border: when at least
# BORDER_IMPRINT_PIXELS of the BORDER_STRIP_PX border strip slope by BORDER_IMPRINT_SLOPE or more,
# far more than lookup noise gives on no-contact frames and far fewer than an edge imprint.
BORDER_STRIP_PX = 8
BORDER_IMPRINT_SLOPE = 0.1
BORDER_IMPRINT_PIXELS = 500
# A free-border solve is known only up to its level and drifts at the imprint's shallow fringe,
# so its contact mask keeps only the deeper part of the imprint.
FREE_BORDER_CONTACT_FRACTION = 0.5
# Gentle slopes: a slope of 0.05 changes the colour by ~2 grey levels, inside the table's
# central bin (8 levels wide), which reads flat. Where the colour change, averaged over
# GENTLE_BLOCK_PX blocks and smoothed over GENTLE_SMOOTHING_PX, lies within half a bin on
# every channel, the slopes are read from it between the bins (trilinear): the averaging takes
# the camera noise (1.5 levels) down to ~0.1, so no-contact frames stay flat, and on blocks it
# costs a few milliseconds (docs/gelsight.md, "Gentle slopes").
GENTLE_BLOCK_PX = 4
GENTLE_SMOOTHING_PX = 6.0


class PoissonSolver:
    """Height from its gradients on an HxW grid: the 5-point Poisson equation by DST-II.

    The height is zero half a pixel outside the image (odd extension about the border), which
    is what the type-II sine transform diagonalises. Its lengths are the image's own, 480 and
    640 (2N = 960, 1280: products of 2, 3, 5), where the textbook DST-I on the (H-2)x(W-2)
    interior needs lengths whose 2(N+1) = 958 = 2 x 479 is prime, which is several times slower
    (timings in docs/gelsight.md). float32 throughout: float64 is slower again.
    """

    def __init__(self, shape: tuple[int, int], mm_per_px: float) -> None:
        height, width = shape
        eigen_rows = 2.0 * np.cos(np.pi * np.arange(1, height + 1) / height) - 2.0
        eigen_cols = 2.0 * np.cos(np.pi * np.arange(1, width + 1) / width) - 2.0
        # 0.5 of the central differences and the pixel pitch are folded into the spectrum.
        self._scale = (0.5 * mm_per_px / (eigen_rows[:, None] + eigen_cols[None, :])).astype(
            np.float32
        )
        self.shape = (height, width)

    def _divergence(
        self, grad_x: NDArray[np.float32], grad_y: NDArray[np.float32], border_sign: float
    ) -> NDArray[np.float32]:
        """Central-difference divergence; past the border the slope continues as
        ``border_sign`` times the border's own (+1: constant; -1: mirrored, zero flux)."""
        divergence = np.empty(self.shape, dtype=np.float32)
        np.subtract(grad_x[:, 2:], grad_x[:, :-2], out=divergence[:, 1:-1])
        divergence[:, 0] = grad_x[:, 1] - border_sign * grad_x[:, 0]
        divergence[:, -1] = border_sign * grad_x[:, -1] - grad_x[:, -2]
        divergence[1:-1] += grad_y[2:]
        divergence[1:-1] -= grad_y[:-2]
        divergence[0] += grad_y[1] - border_sign * grad_y[0]
        divergence[-1] += border_sign * grad_y[-1] - grad_y[-2]
        return divergence

    def solve(self, grad_x: NDArray[np.float32], grad_y: NDArray[np.float32]) -> FloatImage:
        """Height (mm, HxW float32) whose x/y slopes (dimensionless, per pixel) are given.

        The divergence uses central differences (no half-pixel shift), with the slope taken
        as constant past the image border.
        """
        divergence = self._divergence(grad_x, grad_y, 1.0)
        spectrum = scipy.fft.dstn(divergence, type=2, norm="ortho", overwrite_x=True, workers=1)
        spectrum *= self._scale
        return scipy.fft.idstn(spectrum, type=2, norm="ortho", overwrite_x=True, workers=1)


class FreeBorderPoissonSolver(PoissonSolver):
    """The same equation with a free border (zero normal slope past it: DCT-II), for an imprint
    that runs off the gel's edge, where a zero border would flatten it. The height is known up
    to a constant: the undeformed gel is taken as the ``level_percentile`` of the solution (the
    gel is only pushed in, and an edge imprint leaves most of the pad untouched)."""

    def __init__(
        self, shape: tuple[int, int], mm_per_px: float, level_percentile: float = 10.0
    ) -> None:
        height, width = shape
        eigen_rows = 2.0 * np.cos(np.pi * np.arange(height) / height) - 2.0
        eigen_cols = 2.0 * np.cos(np.pi * np.arange(width) / width) - 2.0
        denominator = eigen_rows[:, None] + eigen_cols[None, :]
        denominator[0, 0] = 1.0  # the constant term: set by the level below
        self._scale = (0.5 * mm_per_px / denominator).astype(np.float32)
        self._scale[0, 0] = 0.0
        self.shape = (height, width)
        self.level_percentile = level_percentile

    def solve(self, grad_x: NDArray[np.float32], grad_y: NDArray[np.float32]) -> FloatImage:
        divergence = self._divergence(grad_x, grad_y, -1.0)
        spectrum = scipy.fft.dctn(divergence, type=2, norm="ortho", overwrite_x=True, workers=1)
        spectrum *= self._scale
        height = scipy.fft.idctn(spectrum, type=2, norm="ortho", overwrite_x=True, workers=1)
        height -= np.float32(np.percentile(height, self.level_percentile))
        return height


@dataclass(frozen=True)
class TactileReconstruction:
    """One reconstructed frame: indentation height map and contact mask on the image grid."""

    height_mm: FloatImage
    contact_mask: NDArray[np.bool_]
    mm_per_px: float

    @property
    def peak_mm(self) -> float:
        """Deepest indentation (mm)."""
        return float(self.height_mm.max())


class HeightMapError(ValueError):
    """A height map that cannot be a measurement: wrong size, NaN or infinite values, or all
    zero although the gripper reported contact (a real one always holds sensor noise)."""


def check_height_map(
    height_mm: NDArray[np.floating], image_shape: tuple[int, int], *, contact: bool
) -> None:
    """Refuse a height map that cannot be a measurement of an ``image_shape`` frame
    (:class:`HeightMapError`, naming what is wrong)."""
    height = np.asarray(height_mm)
    if height.shape != tuple(image_shape):
        raise HeightMapError(
            f"height map is {height.shape}, the tactile image {tuple(image_shape)}"
        )
    if not np.all(np.isfinite(height)):
        raise HeightMapError(f"height map holds {int(np.sum(~np.isfinite(height)))} NaN/inf values")
    if contact and not np.any(height):
        raise HeightMapError("height map is all zero although the gripper reported contact")


class TactileReconstructor:
    """Reconstructs frames of one sensor session: a lookup table plus that session's
    reference.

    Construction prepares everything that does not change per frame (colour-level lookups,
    tile offsets, the Poisson spectrum), so a 640x480 frame costs about 10 ms on one thread
    (docs/gelsight.md, "Speed"). Frames must be uint8 BGR of the table's image size.
    """

    def __init__(self, lut: GelSightLUT, reference_bgr: ImageBGR) -> None:
        lut.validate()
        check_image(reference_bgr, "reference image", lut.image_shape)
        self.lut = lut
        level_lut, levels = colour_level_luts(lut.colour_step, lut.colour_limit)
        # The colour index is B * levels^2 + G * levels + R: one lookup per channel that already
        # carries its stride, then two integer additions.
        self._lut_b = level_lut * np.int32(levels * levels)
        self._lut_g = level_lut * np.int32(levels)
        self._lut_r = level_lut
        tiles, _, _ = tile_grid(lut.image_shape, lut.tile_px)
        self._tile_offset = tiles * np.int32(levels**3)
        self._levels = levels
        block = GENTLE_BLOCK_PX
        self._block_rows = -(-lut.image_shape[0] // block)
        self._block_cols = -(-lut.image_shape[1] // block)
        self._block_tile_offset = self._tile_offset[::block, ::block]
        # image + (255 - reference) = image - reference + 255 in [0, 510], the lookups' index.
        self._reference_shifted = 255 - reference_bgr.astype(np.int16)
        self._solver = PoissonSolver(lut.image_shape, lut.mm_per_px)
        self._free_border_solver = FreeBorderPoissonSolver(lut.image_shape, lut.mm_per_px)

    def gradients(self, image_bgr: ImageBGR) -> tuple[FloatImage, FloatImage]:
        """Indentation slopes dh/dx, dh/dy (dimensionless, x = columns, y = rows) per pixel."""
        check_image(image_bgr, "image", self.lut.image_shape)
        shifted = image_bgr + self._reference_shifted
        index = self._lut_b.take(shifted[..., 0])
        index += self._lut_g.take(shifted[..., 1])
        index += self._lut_r.take(shifted[..., 2])
        index += self._tile_offset
        grad_x, grad_y = self.lut.table_gx.take(index), self.lut.table_gy.take(index)
        gentle, gentle_x, gentle_y = self._gentle_slopes(shifted)
        return np.where(gentle, gentle_x, grad_x), np.where(gentle, gentle_y, grad_y)

    def _gentle_slopes(
        self, shifted: NDArray[np.int16]
    ) -> tuple[NDArray[np.bool_], FloatImage, FloatImage]:
        """Where the colour change is gentle (``GENTLE_BLOCK_PX``), and the slopes read there
        between the bins, on blocks repeated to the image's pixels. ``shifted`` is the lookups'
        index, image - reference + 255."""
        height, width = self.lut.image_shape
        block, rows, cols = GENTLE_BLOCK_PX, self._block_rows, self._block_cols
        if (rows * block, cols * block) != (height, width):
            pad = ((0, rows * block - height), (0, cols * block - width), (0, 0))
            shifted = np.pad(shifted, pad, mode="edge")
        # Block sums as sums of strided slices (rows, then columns): 10x faster than numpy's
        # reduction over the reshaped block axes. 16 values of at most 510 fit int16.
        row_sums = sum(shifted[offset::block] for offset in range(block))
        sums = sum(row_sums[:, offset::block] for offset in range(block))
        blocks = np.asarray(sums, dtype=np.float32) / np.float32(block * block) - np.float32(255)
        for channel in range(3):
            ndimage.gaussian_filter(
                blocks[..., channel],
                GENTLE_SMOOTHING_PX / block,
                output=blocks[..., channel],
                mode="nearest",
            )
        gentle = np.all(np.abs(blocks) < 0.5 * self.lut.colour_step, axis=-1)
        block_x = np.zeros((rows, cols), np.float32)
        block_y = np.zeros((rows, cols), np.float32)
        block_x[gentle], block_y[gentle] = self._between_bins(
            blocks[gentle], self._block_tile_offset[gentle]
        )

        def to_pixels(values: NDArray) -> NDArray:
            return values.repeat(block, axis=0).repeat(block, axis=1)[:height, :width]

        return to_pixels(gentle), to_pixels(block_x), to_pixels(block_y)

    def _between_bins(
        self, change: NDArray[np.float32], tile_offset: NDArray[np.int32]
    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """The table's slopes at colour changes (M, 3) in tiles ``tile_offset`` (M,), trilinear
        between the bins' centres (multiples of the colour step)."""
        levels, half = self._levels, self._levels // 2
        position = np.clip(change / self.lut.colour_step, -half, half) + half
        lower = np.minimum(np.floor(position).astype(np.int32), levels - 2)
        upper_weight = position - lower
        base = tile_offset + (lower[:, 0] * levels + lower[:, 1]) * levels + lower[:, 2]
        grad_x = np.zeros(len(change), np.float32)
        grad_y = np.zeros(len(change), np.float32)
        for corner in itertools.product((0, 1), repeat=3):
            weight = np.prod(
                np.where(corner, upper_weight, 1.0 - upper_weight), axis=1, dtype=np.float32
            )
            index = base + (corner[0] * levels + corner[1]) * levels + corner[2]
            grad_x += weight * self.lut.table_gx.take(index)
            grad_y += weight * self.lut.table_gy.take(index)
        return grad_x, grad_y

    def height_map_mm(self, image_bgr: ImageBGR) -> FloatImage:
        """Indentation (mm, HxW float32, >= 0) of the gel in ``image_bgr``."""
        return self._solve(image_bgr)[0]

    def reconstruct(self, image_bgr: ImageBGR) -> TactileReconstruction:
        """Height map and contact mask (see :func:`contact_mask`) of one frame."""
        height, free_border = self._solve(image_bgr)
        fraction = FREE_BORDER_CONTACT_FRACTION if free_border else CONTACT_FRACTION
        mask = contact_mask(height, fraction=fraction)
        return TactileReconstruction(height, mask, self.lut.mm_per_px)

    def _solve(self, image_bgr: ImageBGR) -> tuple[FloatImage, bool]:
        """Height map, and whether the imprint ran off the border (free-border solve): where
        steep slopes reach the border, or where the zero border leaves no contact and the
        free one does (a gentle press over much of the pad, crushed by a zero border)."""
        grad_x, grad_y = self.gradients(image_bgr)
        if imprint_at_border(grad_x, grad_y):
            return self._positive(self._free_border_solver.solve(grad_x, grad_y)), True
        height = self._positive(self._solver.solve(grad_x, grad_y))
        if height.max() < MIN_CONTACT_MM:
            free = self._positive(self._free_border_solver.solve(grad_x, grad_y))
            if free.max() >= MIN_CONTACT_MM:
                return free, True
        return height, False

    @staticmethod
    def _positive(height: FloatImage) -> FloatImage:
        """The gel is only pushed in: negative heights are noise and the boundary's doing."""
        return np.maximum(height, 0.0, out=height)


def imprint_at_border(
    grad_x: NDArray[np.float32],
    grad_y: NDArray[np.float32],
    *,
    border_px: int = BORDER_STRIP_PX,
    min_slope: float = BORDER_IMPRINT_SLOPE,
    min_pixels: int = BORDER_IMPRINT_PIXELS,
) -> bool:
    """Whether an imprint runs off the gel's edge: at least ``min_pixels`` pixels within
    ``border_px`` of the border slope by ``min_slope`` or more."""
    steep = (np.abs(grad_x) >= min_slope) | (np.abs(grad_y) >= min_slope)
    b = border_px
    count = steep[:b].sum() + steep[-b:].sum() + steep[b:-b, :b].sum() + steep[b:-b, -b:].sum()
    return int(count) >= min_pixels


def contact_mask(
    height_mm: FloatImage,
    *,
    fraction: float = CONTACT_FRACTION,
    min_depth_mm: float = MIN_CONTACT_MM,
) -> NDArray[np.bool_]:
    """Pixels in contact: indented >= ``fraction`` of the peak and >= ``min_depth_mm``.

    Relative to the frame's peak, which suits one contact (a press); an object pressed at very
    different depths in two places keeps only the deeper part.
    """
    peak = float(height_mm.max())
    if peak < min_depth_mm:
        return np.zeros(height_mm.shape, dtype=bool)
    return height_mm >= max(fraction * peak, min_depth_mm)


@dataclass(frozen=True)
class TactileContact:
    """Contact geometry of one frame in the pad frame (mm).

    ``normal_pad`` is the unit mean outward normal of the object's surface over the contact:
    it points from the object toward the sensor, (0, 0, -1) for a face pressed square on.
    """

    points_pad_mm: NDArray[np.float64]
    normal_pad: NDArray[np.float64]

    @property
    def centroid_pad_mm(self) -> NDArray[np.float64]:
        """Mean contact point (mm, pad frame)."""
        return self.points_pad_mm.mean(axis=0)

    def points_world_m(self, pose_world_pad: ArrayLike) -> NDArray[np.float64]:
        """Contact points (N, 3) in the world, metres."""
        return transform_points(pose_world_pad, self.points_pad_mm * 1e-3)

    def normal_world(self, pose_world_pad: ArrayLike) -> NDArray[np.float64]:
        """Mean contact normal (unit, object's outward) in the world."""
        return transform_directions(pose_world_pad, self.normal_pad)


def contact_geometry(
    height_mm: FloatImage,
    mask: NDArray[np.bool_],
    mm_per_px: float,
    *,
    stride_px: int = 1,
) -> TactileContact | None:
    """Contact points (every ``stride_px``-th pixel of ``mask``) and mean normal, or None.

    A pixel (r, c) with indentation h gives the object surface point
    ((c - (W-1)/2) * mm_per_px, (r - (H-1)/2) * mm_per_px, -h) in the pad frame; the normal of
    the surface z = -h(x, y) pointing out of the object is (-dh/dx, -dh/dy, -1), normalised.
    """
    if height_mm.shape != mask.shape:
        raise ValueError(f"height map {height_mm.shape} and mask {mask.shape} differ in size")
    if stride_px < 1:
        raise ValueError("stride_px must be >= 1")
    sampled = np.zeros_like(mask)
    sampled[::stride_px, ::stride_px] = mask[::stride_px, ::stride_px]
    rows, cols = np.nonzero(sampled)
    if rows.size == 0:
        return None
    rows_count, cols_count = height_mm.shape
    depth = height_mm[rows, cols].astype(np.float64)
    points = np.column_stack(
        [
            (cols - (cols_count - 1) / 2) * mm_per_px,
            (rows - (rows_count - 1) / 2) * mm_per_px,
            -depth,
        ]
    )
    slope_rows, slope_cols = np.gradient(height_mm.astype(np.float64), mm_per_px)
    normals = np.column_stack(
        [-slope_cols[rows, cols], -slope_rows[rows, cols], -np.ones(rows.size)]
    )
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    mean = normals.mean(axis=0)
    return TactileContact(points, mean / np.linalg.norm(mean))
