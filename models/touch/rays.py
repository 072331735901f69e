"""Ray casting through a voxel probability volume: the rays the active touch policy scores.

For every approach direction (yaw every 90 degrees about the voxel grid's vertical axis, elevation
every 10 degrees from -90 to 90) a grid of parallel rays is cast along the approach direction;
each ray (grid point) gets the confidence ``|v - 0.5|`` of its *probe voxel*:

* the first voxel with ``v >= 0.5`` it meets (the predicted surface), or
* for a ray that misses the predicted shape, its most probable voxel (largest ``v`` on the ray):
  confidence ``0.5 - max v``, so a ray grazing an uncertain region still counts as uncertain
  while one through confident free space gets nearly the maximum, 0.5;
* a ray that crosses no voxel at all gets 0.5.

Ray grid: the directions all lie in vertical planes spanned by a horizontal voxel axis (a_x or
a_y) and a_z, so a ray stays in one voxel slice of the other horizontal axis. Rays are sampled
once per voxel along their major axis (the nearest voxel of each slice, like a DDA line), which
makes the grid spacing 1 voxel across slices and cos/sin(elevation) voxels within them. The two
opposite directions of a line family share one gather of the volume, and only the block of
voxels with v >= 1/254 is gathered (rays outside it see nothing but v < 1/254: misses whose
values are known). See docs/touch.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cache, lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def quantise(voxels: NDArray[np.float32]) -> NDArray[np.uint8]:
    """1 + floor(254 v) in [1, 255]: exact for the surface test (q >= 128 iff v >= 0.5), 0 is
    left for samples outside the grid, and a byte per sample keeps the ray gathers cheap."""
    return (1 + np.floor(np.clip(voxels, 0.0, 1.0) * 254)).astype(np.uint8)


_Q_SURFACE = 128


@dataclass(frozen=True)
class LineFamily:
    """Parallel lines in the (a, k) plane of an N^3 grid with direction (cos t, sin t).

    ``rows[u, l]``: flat index a * N + k of the voxel sample l of line u (N * N = outside), l
    increasing along the line direction; ``along[u, l]``: that sample's coordinate along the line
    direction (voxels); ``anchor[u]``: a point (a, k) of line u; ``spacing``: distance between
    neighbouring lines (voxels); ``has_voxel[u]``: line u crosses the grid; ``first_inside[u]``
    / ``last_inside[u]``: its first and last sample inside the grid.
    """

    direction: FloatArray
    rows: NDArray[np.intp]
    along: FloatArray
    anchor: FloatArray
    spacing: float
    has_voxel: NDArray[np.bool_]
    first_inside: NDArray[np.intp]
    last_inside: NDArray[np.intp]


@lru_cache(maxsize=128)
def _line_family(resolution: int, elevation_deg: int) -> LineFamily:
    n = resolution
    angle = math.radians(elevation_deg)
    cos, sin = math.cos(angle), math.sin(angle)
    major_is_a = abs(cos) >= abs(sin)
    slope = sin / cos if major_is_a else cos / sin  # minor-axis change per major-axis voxel
    margin = math.ceil(n / 2 * abs(slope) - 1e-9)  # cos(90 deg) is 6e-17, not 0
    intercepts = np.arange(-margin, n + margin) + 0.5  # minor coordinate at the grid's mid-plane
    major = np.arange(n) + 0.5
    if not major_is_a and sin < 0:
        major = major[::-1]  # keep samples ordered along +direction
    minor = intercepts[:, None] + (major[None, :] - n / 2) * slope
    minor_index = np.floor(minor).astype(np.intp)
    major_index = np.broadcast_to(np.floor(major).astype(np.intp), minor_index.shape)
    a, k = (major_index, minor_index) if major_is_a else (minor_index, major_index)
    inside = (minor_index >= 0) & (minor_index < n)
    rows = np.where(inside, a * n + k, n * n)
    points_a, points_k = (major[None, :], minor) if major_is_a else (minor, major[None, :])
    along = np.ascontiguousarray(np.broadcast_to(points_a * cos + points_k * sin, rows.shape))
    mid = np.full_like(intercepts, n / 2)
    anchor = np.stack((mid, intercepts) if major_is_a else (intercepts, mid), axis=1)
    spacing = max(abs(cos), abs(sin))
    first_inside = inside.argmax(axis=1)
    last_inside = inside.shape[1] - 1 - inside[:, ::-1].argmax(axis=1)
    return LineFamily(
        np.array([cos, sin]),
        rows,
        along,
        anchor,
        spacing,
        inside.any(axis=1),
        first_inside,
        last_inside,
    )


@dataclass(frozen=True)
class RayPlane:
    """The rays of one approach direction: a line family traversed from one of its ends."""

    axis: str  # "x": lines in (a, k) = (i, k) slices, b = j; "y": (a, k) = (j, k), b = i
    family: LineFamily
    yaw_deg: float
    elevation_deg: float
    sign: float  # +1: the sensor moves along +family.direction; depth = sign * along
    confidence: NDArray[np.float32]  # (U, B) confidence of each ray's probe voxel
    hit_depth: FloatArray  # (U, B) depth (voxels along the approach) of the first surface voxel
    # met, inf for a miss
    miss_depth: Callable[[], FloatArray]  # (U, B) depth of each ray's most probable voxel, inf
    # without a voxel; computed on demand (a pass over the block shared by both ends)


@dataclass(frozen=True)
class _Layout:
    """The volume for one line-family axis as rows (a * N + k) of the b axis, plus a last row
    for samples outside the grid. Only the block of voxels with q >= 2 (v >= 1/254) needs ray
    casting: any other voxel has q = 1, so rays elsewhere are misses whose peak is known."""

    quantised_rows: NDArray[np.uint8]  # (N * N + 1, b_hi - b_lo): the block's b range
    value_rows: NDArray[np.float32]  # (N * N + 1, N)
    active: NDArray[np.bool_]  # (N * N + 1,): some b of this (a, k) has q >= 2
    b_range: tuple[int, int]


def _layout(quantised: NDArray[np.uint8], voxels: NDArray[np.float32], axis: str) -> _Layout:
    n = voxels.shape[0]
    # For the a_x family a = i, b = j; for the a_y family a = j, b = i.
    order = (0, 2, 1) if axis == "x" else (1, 2, 0)
    q = quantised.transpose(order).reshape(n * n, n)
    active = q >= 2
    columns = np.flatnonzero(active.any(axis=0))
    b_lo, b_hi = (int(columns[0]), int(columns[-1]) + 1) if columns.size else (0, 0)
    outside_u8 = np.zeros((1, b_hi - b_lo), np.uint8)
    outside_f32 = np.zeros((1, n), np.float32)
    return _Layout(
        np.concatenate([q[:, b_lo:b_hi], outside_u8]),
        np.concatenate([voxels.transpose(order).reshape(n * n, n), outside_f32]),
        np.append(active.any(axis=1), False),
        (b_lo, b_hi),
    )


def _first_last(mask: NDArray[np.bool_]) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """First and last l with mask[u, l, b] for every (u, b) of a (U, L, B) mask; -1 if none.

    The largest of (L - l) resp. (l + 1) over the mask's samples (0 = none), by elementwise
    maxima: much cheaper than an argmax along a middle, strided axis.
    """
    length = mask.shape[1]
    dtype = np.uint8 if length < 255 else np.uint16
    index = np.arange(length, dtype=dtype)[None, :, None]
    first_key = _max_over_axis1(np.multiply(mask, length - index, dtype=dtype)).astype(np.intp)
    last_key = _max_over_axis1(np.multiply(mask, index + 1, dtype=dtype)).astype(np.intp)
    return np.where(first_key > 0, length - first_key, -1), last_key - 1


def _cast(
    axis: str, family: LineFamily, layout: _Layout, elevation_deg: int
) -> tuple[RayPlane, RayPlane]:
    """Probe every ray of a line family from both ends (the two opposite approach directions)."""
    n_lines = family.rows.shape[0]
    n_columns = layout.value_rows.shape[1]
    # Outside the active block every in-grid sample has q = 1: rays there are misses with peak 1
    # (0 for a line that misses the grid) and meet their most probable voxel first thing.
    line_peak = family.has_voxel.astype(np.uint8)[:, None]
    peak = np.repeat(line_peak, n_columns, axis=1)
    first = np.full((n_lines, n_columns), -1, np.intp)  # first surface sample along +direction
    last = first.copy()  # ... and along -direction
    active = layout.active[family.rows]
    active_lines = np.flatnonzero(active.any(axis=1))
    active_samples = np.flatnonzero(active.any(axis=0))
    block = block_peak = None
    if active_lines.size:
        l_lo = active_samples[0]
        in_block = (slice(active_lines[0], active_lines[-1] + 1), slice(*layout.b_range))
        block_rows = family.rows[in_block[0], l_lo : active_samples[-1] + 1]
        block = np.take(layout.quantised_rows, block_rows, axis=0)  # (U', L', B')
        block_peak = np.maximum(_max_over_axis1(block), line_peak[in_block[0]])
        peak[in_block] = block_peak
        block_first, block_last = _first_last(block >= _Q_SURFACE)
        first[in_block] = np.where(block_first >= 0, block_first + l_lo, -1)
        last[in_block] = np.where(block_last >= 0, block_last + l_lo, -1)

    # Misses: 0.5 - max v, with max v taken at the middle of its quantisation bin (+-1/508).
    peak_v = (peak.astype(np.float32) - 0.5) / 254.0
    miss_confidence = np.where(peak > 0, 0.5 - peak_v, 0.5).astype(np.float32)
    lines = np.arange(n_lines)[:, None]
    columns = np.arange(n_columns)[None, :]

    @cache
    def peak_samples() -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """First / last sample of each ray holding its peak: a sensor meets the nearest of
        equally probable voxels first. With peak 1 that is the line's first in-grid sample."""
        first_peak = np.repeat(family.first_inside[:, None], n_columns, axis=1)
        last_peak = np.repeat(family.last_inside[:, None], n_columns, axis=1)
        if block is not None:
            block_first_peak, block_last_peak = _first_last(block == block_peak[:, None, :])
            above_one = block_peak > 1
            first_peak[in_block] = np.where(
                above_one, block_first_peak + l_lo, first_peak[in_block]
            )
            last_peak[in_block] = np.where(above_one, block_last_peak + l_lo, last_peak[in_block])
        return first_peak, last_peak

    def miss_depth(sign: float) -> Callable[[], FloatArray]:
        def depth() -> FloatArray:
            index = peak_samples()[0 if sign > 0 else 1]
            return np.where(peak > 0, sign * family.along[lines, index], np.inf)

        return depth

    planes = []
    for sign, probe in ((1.0, first), (-1.0, last)):
        hit = probe >= 0
        probe = np.maximum(probe, 0)
        value = layout.value_rows[family.rows[lines, probe], columns]
        conf = np.where(hit, np.abs(value - 0.5), miss_confidence).astype(np.float32)
        # The sensor at the - end moves along +direction; the elevation it comes from flips.
        from_plus_end = sign < 0
        yaw = (0.0 if axis == "x" else 90.0) + (0.0 if from_plus_end else 180.0)
        elevation = float(elevation_deg if from_plus_end else -elevation_deg)
        hit_depth = np.where(hit, sign * family.along[lines, probe], np.inf)
        planes.append(
            RayPlane(axis, family, yaw, elevation, sign, conf, hit_depth, miss_depth(sign))
        )
    return planes[0], planes[1]


def _max_over_axis1(values: NDArray) -> NDArray:
    """``values.max(axis=1)`` of a (U, L, B) array by halving L: contiguous elementwise maxima
    vectorise far better than numpy's reduction over a middle axis."""
    while values.shape[1] > 1:
        half = values.shape[1] // 2
        folded = np.maximum(values[:, :half], values[:, half : 2 * half])
        if values.shape[1] % 2:
            folded[:, 0] = np.maximum(folded[:, 0], values[:, -1])
        values = folded
    return values[:, 0]


def ray_planes(voxels: NDArray[np.float32], elevations_deg: Sequence[int]) -> list[RayPlane]:
    """The rays of every approach direction at ``elevations_deg`` (yaws 0, 90, 180, 270; the
    vertical directions once each) through an (N, N, N) volume of probabilities."""
    n = voxels.shape[0]
    quantised = quantise(voxels)
    out: list[RayPlane] = []
    for axis in ("x", "y"):
        layout = _layout(quantised, voxels, axis)
        for elevation in elevations_deg:
            if abs(elevation) >= 90 and (axis == "y" or elevation < 0):
                continue  # vertical lines: one family serves from-above and from-below
            out += _cast(axis, _line_family(n, int(elevation)), layout, int(elevation))
    return out


def plane_to_voxel(axis: str, points_ak: FloatArray, b: ArrayLike) -> FloatArray:
    """(a, k) plane points (M, 2) and b coordinates -> continuous voxel coordinates (M, 3)."""
    b = np.broadcast_to(np.asarray(b, dtype=float), len(points_ak))
    if axis == "x":
        return np.stack([points_ak[:, 0], b, points_ak[:, 1]], axis=1)
    return np.stack([b, points_ak[:, 0], points_ak[:, 1]], axis=1)
