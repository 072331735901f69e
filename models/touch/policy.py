"""Where to touch next: the paper's active policy, the random baseline and the oracle helper.

Active policy (paper, Sec. "Policy for Active Tactile Exploration"): the confidence of a voxel is
``c = |v - 0.5|``. The rays of every approach direction (:mod:`models.touch.rays`) carry the
confidence of their probe voxel. An integral image of the ray confidences gives the summed
confidence of every sensor-sized window in O(1) each, so the least confident window of a plane is
found in O(rays) = O(N^2). The target is the window centre at the depth where a flat pad moving
along the approach direction first meets the predicted surface in that window (its nearest hit
probe; a window without hits uses its nearest probe). See docs/touch.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from models.geometry import VoxelGrid, frame_from_z_axis
from models.touch.rays import RayPlane, plane_to_voxel, ray_planes

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
    uncertainty: float = 1.0
    """1 - 2 x the window's mean confidence: 0 when every probe is certain (v = 0 or 1), 1 when
    every probe is at v = 0.5."""


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

    plane: RayPlane
    sums: FloatArray
    rows: int
    cols: int


def _windows(plane: RayPlane, voxel_m: float, window_m: float) -> _Windows:
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
    direction_world = axes @ plane_to_voxel(plane.axis, approach_2d[None, :], 0.0)[0]
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
        targets_world = grid.voxel_to_world(plane_to_voxel(plane.axis, point_ak, b0 + cols / 2))
        score = flat[chosen]
        if feasible is not None:
            score = np.where(feasible(targets_world, direction_world), score, np.inf)
        if np.isfinite(score.min()):
            break
    else:
        return None
    best = int(np.argmin(score))
    across = plane_to_voxel(plane.axis, np.array([[-approach_2d[1], approach_2d[0]]]), 0.0)[0]
    b_axis = axes[:, 1] if plane.axis == "x" else axes[:, 0]
    half_u = 0.5 * rows * family.spacing * grid.voxel_size_m * (axes @ across)
    half_b = 0.5 * cols * grid.voxel_size_m * b_axis
    centre = targets_world[best]
    corners = np.array([centre + su * half_u + sb * half_b for su, sb in _CORNER_SIGNS])
    uncertainty = 1.0 - 2.0 * float(score[best]) / (rows * cols)
    return TouchCandidate(
        centre,
        direction_world,
        float(score[best]),
        plane.yaw_deg,
        plane.elevation_deg,
        corners,
        uncertainty,
    )


_CORNER_SIGNS = ((-1, -1), (1, -1), (1, 1), (-1, 1))


def _all_windows(
    voxels: ArrayLike, grid: VoxelGrid, window_m: float, elevations_deg: Sequence[int]
) -> list[_Windows]:
    volume = np.ascontiguousarray(voxels, dtype=np.float32)
    if volume.shape != (grid.resolution,) * 3:
        raise ValueError(f"volume {volume.shape} does not match the {grid.resolution}^3 grid")
    return [
        _windows(plane, grid.voxel_size_m, window_m) for plane in ray_planes(volume, elevations_deg)
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


NORMAL_STEP_M = 0.002
"""Central-difference step of a signed distance's gradient (the surface normal at a target)."""
MAX_AIM_TURN_DEG = 50.0
"""An aimed approach stays this close to the policy's (beyond it the estimate's normal there is
taken for noise)."""


def normal_approach(
    sdf: Callable[[FloatArray], FloatArray],
    target_world: ArrayLike,
    direction_world: ArrayLike,
    max_turn_deg: float = MAX_AIM_TURN_DEG,
) -> FloatArray | None:
    """The inward surface normal at a target (world, unit) of a signed distance (metres, > 0
    outside, (K, 3) points -> (K,)), to approach along so the gel lands flat and the window,
    not the finger's rim, meets the surface; the policy's window directions are a lattice up to
    45 degrees off it. None where the gradient vanishes or turns more than ``max_turn_deg``
    from ``direction_world``."""
    point = np.asarray(target_world, dtype=float)
    steps = NORMAL_STEP_M * np.eye(3)
    gradient = np.asarray(sdf(point + steps)) - np.asarray(sdf(point - steps))
    length = float(np.linalg.norm(gradient))
    if length < 1e-9:
        return None
    inward = -gradient / length
    if float(inward @ np.asarray(direction_world, dtype=float)) < math.cos(
        math.radians(max_turn_deg)
    ):
        return None
    return inward


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
