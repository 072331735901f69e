"""Touch constraints: exact voxel traversal against brute force, rays of a touch, merging."""

from __future__ import annotations

import numpy as np
import pytest

from models.geometry import VoxelGrid, frame_from_z_axis, make_transform, segment_box_clip
from models.touch.constraints import (
    TouchResult,
    VoxelConstraints,
    _clip_to_box,
    constraints_from_touches,
    free_pad_points,
    pad_grid_world,
    touch_constraints,
    traverse_segments,
)

N = 12


def _crossed_voxels(start: np.ndarray, end: np.ndarray, n: int) -> set[tuple[int, int, int]]:
    """Brute force, exact: cut the segment at every integer plane it crosses and take the voxel
    of each piece's midpoint (pieces of zero length drop out)."""
    delta = end - start
    cuts = [0.0, 1.0]
    for axis in range(3):
        if delta[axis] != 0:
            t = (np.arange(n + 1) - start[axis]) / delta[axis]
            cuts += list(t[(t > 0) & (t < 1)])
    cuts = np.unique(cuts)
    middles = start + 0.5 * (cuts[:-1] + cuts[1:])[:, None] * delta
    voxels = np.floor(middles).astype(int)
    inside = np.all((voxels >= 0) & (voxels < n), axis=1)
    return set(map(tuple, voxels[inside]))


def _sampled_voxels(start: np.ndarray, end: np.ndarray, n: int, count: int) -> set:
    """Brute force by dense sampling along the segment."""
    points = start + np.linspace(0, 1, count)[:, None] * (end - start)
    voxels = np.floor(points).astype(int)
    inside = np.all((voxels >= 0) & (voxels < n), axis=1)
    return set(map(tuple, voxels[inside]))


def _segments(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Random segments inside, outside and across the grid, plus awkward special cases."""
    starts = rng.uniform(-4, N + 4, (300, 3))
    ends = rng.uniform(-4, N + 4, (300, 3))
    special_starts = [
        [0.5, 0.5, 0.5],  # axis-parallel, each direction
        [N - 0.5, 3.2, 4.7],
        [3.0, 4.0, -2.0],  # along a voxel edge (x, y integral), entering from below
        [2.0, 7.3, 5.1],  # in a voxel face, moving down x
        [-3.0, -3.0, -3.0],  # the main diagonal through every corner
        [5.5, 5.5, 5.5],  # zero length
        [N + 1.0, 2.0, 2.0],  # parallel to the grid, outside it
        [0.0, 2.5, 2.5],  # in the grid's x = 0 face: inside (voxels are half-open)
        [N, 2.5, 2.5],  # in the x = N face: outside
        [-1.0, 1.0, 5.0],  # grazing the grid's edge x = y = 0 at one point
    ]
    special_ends = [
        [N - 0.5, 0.5, 0.5],
        [-3.0, 3.2, 4.7],
        [3.0, 4.0, N + 2.0],
        [0.3, 7.3, 9.9],
        [N + 3.0, N + 3.0, N + 3.0],
        [5.5, 5.5, 5.5],
        [N + 1.0, 9.0, 2.0],
        [0.0, 8.5, 2.5],
        [N, 8.5, 2.5],
        [1.0, -1.0, 5.0],
    ]
    return np.concatenate([starts, special_starts]), np.concatenate([ends, special_ends])


def test_traversal_matches_exact_brute_force(rng: np.random.Generator) -> None:
    starts, ends = _segments(rng)
    segment, voxels = traverse_segments(starts, ends, N)
    for index, (start, end) in enumerate(zip(starts, ends, strict=True)):
        found = voxels[segment == index]
        assert len(set(map(tuple, found))) == len(found), "a voxel was reported twice"
        expected = _crossed_voxels(start, end, N)
        if np.allclose(start, end):  # zero length: the voxel it lies in
            expected = {tuple(np.floor(start).astype(int))}
        assert set(map(tuple, found)) == expected, f"segment {index}: {start} -> {end}"


def test_traversal_agrees_with_dense_sampling(rng: np.random.Generator) -> None:
    """Every densely sampled voxel is found; any extra voxel is only clipped by a sliver."""
    starts, ends = _segments(rng)
    starts, ends = starts[:60], ends[:60]
    count = 20_000
    segment, voxels = traverse_segments(starts, ends, N)
    for index, (start, end) in enumerate(zip(starts, ends, strict=True)):
        found = set(map(tuple, voxels[segment == index]))
        sampled = _sampled_voxels(start, end, N, count)
        assert sampled <= found
        step = np.linalg.norm(end - start) / (count - 1)
        for voxel in found - sampled:
            clip = segment_box_clip(start, end, np.array(voxel), np.array(voxel) + 1)
            assert clip is not None
            assert (clip[1] - clip[0]) * np.linalg.norm(end - start) <= 2 * step


def test_traversal_is_ordered_and_face_connected(rng: np.random.Generator) -> None:
    starts = rng.uniform(-3, N + 3, (100, 3))
    ends = rng.uniform(-3, N + 3, (100, 3))
    segment, voxels = traverse_segments(starts, ends, N)
    for index in np.unique(segment):
        path = voxels[segment == index]
        steps = np.abs(np.diff(path, axis=0)).sum(axis=1)
        assert np.all(steps == 1)
        # Ordered from the start: distances of the voxel centres from it grow along the path.
        direction = ends[index] - starts[index]
        along = (path + 0.5 - starts[index]) @ direction
        assert along[0] <= along[-1]


def test_vectorised_clip_matches_geometry_module(rng: np.random.Generator) -> None:
    starts, ends = _segments(rng)
    t0, t1 = _clip_to_box(starts, ends, float(N))
    inside = t0 <= t1
    for index, (start, end) in enumerate(zip(starts, ends, strict=True)):
        if np.any(start == N):
            continue  # the geometry module's box is closed, the traversal's half-open
        expected = segment_box_clip(start, end, [0, 0, 0], [N, N, N])
        assert inside[index] == (expected is not None)
        if expected is not None:
            assert t0[index] == pytest.approx(expected[0]) and t1[index] == pytest.approx(
                expected[1]
            )


def _wall_grid() -> VoxelGrid:
    """16^3 grid of 1 cm voxels with the paper's axes (voxel i grows toward world -x)."""
    return VoxelGrid(resolution=16, extent_m=0.16)


def test_contact_touch_on_a_wall() -> None:
    """Pad pressed along world +x onto a wall x = 0.0325 m: voxels in front empty, wall occupied."""
    grid = _wall_grid()
    direction = np.array([1.0, 0.0, 0.0])
    pose_world_pad = make_transform(frame_from_z_axis(direction), [0.0325, 0.0, 0.05])
    contacts = pad_grid_world(pose_world_pad, (0.019, 0.014), 0.001)
    touch = TouchResult.from_contact(contacts, direction, [-0.2, 0.0, 0.05])
    assert not touch.is_miss
    np.testing.assert_allclose(touch.ray_starts_world[:, 0], -0.2)
    constraints = touch_constraints(touch, grid)
    occupied = constraints.occupied_ijk()
    empty = constraints.empty_ijk()
    # World x = 0.0325 is voxel coordinate i = 8 - 3.25 = 4.75: the contact voxel is i = 4, the
    # pad came from world -x = high i, so i = 5..15 are in front of it. The occupied voxel holds
    # the point sqrt(3)/2 voxel deeper, i = 3.88; the contact voxel i = 4 stays unconstrained.
    assert set(occupied[:, 0]) == {3}
    assert set(empty[:, 0]) == set(range(5, 16))
    # The 19 x 14 mm patch centred on voxel corner (j, k) = (8, 5) covers j = 7, 8 and k = 4, 5.
    world_y = grid.voxel_to_world(occupied + 0.5)[:, 1]
    world_z = grid.voxel_to_world(occupied + 0.5)[:, 2]
    assert np.all(np.abs(world_y) < 0.015) and np.all(np.abs(world_z - 0.05) < 0.015)
    assert len(occupied) == 4
    assert len(empty) == 11 * len(occupied)  # every patch ray crosses the same columns


def test_occupied_voxel_centres_lie_behind_a_plane_facing_the_ray() -> None:
    """For any approach direction onto a plane normal to it, the voxel called occupied has its
    centre behind the plane (inside the object, as voxelisation by centres decides), and no
    voxel called empty has its centre behind it."""
    grid = _wall_grid()
    rng = np.random.default_rng(3)
    for _ in range(50):
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        centre = rng.uniform(-0.03, 0.03, size=3) + np.array([0.0, 0.0, 0.08])
        pose_world_pad = make_transform(frame_from_z_axis(direction), centre)
        contacts = pad_grid_world(pose_world_pad, (0.019, 0.014), 0.001)
        touch = TouchResult.from_contact(contacts, direction, centre - 0.05 * direction)
        constraints = touch_constraints(touch, grid)
        depth_occupied = (
            grid.voxel_to_world(constraints.occupied_ijk() + 0.5) - centre
        ) @ direction
        depth_empty = (grid.voxel_to_world(constraints.empty_ijk() + 0.5) - centre) @ direction
        assert len(depth_occupied) and np.all(depth_occupied > 0)
        assert np.all(depth_empty < 0)


def test_free_pad_points_keep_away_from_contacts() -> None:
    direction = np.array([0.0, 0.0, -1.0])
    pose = make_transform(frame_from_z_axis(direction), [0.0, 0.0, 0.1])
    contacts = np.array([[0.0, 0.0, 0.0995]])
    free = free_pad_points(pose, contacts, (0.019, 0.014), 0.001, margin_m=0.002)
    lateral = np.linalg.norm(free[:, :2], axis=1)
    assert lateral.min() > 0.002
    np.testing.assert_allclose(free[:, 2], 0.102)  # pulled back against the approach
    grid = pad_grid_world(pose, (0.019, 0.014), 0.001)
    near = np.linalg.norm(grid[:, :2], axis=1) <= 0.002
    assert len(free) == len(grid) - near.sum() and near.sum() > 0


def test_miss_empties_the_swept_volume_and_free_rays_do_too() -> None:
    grid = _wall_grid()
    direction = np.array([0.0, 0.0, -1.0])
    start_pose = make_transform(frame_from_z_axis(direction), [0.0, 0.0, 0.2])
    starts = pad_grid_world(start_pose, (0.019, 0.014), 0.002)
    miss = TouchResult.from_miss(starts, starts + np.array([0.0, 0.0, -0.15]))
    assert miss.is_miss
    constraints = touch_constraints(miss, grid)
    assert len(constraints.occupied) == 0
    empty = constraints.empty_ijk()
    assert set(empty[:, 2]) == set(range(5, 16))  # world z from 0.05 up to the grid top
    # The same sweep as free rays of a contact touch elsewhere gives the same empties.
    contact = TouchResult.from_contact(
        [[0.5, 0.5, 0.0]], direction, [0.0, 0.0, 0.2], free_points_world=starts - [0, 0, 0.15]
    )
    np.testing.assert_array_equal(touch_constraints(contact, grid).empty, constraints.empty)


def test_a_stopped_sweep_empties_only_voxels_whose_centres_it_passed() -> None:
    grid = _wall_grid()
    direction = np.array([0.0, 0.0, -1.0])
    start_pose = make_transform(frame_from_z_axis(direction), [0.0, 0.0, 0.2])
    starts = pad_grid_world(start_pose, (0.019, 0.014), 0.002)
    for stop_z, lowest_empty_layer in ((0.053, 5), (0.057, 6)):
        # Layer 5 spans z 0.05-0.06 with its centres at 0.055: a stop above them proves nothing
        # about them (a thin part may fill them).
        stopped = TouchResult.from_miss(starts, starts * [1, 1, 0] + [0, 0, stop_z])
        empty = touch_constraints(stopped, grid).empty_ijk()
        assert empty[:, 2].min() == lowest_empty_layer


def test_occupied_wins_when_merging() -> None:
    a = VoxelConstraints.from_voxels(8, empty_ijk=[[1, 1, 1], [2, 2, 2]], occupied_ijk=[[3, 3, 3]])
    b = VoxelConstraints.from_voxels(8, empty_ijk=[[3, 3, 3]], occupied_ijk=[[2, 2, 2]])
    merged = a.merged(b)
    assert {tuple(v) for v in merged.occupied_ijk()} == {(2, 2, 2), (3, 3, 3)}
    assert {tuple(v) for v in merged.empty_ijk()} == {(1, 1, 1)}
    assert len(merged) == 3
    with pytest.raises(ValueError):
        a.merged(VoxelConstraints.none(16))


def test_constraints_from_touches_merges_in_any_order() -> None:
    grid = _wall_grid()
    down = np.array([0.0, 0.0, -1.0])
    across = np.array([1.0, 0.0, 0.0])
    first = TouchResult.from_contact([[0.0, 0.0, 0.031]], down, [0.0, 0.0, 0.3])
    second = TouchResult.from_contact([[0.021, 0.0, 0.035]], across, [-0.3, 0.0, 0.035])
    forward = constraints_from_touches([first, second], grid)
    backward = constraints_from_touches([second, first], grid)
    np.testing.assert_array_equal(forward.empty, backward.empty)
    np.testing.assert_array_equal(forward.occupied, backward.occupied)
    assert len(forward.occupied) == 2


def test_touch_result_validation() -> None:
    with pytest.raises(ValueError):
        TouchResult.from_contact([[0, 0, 0]], [0, 0, 0], [0, 0, 1])
    with pytest.raises(ValueError):
        TouchResult.from_contact([[0, 0, 2]], [0, 0, -1], [0, 0, 1])  # behind the start
    with pytest.raises(ValueError):
        TouchResult.from_contact(np.zeros((0, 3)), [0, 0, -1], [0, 0, 1])
    with pytest.raises(ValueError):
        TouchResult.from_miss(np.zeros((2, 3)), np.ones((3, 3)))


def test_a_stop_adds_one_group_beyond_its_points_and_later_sweeps_empty_it() -> None:
    """A stop without an imprint: its points' voxels (sqrt(3)/2 voxel beyond them, each along
    the direction it moved: the pad's side down, the other finger's up) form one group, none
    of them empty; a later sweep through some of them leaves the rest; a stop whose voxels are
    all swept free afterwards drops out."""
    grid = _wall_grid()
    direction = np.array([0.0, 0.0, -1.0])
    start_pose = make_transform(frame_from_z_axis(direction), [0.0, 0.0, 0.2])
    starts = pad_grid_world(start_pose, (0.019, 0.014), 0.002)
    ends = starts * [1, 1, 0] + [0, 0, 0.1]
    beside = ends + np.array([0.03, 0.0, 0.0])  # beside the pad, as the housing's front is
    behind = ends + np.array([0.0, 0.04, 0.03])  # the other finger, moving up
    stop_points = np.concatenate([beside, behind])
    directions = np.concatenate(
        [np.tile(direction, (len(ends), 1)), np.tile(-direction, (len(ends), 1))]
    )
    touch = TouchResult.from_miss(starts, ends, stop_points, directions)
    stopped = touch_constraints(touch, grid)
    (group,) = stopped.any_occupied
    ijk = np.stack(np.unravel_index(group, (grid.resolution,) * 3), axis=1)
    depth_m = 0.01 * np.sqrt(3) / 2
    expected = np.floor(grid.world_to_voxel(stop_points + directions * depth_m)).astype(int)
    assert {tuple(v) for v in ijk} == {tuple(v) for v in expected}
    assert not np.intersect1d(group, stopped.empty).size
    assert len(touch_constraints(TouchResult.from_miss(starts, ends), grid).any_occupied) == 0
    with pytest.raises(ValueError):
        TouchResult.from_miss(starts, ends, stop_points, directions[:3])
    up = np.array([0.0, 0.0, 0.05])
    sweep_starts = beside[:5] + up
    partly = stopped.merged(
        touch_constraints(TouchResult.from_miss(sweep_starts, sweep_starts - [0, 0, 0.2]), grid)
    )
    (rest,) = partly.any_occupied
    assert 0 < len(rest) < len(group)
    swept = stop_points + up
    cleared = stopped.merged(
        touch_constraints(TouchResult.from_miss(swept, swept - [0, 0, 0.3]), grid)
    )
    assert cleared.any_occupied == ()
