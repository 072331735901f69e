"""Where to touch next: the paper's active policy, the random baseline and the oracle helper.

Active policy (paper, Sec. "Policy for Active Tactile Exploration"): the confidence of a voxel is
``c = |v - 0.5|``. For every approach direction (yaw every 90 degrees about the voxel grid's
vertical axis, elevation every 10 degrees from -90 to 90) a grid of parallel rays is cast along
the approach direction; each ray (grid point) gets the confidence of its *probe voxel*:

* the first voxel with ``v >= 0.5`` it meets (the predicted surface), or
* for a ray that misses the predicted shape, its most probable voxel (largest ``v`` on the ray):
  confidence ``0.5 - max v``, so a ray grazing an uncertain region still counts as uncertain
  while one through confident free space gets nearly the maximum, 0.5;
* a ray that crosses no voxel at all gets 0.5.

An integral image of the ray confidences gives the summed confidence of every sensor-sized window
in O(1) each, so the least confident window of a plane is found in O(rays) = O(N^2). The target
is the window centre at the depth where a flat pad moving along the approach direction first
meets the predicted surface in that window (its nearest hit probe; a window without hits uses
its nearest probe).

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

from models.geometry import VoxelGrid, frame_from_z_axis

FloatArray = NDArray[np.float64]

TargetFilter = Callable[[FloatArray, FloatArray], NDArray[np.bool_]]
"""(targets_world (M, 3), approach_direction_world (3,)) -> feasible (M,) bool.

Vectorised over targets so the policy can check all windows of a plane in one call; compose
reachability (arm IK) and :func:`above_table_filter` in it."""

YAWS_DEG = (0, 90, 180, 270)
ELEVATIONS_DEG = tuple(range(-90, 91, 10))
DEFAULT_WINDOW_M = 0.014
"""Sensor window edge: the pad's short side (19 x 14 mm), so the pad covers it at any roll."""


@dataclass(frozen=True)
class TouchCandidate:
    """A touch to make: move the pad along ``approach_direction_world`` through ``target_world``.

    ``target_world`` (metres) is where the pad centre meets the predicted surface; the executor
    starts a standoff before it and strokes past it. ``score`` is the window's summed confidence
    (lower = less certain; NaN for the random policy). ``yaw_deg`` / ``elevation_deg`` locate
    where the sensor comes from (voxel frame: yaw 0 = from +a_x, the camera side; elevation 90 =
    from above). ``window_corners_world`` (4, 3) outline the searched window on the pad plane.
    """

    target_world: FloatArray
    approach_direction_world: FloatArray
    score: float
    yaw_deg: float
    elevation_deg: float
    window_corners_world: FloatArray


def confidence(voxels: ArrayLike) -> NDArray[np.float32]:
    """The paper's per-voxel confidence |v - 0.5| (0 = most uncertain, 0.5 = certain)."""
    return np.abs(np.asarray(voxels, dtype=np.float32) - 0.5)


def approach_direction_voxel(yaw_deg: float, elevation_deg: float) -> FloatArray:
    """Unit approach direction (sensor motion) in voxel axes for a sensor coming from
    (yaw, elevation): it moves along minus the direction it comes from."""
    yaw, elevation = math.radians(yaw_deg), math.radians(elevation_deg)
    from_direction = np.array(
        [
            math.cos(elevation) * math.cos(yaw),
            math.cos(elevation) * math.sin(yaw),
            math.sin(elevation),
        ]
    )
    return -from_direction


def policy_directions() -> list[tuple[float, float]]:
    """(yaw_deg, elevation_deg) of the 70 approach directions the active policy searches:
    every yaw and elevation, with straight down and straight up once each."""
    slanted = [(y, e) for y in YAWS_DEG for e in ELEVATIONS_DEG if abs(e) < 90]
    return [(float(y), float(e)) for y, e in slanted] + [(0.0, 90.0), (180.0, -90.0)]


def integral_image(values: ArrayLike) -> FloatArray:
    """G with G[p, q] = sum of values[:p, :q] (a zero first row and column), float64."""
    values = np.asarray(values, dtype=np.float64)
    integral = np.zeros((values.shape[0] + 1, values.shape[1] + 1))
    np.cumsum(np.cumsum(values, axis=0), axis=1, out=integral[1:, 1:])
    return integral


def window_sums(values: ArrayLike, rows: int, cols: int) -> FloatArray:
    """Sum of every rows x cols window of a 2D array, (H - rows + 1, W - cols + 1), via the
    integral image: S[p, q] = G[p+r, q+c] - G[p, q+c] - G[p+r, q] + G[p, q]."""
    g = integral_image(values)
    return g[rows:, cols:] - g[:-rows, cols:] - g[rows:, :-cols] + g[:-rows, :-cols]


def _quantise(voxels: NDArray[np.float32]) -> NDArray[np.uint8]:
    """1 + floor(254 v) in [1, 255]: exact for the surface test (q >= 128 iff v >= 0.5), 0 is
    left for samples outside the grid, and a byte per sample keeps the ray gathers cheap."""
    return (1 + np.floor(np.clip(voxels, 0.0, 1.0) * 254)).astype(np.uint8)


_Q_SURFACE = 128


@dataclass(frozen=True)
class _LineFamily:
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
def _line_family(resolution: int, elevation_deg: int) -> _LineFamily:
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
    return _LineFamily(
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
class _Plane:
    """The rays of one approach direction: a line family traversed from one of its ends."""

    axis: str  # "x": lines in (a, k) = (i, k) slices, b = j; "y": (a, k) = (j, k), b = i
    family: _LineFamily
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
    axis: str, family: _LineFamily, layout: _Layout, elevation_deg: int
) -> tuple[_Plane, _Plane]:
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
        planes.append(_Plane(axis, family, yaw, elevation, sign, conf, hit_depth, miss_depth(sign)))
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


def _planes(voxels: NDArray[np.float32], elevations_deg: Sequence[int]) -> list[_Plane]:
    """The rays of every approach direction."""
    n = voxels.shape[0]
    quantised = _quantise(voxels)
    out: list[_Plane] = []
    for axis in ("x", "y"):
        layout = _layout(quantised, voxels, axis)
        for elevation in elevations_deg:
            if abs(elevation) >= 90 and (axis == "y" or elevation < 0):
                continue  # vertical lines: one family serves from-above and from-below
            out += _cast(axis, _line_family(n, int(elevation)), layout, int(elevation))
    return out


def _plane_to_voxel(axis: str, points_ak: FloatArray, b: ArrayLike) -> FloatArray:
    """(a, k) plane points (M, 2) and b coordinates -> continuous voxel coordinates (M, 3)."""
    b = np.broadcast_to(np.asarray(b, dtype=float), len(points_ak))
    if axis == "x":
        return np.stack([points_ak[:, 0], b, points_ak[:, 1]], axis=1)
    return np.stack([b, points_ak[:, 0], points_ak[:, 1]], axis=1)


def _window_min(values: FloatArray, rows: int, cols: int) -> FloatArray:
    """Minimum over every rows x cols window of a 2D array (separable running minimum)."""
    out = values[: values.shape[0] - rows + 1]
    for offset in range(1, rows):
        out = np.minimum(out, values[offset : offset + out.shape[0]])
    result = out[:, : out.shape[1] - cols + 1]
    for offset in range(1, cols):
        result = np.minimum(result, out[:, offset : offset + result.shape[1]])
    return result


@dataclass(frozen=True)
class _Windows:
    """Summed confidence of every sensor window of a plane: ``sums[u0, b0]`` covers lines
    u0 .. u0 + rows - 1 and slices b0 .. b0 + cols - 1 (inf where no line crosses the grid)."""

    plane: _Plane
    sums: FloatArray
    rows: int
    cols: int


def _windows(plane: _Plane, voxel_m: float, window_m: float) -> _Windows:
    lines, columns = plane.confidence.shape
    rows = min(lines, max(1, round(window_m / (plane.family.spacing * voxel_m))))
    cols = min(columns, max(1, round(window_m / voxel_m)))
    sums = window_sums(plane.confidence, rows, cols)
    window_has_voxel = np.convolve(plane.family.has_voxel, np.ones(rows), mode="valid") > 0
    sums[~window_has_voxel] = np.inf
    return _Windows(plane, sums, rows, cols)


def _best_window(
    windows: _Windows, grid: VoxelGrid, feasible: TargetFilter | None, below: float = np.inf
) -> TouchCandidate | None:
    """Least confident feasible window of one plane among those scoring below ``below``."""
    plane, rows, cols = windows.plane, windows.rows, windows.cols
    family = plane.family
    flat = windows.sums.ravel()
    eligible = np.flatnonzero(flat < below)
    axes = np.asarray(grid.axes_world, dtype=float).T
    approach_2d = plane.sign * family.direction
    direction_world = axes @ _plane_to_voxel(plane.axis, approach_2d[None, :], 0.0)[0]
    # A flat pad over a window first meets the predicted surface at the window's nearest hit
    # probe; a window without hits uses its nearest miss probe (computed only when needed).
    depth = _window_min(plane.hit_depth, rows, cols)
    # Check feasibility on the lowest-scoring windows first, widening only while none passes.
    size = eligible.size
    for count in dict.fromkeys((min(32, size), min(1024, size), size)):
        chosen = eligible
        if count < size:
            chosen = eligible[np.argpartition(flat[eligible], count)[:count]]
        if not chosen.size:
            return None
        u0, b0 = np.divmod(chosen, windows.sums.shape[1])
        window_depth = depth[u0, b0]
        no_hit = ~np.isfinite(window_depth)
        if no_hit.any():
            miss_depth = _window_min(plane.miss_depth(), rows, cols)
            window_depth[no_hit] = miss_depth[u0[no_hit], b0[no_hit]]
        # Anchors are evenly spaced: the window's centre line lies midway between its extremes.
        anchor = 0.5 * (family.anchor[u0] + family.anchor[u0 + rows - 1])
        point_ak = anchor + (window_depth - anchor @ approach_2d)[:, None] * approach_2d
        targets_world = grid.voxel_to_world(_plane_to_voxel(plane.axis, point_ak, b0 + cols / 2))
        score = flat[chosen]
        if feasible is not None:
            score = np.where(feasible(targets_world, direction_world), score, np.inf)
        if np.isfinite(score.min()):
            break
    else:
        return None
    best = int(np.argmin(score))
    across = _plane_to_voxel(plane.axis, np.array([[-approach_2d[1], approach_2d[0]]]), 0.0)[0]
    b_axis = axes[:, 1] if plane.axis == "x" else axes[:, 0]
    half_u = 0.5 * rows * family.spacing * grid.voxel_size_m * (axes @ across)
    half_b = 0.5 * cols * grid.voxel_size_m * b_axis
    centre = targets_world[best]
    corners = np.array([centre + su * half_u + sb * half_b for su, sb in _CORNER_SIGNS])
    return TouchCandidate(
        centre, direction_world, float(score[best]), plane.yaw_deg, plane.elevation_deg, corners
    )


_CORNER_SIGNS = ((-1, -1), (1, -1), (1, 1), (-1, 1))


def _all_windows(
    voxels: ArrayLike, grid: VoxelGrid, window_m: float, elevations_deg: Sequence[int]
) -> list[_Windows]:
    volume = np.ascontiguousarray(voxels, dtype=np.float32)
    if volume.shape != (grid.resolution,) * 3:
        raise ValueError(f"volume {volume.shape} does not match the {grid.resolution}^3 grid")
    return [
        _windows(plane, grid.voxel_size_m, window_m) for plane in _planes(volume, elevations_deg)
    ]


def touch_candidates(
    voxels: ArrayLike,
    grid: VoxelGrid,
    feasible: TargetFilter | None = None,
    window_m: float = DEFAULT_WINDOW_M,
    elevations_deg: Sequence[int] = ELEVATIONS_DEG,
) -> list[TouchCandidate]:
    """The least confident feasible window of every approach direction, best (lowest) first.

    ``voxels``: (N, N, N) occupancy probabilities indexed [i, j, k] in ``grid``'s frame.
    ``elevations_deg``: multiples of 10 in [-90, 90]; yaws are 0, 90, 180, 270 (the vertical
    directions are searched once each). ``window_m``: sensor window edge, metres.
    """
    candidates = [
        _best_window(windows, grid, feasible)
        for windows in _all_windows(voxels, grid, window_m, elevations_deg)
    ]
    return sorted((c for c in candidates if c is not None), key=lambda c: c.score)


def select_touch(
    voxels: ArrayLike,
    grid: VoxelGrid,
    feasible: TargetFilter | None = None,
    window_m: float = DEFAULT_WINDOW_M,
    elevations_deg: Sequence[int] = ELEVATIONS_DEG,
) -> TouchCandidate | None:
    """The paper's active policy: the feasible sensor window of least summed confidence over
    all approach directions (arguments as :func:`touch_candidates`), or None if none is
    feasible. Planes are visited from the lowest window score up and only windows scoring
    below the best feasible one so far are checked (same score as ``touch_candidates()[0]``).
    """
    planes = _all_windows(voxels, grid, window_m, elevations_deg)
    best: TouchCandidate | None = None
    for windows in sorted(planes, key=lambda w: float(w.sums.min())):
        below = best.score if best is not None else np.inf
        if windows.sums.min() >= below:
            break
        candidate = _best_window(windows, grid, feasible, below)
        if candidate is not None:
            best = candidate
    return best


def above_table_filter(
    standoff_m: float, clearance_m: float = 0.01, table_z_m: float = 0.0
) -> TargetFilter:
    """Feasible when the target and the approach start (``standoff_m`` before the target along
    the approach) are both at least ``clearance_m`` above the table top (world z-up, metres)."""

    def feasible(targets_world: FloatArray, direction_world: FloatArray) -> NDArray[np.bool_]:
        start_z = targets_world[:, 2] - standoff_m * direction_world[2]
        lowest = np.minimum(targets_world[:, 2], start_z)
        return lowest >= table_z_m + clearance_m

    return feasible


def facing_surface_filter(voxels: ArrayLike, grid: VoxelGrid, max_angle_deg: float) -> TargetFilter:
    """Feasible when the approach is within ``max_angle_deg`` of the predicted surface's inward
    normal at the target, as the paper approaches "in the direction of the surface normal".

    The inward normal is the gradient of the probabilities (central differences at the voxel
    holding the target); where the prediction is flat it is undefined and every approach passes.
    """
    volume = np.asarray(voxels, dtype=np.float32)
    n = volume.shape[0]
    axes = np.asarray(grid.axes_world, dtype=float).T
    world_to_voxel = np.linalg.inv(grid.matrix_world_voxel)
    min_cosine = math.cos(math.radians(max_angle_deg))
    steps = np.eye(3, dtype=np.intp)

    def feasible(targets_world: FloatArray, direction_world: FloatArray) -> NDArray[np.bool_]:
        points = targets_world @ world_to_voxel[:3, :3].T + world_to_voxel[:3, 3]
        index = np.clip(np.floor(points).astype(np.intp), 1, n - 2)
        gradient = np.empty(index.shape)
        for axis, step in enumerate(steps):
            ahead, behind = (index + step).T, (index - step).T
            gradient[:, axis] = 0.5 * (volume[tuple(ahead)] - volume[tuple(behind)])
        inward = gradient @ axes.T  # probabilities grow into the object
        length = np.linalg.norm(inward, axis=1)
        cosine = (inward @ direction_world) / np.maximum(length, 1e-12)
        return (length < 1e-3) | (cosine >= min_cosine)

    return feasible


def not_repeated_filter(
    touches_world: Sequence[tuple[ArrayLike, ArrayLike]],
    radius_m: float,
    max_angle_deg: float = 10.0,
) -> TargetFilter:
    """Feasible unless an earlier touch (target, approach direction; world) aimed within
    ``radius_m`` of the target from within ``max_angle_deg`` of the same direction."""
    earlier = [
        (np.asarray(point, dtype=float), np.asarray(direction, dtype=float))
        for point, direction in touches_world
    ]
    min_cosine = math.cos(math.radians(max_angle_deg))

    def feasible(targets_world: FloatArray, direction_world: FloatArray) -> NDArray[np.bool_]:
        keep = np.ones(len(targets_world), dtype=bool)
        for point, direction in earlier:
            if float(direction @ direction_world) >= min_cosine:
                keep &= np.linalg.norm(targets_world - point, axis=1) >= radius_m
        return keep

    return feasible


def all_of(*filters: TargetFilter) -> TargetFilter:
    """A filter that passes where every one of ``filters`` passes."""

    def feasible(targets_world: FloatArray, direction_world: FloatArray) -> NDArray[np.bool_]:
        passed = np.ones(len(targets_world), bool)
        for check in filters:
            passed &= check(targets_world, direction_world)
        return passed

    return feasible


def predicted_bounding_box_world(
    voxels: ArrayLike, grid: VoxelGrid, threshold: float = 0.5
) -> tuple[FloatArray, FloatArray] | None:
    """World axis-aligned box (min, max corners, metres) of the voxels with v >= threshold, or
    None when there are none."""
    occupied = np.argwhere(np.asarray(voxels) >= threshold)
    if len(occupied) == 0:
        return None
    low, high = occupied.min(axis=0), occupied.max(axis=0) + 1
    corners = np.array(
        [
            [x, y, z]
            for x in (low[0], high[0])
            for y in (low[1], high[1])
            for z in (low[2], high[2])
        ],
        dtype=float,
    )
    world = grid.voxel_to_world(corners)
    return world.min(axis=0), world.max(axis=0)


def random_touch(
    box_min_world: ArrayLike,
    box_max_world: ArrayLike,
    grid: VoxelGrid,
    rng: np.random.Generator,
    feasible: TargetFilter | None = None,
    window_m: float = DEFAULT_WINDOW_M,
    max_tries: int = 1000,
) -> TouchCandidate | None:
    """The paper's Random Policy: a target uniform in the object's bounding box (world metres)
    and an approach direction drawn uniformly from the active policy's directions; redrawn until
    ``feasible`` accepts it (None after ``max_tries``). Directions: :func:`policy_directions`."""
    low, high = np.asarray(box_min_world, float), np.asarray(box_max_world, float)
    directions = policy_directions()
    axes = np.asarray(grid.axes_world, dtype=float).T
    for _ in range(max_tries):
        target = rng.uniform(low, high)
        yaw, elevation = directions[rng.integers(len(directions))]
        direction = axes @ approach_direction_voxel(yaw, elevation)
        if feasible is None or feasible(target[None, :], direction)[0]:
            frame = frame_from_z_axis(direction)
            half_u, half_b = 0.5 * window_m * frame[:, 0], 0.5 * window_m * frame[:, 1]
            corners = np.array([target + su * half_u + sb * half_b for su, sb in _CORNER_SIGNS])
            return TouchCandidate(target, direction, math.nan, yaw, elevation, corners)
    return None


def oracle_select(
    candidates: Sequence[TouchCandidate], error_after: Callable[[TouchCandidate], float]
) -> tuple[TouchCandidate, float]:
    """The benchmark's oracle (the paper's human upper bound): the candidate whose touch leaves
    the smallest shape error. ``error_after`` simulates the touch and the refinement with the
    ground truth and returns e.g. the Chamfer distance in mm; it is called once per candidate."""
    if not candidates:
        raise ValueError("the oracle needs at least one candidate")
    errors = [error_after(candidate) for candidate in candidates]
    best = int(np.argmin(errors))
    return candidates[best], float(errors[best])
