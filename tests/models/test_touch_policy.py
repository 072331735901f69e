"""Active touch policy on synthetic volumes, integral images, random and oracle policies."""

from __future__ import annotations

import numpy as np
import pytest

from models.geometry import VoxelGrid
from models.touch.policy import (
    ELEVATIONS_DEG,
    YAWS_DEG,
    TouchCandidate,
    above_table_filter,
    all_of,
    approach_direction_voxel,
    confidence,
    facing_surface_filter,
    integral_image,
    normal_approach,
    oracle_select,
    policy_directions,
    predicted_bounding_box_world,
    random_touch,
    select_touch,
    touch_candidates,
    window_sums,
)
from models.touch.rays import quantise, ray_planes

N = 32
GRID = VoxelGrid(resolution=N, extent_m=0.16)  # 5 mm voxels: the 14 mm window is 3 x 3 rays
AXES = np.asarray(GRID.axes_world).T  # columns a_x, a_y, a_z in the world


def _box(patch: tuple[slice, slice, slice] | None = None, value: float = 0.55) -> np.ndarray:
    """A confident box (0.97 inside, 0.03 outside) on the table, voxels [10, 22)^2 x [0, 12),
    with an optional patch of barely occupied voxels (v = value)."""
    voxels = np.full((N, N, N), 0.03, np.float32)
    voxels[10:22, 10:22, 0:12] = 0.97
    if patch is not None:
        voxels[patch] = value
    return voxels


def _voxel_of(point_world: np.ndarray) -> np.ndarray:
    return GRID.world_to_voxel(point_world)


def test_integral_image_and_window_sums_match_brute_force(rng: np.random.Generator) -> None:
    values = rng.random((13, 9))
    integral = integral_image(values)
    assert integral.shape == (14, 10)
    assert integral[7, 4] == pytest.approx(values[:7, :4].sum())
    for rows, cols in ((1, 1), (3, 3), (4, 2), (13, 9)):
        sums = window_sums(values, rows, cols)
        assert sums.shape == (13 - rows + 1, 9 - cols + 1)
        for p in range(sums.shape[0]):
            for q in range(sums.shape[1]):
                assert sums[p, q] == pytest.approx(values[p : p + rows, q : q + cols].sum())


def test_confidence_is_distance_from_one_half() -> None:
    np.testing.assert_allclose(confidence([0.0, 0.3, 0.5, 0.9, 1.0]), [0.5, 0.2, 0.0, 0.4, 0.5])


def _plane(planes: list, yaw: float, elevation: float):
    return next(p for p in planes if p.yaw_deg == yaw and p.elevation_deg == elevation)


@pytest.mark.parametrize("sparse", [False, True])
def test_axis_aligned_rays_probe_the_first_surface_voxel(
    rng: np.random.Generator, sparse: bool
) -> None:
    """Brute force along voxel rows: horizontal rays from +a_x and vertical rays from above.

    ``sparse``: exact zeros outside a small block, so most rays skip the ray casting (their
    voxels are all below 1/254) and get their values from the shortcut."""
    n = 12
    voxels = rng.random((n, n, n)).astype(np.float32) * 0.9
    if sparse:
        block = voxels[3:7, 5:8, 2:9].copy()
        voxels[:] = 0.0
        voxels[3:7, 5:8, 2:9] = block
    planes = ray_planes(voxels, ELEVATIONS_DEG)
    assert len(planes) == 4 * 17 + 2
    from_x = _plane(planes, 0.0, 0.0)  # moves along -a_x: lines u = k, columns b = j
    from_above = _plane(planes, 0.0, 90.0)  # moves down: lines u = i, columns b = j
    for j in range(n):
        for k in range(n):
            # The order the sensor from +a_x meets voxels, and from the top down (k plays i).
            for plane, values, line in (
                (from_x, voxels[::-1, j, k], k),
                (from_above, voxels[k, j, ::-1], k),
            ):
                expected = _expected_confidence(values)
                assert plane.confidence[line, j] == pytest.approx(expected, abs=1 / 500)
                # Depth along the approach of the probe: hits at the first surface voxel,
                # misses at the first most probable (quantised) voxel; sample centres at +0.5.
                surface = np.flatnonzero(values >= 0.5)
                met = surface[0] if len(surface) else np.argmax(quantise(values))
                depth = plane.hit_depth[line, j] if len(surface) else plane.miss_depth()[line, j]
                assert depth == pytest.approx(-(n - 1 - met + 0.5))


def _expected_confidence(values_in_order: np.ndarray) -> float:
    surface = np.flatnonzero(values_in_order >= 0.5)
    if len(surface):
        return abs(float(values_in_order[surface[0]]) - 0.5)
    return 0.5 - float(values_in_order.max())  # a miss: its most probable voxel


def test_selects_a_known_uncertain_patch_on_a_side() -> None:
    # The +a_x face of the box is i = 21; the patch spans j, k in [13, 19) x [4, 10).
    voxels = _box((slice(21, 22), slice(13, 19), slice(4, 10)))
    candidate = select_touch(voxels, GRID)
    assert isinstance(candidate, TouchCandidate)
    assert candidate.score == pytest.approx(9 * 0.05, abs=1e-5)
    # The target is the pad centre where the pad first meets the patch: on the face, or up to
    # half a window off it when the pad comes in steeply.
    i, j, k = _voxel_of(candidate.target_world)
    assert 21 <= i <= 23.5 and 13 <= j <= 19 and 4 <= k <= 10
    # Several elevations see the same 3 x 3 patch rays; all come from the +a_x side.
    assert candidate.yaw_deg == 0.0
    assert candidate.approach_direction_world @ AXES[:, 0] < -0.1  # moving into the +a_x face
    assert candidate.window_corners_world.shape == (4, 3)
    np.testing.assert_allclose(candidate.window_corners_world.mean(axis=0), candidate.target_world)


def test_selects_a_known_uncertain_patch_on_top_and_respects_the_filter() -> None:
    voxels = _box((slice(13, 19), slice(13, 19), slice(11, 12)))
    candidate = select_touch(voxels, GRID)
    assert candidate is not None
    assert candidate.score == pytest.approx(9 * 0.05, abs=1e-5)
    assert candidate.elevation_deg >= 50
    assert candidate.approach_direction_world[2] < -0.7
    i, j, k = _voxel_of(candidate.target_world)
    assert 13 <= i <= 19 and 13 <= j <= 19 and 11 <= k <= 12

    def not_from_above(targets: np.ndarray, direction: np.ndarray) -> np.ndarray:
        return np.full(len(targets), direction[2] > -0.2)

    other = select_touch(voxels, GRID, not_from_above)
    assert other is not None and other.approach_direction_world[2] > -0.2
    assert other.score == touch_candidates(voxels, GRID, not_from_above)[0].score
    assert other.score > candidate.score
    assert select_touch(voxels, GRID, lambda t, d: np.zeros(len(t), bool)) is None


def test_facing_surface_filter_keeps_approaches_near_the_normal() -> None:
    voxels = _box((slice(21, 22), slice(13, 19), slice(4, 10)))
    facing = facing_surface_filter(voxels, GRID, max_angle_deg=25)
    candidate = select_touch(voxels, GRID, facing)
    assert candidate is not None
    assert candidate.yaw_deg == 0.0 and abs(candidate.elevation_deg) <= 20
    assert candidate.score == pytest.approx(9 * 0.05, abs=1e-5)
    face_point = GRID.voxel_to_world([[21.5, 16.0, 7.0]])
    inward = -AXES[:, 0]  # into the +a_x face
    assert facing(face_point, inward)[0]
    assert not facing(face_point, AXES[:, 0])[0]
    assert not facing(face_point, np.array([0.0, 0.0, -1.0]))[0]
    flat_space = GRID.voxel_to_world([[3.0, 3.0, 25.0]])
    assert facing(flat_space, AXES[:, 0])[0]  # no surface there: no normal to check against
    both = all_of(facing, above_table_filter(standoff_m=0.1))
    np.testing.assert_array_equal(both(np.concatenate([face_point, flat_space]), inward), [1, 1])
    low = GRID.voxel_to_world([[21.5, 16.0, 0.5]])
    assert facing(low, inward)[0] and not both(low, inward)[0]


def test_quantisation_keeps_the_surface_threshold_exact() -> None:
    below = np.nextafter(np.float32(0.5), np.float32(0))
    values = np.array(
        [0.0, below, 0.5, np.nextafter(np.float32(0.5), np.float32(1)), 1.0], np.float32
    )
    np.testing.assert_array_equal(quantise(values), [1, 127, 128, 128, 255])


def test_a_ray_that_misses_gets_the_confidence_of_its_most_probable_voxel() -> None:
    """Nothing reaches 0.5; an uncertain blob (v = 0.45) in confident free space wins."""
    voxels = np.full((N, N, N), 0.02, np.float32)
    voxels[12:18, 12:18, 8:14] = 0.45
    candidate = select_touch(voxels, GRID)
    assert candidate is not None
    assert candidate.score == pytest.approx(9 * 0.05, abs=9 / 500)
    i, j, k = _voxel_of(candidate.target_world)
    assert 11.5 <= i <= 18.5 and 11.5 <= j <= 18.5 and 7.5 <= k <= 14.5
    # The target is on the blob's side facing the sensor: one voxel into it along the approach.
    direction_voxel = AXES.T @ candidate.approach_direction_world
    before = _voxel_of(candidate.target_world) - 1.0 * direction_voxel
    assert voxels[tuple(np.floor(before).astype(int))] == pytest.approx(0.02)


def test_every_candidate_is_on_the_near_side_of_a_sphere() -> None:
    centres = np.arange(N) + 0.5
    i, j, k = np.meshgrid(centres, centres, centres, indexing="ij")
    centre = np.array([N / 2, N / 2, 12.0])
    radius = np.sqrt((i - centre[0]) ** 2 + (j - centre[1]) ** 2 + (k - centre[2]) ** 2)
    voxels = (1 / (1 + np.exp((radius - 9.0) / 0.7))).astype(np.float32)
    candidates = touch_candidates(voxels, GRID)
    assert select_touch(voxels, GRID).score == candidates[0].score
    assert len(policy_directions()) == 70
    assert {(c.yaw_deg, c.elevation_deg) for c in candidates} == set(policy_directions())
    assert [c.score for c in candidates] == sorted(c.score for c in candidates)
    for candidate in candidates:
        target = _voxel_of(candidate.target_world)
        assert abs(np.linalg.norm(target - centre) - 9.0) < 2.0
        outward = (target - centre) / np.linalg.norm(target - centre)
        direction_voxel = AXES.T @ candidate.approach_direction_world
        assert direction_voxel @ outward < 0.35  # comes from outside, not through the sphere
        expected = approach_direction_voxel(candidate.yaw_deg, candidate.elevation_deg)
        np.testing.assert_allclose(direction_voxel, expected, atol=1e-9)


def test_above_table_filter() -> None:
    feasible = above_table_filter(standoff_m=0.1, clearance_m=0.01)
    targets = np.array([[0.0, 0.0, 0.05], [0.0, 0.0, 0.005], [0.0, 0.0, 0.2]])
    down = np.array([0.0, 0.0, -1.0])
    up = np.array([0.0, 0.0, 1.0])
    np.testing.assert_array_equal(feasible(targets, down), [True, False, True])
    np.testing.assert_array_equal(feasible(targets, up), [False, False, True])


def test_random_policy_draws_feasible_targets_in_the_box(rng: np.random.Generator) -> None:
    box = predicted_bounding_box_world(_box(), GRID)
    assert box is not None
    low, high = box
    np.testing.assert_allclose(low, [-0.03, -0.03, 0.0], atol=1e-12)
    np.testing.assert_allclose(high, [0.03, 0.03, 0.06], atol=1e-12)
    feasible = above_table_filter(standoff_m=0.05)
    for _ in range(20):
        touch = random_touch(low, high, GRID, rng, feasible)
        assert touch is not None and np.isnan(touch.score)
        assert np.all(touch.target_world >= low) and np.all(touch.target_world <= high)
        assert touch.yaw_deg in YAWS_DEG and touch.elevation_deg in ELEVATIONS_DEG
        assert feasible(touch.target_world[None], touch.approach_direction_world)[0]
    never = random_touch(low, high, GRID, rng, lambda t, d: np.zeros(len(t), bool), max_tries=5)
    assert never is None
    assert predicted_bounding_box_world(np.zeros((N, N, N)), GRID) is None


def test_oracle_picks_the_candidate_with_the_lowest_error() -> None:
    candidates = touch_candidates(_box((slice(21, 22), slice(13, 19), slice(4, 10))), GRID)[:5]
    calls = []

    def error_after(candidate: TouchCandidate) -> float:
        calls.append(candidate)
        return float(candidate.target_world[2])  # stand-in for "Chamfer after this touch"

    best, error = oracle_select(candidates, error_after)
    assert len(calls) == 5
    assert error == min(c.target_world[2] for c in candidates)
    assert best.target_world[2] == error
    with pytest.raises(ValueError):
        oracle_select([], error_after)


def test_volume_must_match_the_grid() -> None:
    with pytest.raises(ValueError):
        select_touch(np.zeros((8, 8, 8)), GRID)


def _sphere_sdf(centre, radius):
    centre = np.asarray(centre, dtype=float)
    return lambda points: np.linalg.norm(np.asarray(points) - centre, axis=-1) - radius


def test_normal_approach_turns_a_lattice_direction_onto_the_surface_normal() -> None:
    """A target on a sphere approached 40 degrees off its normal is re-aimed along the inward
    normal: the gel lands flat."""
    sdf = _sphere_sdf((0.0, 0.0, 0.1), 0.05)
    target = np.array([0.05 * np.cos(0.3), 0.05 * np.sin(0.3), 0.1])
    inward = -np.array([np.cos(0.3), np.sin(0.3), 0.0])
    off = np.array([np.cos(np.radians(40)), 0.0, 0.0])
    policy_direction = inward * off[0] + np.array([0.0, 0.0, -np.sin(np.radians(40))])
    aimed = normal_approach(sdf, target, policy_direction)
    assert aimed is not None
    assert np.linalg.norm(aimed) == pytest.approx(1.0)
    assert np.degrees(np.arccos(np.clip(aimed @ inward, -1, 1))) < 1.0


def test_normal_approach_refuses_a_turn_past_its_limit_and_a_flat_field() -> None:
    sdf = _sphere_sdf((0.0, 0.0, 0.1), 0.05)
    target = np.array([0.05, 0.0, 0.1])
    sideways = np.array([0.0, 1.0, 0.0])  # 90 degrees off the inward normal
    assert normal_approach(sdf, target, sideways) is None
    assert normal_approach(lambda p: np.zeros(len(p)), target, -np.array([1.0, 0, 0])) is None
