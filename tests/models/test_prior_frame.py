"""The object-fitted frame: a known object's centre and size come back from its silhouette."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from models.camera import CameraIntrinsics, look_at_pose
from models.geometry import axes_facing_camera, make_transform
from models.prior.frame import (
    FRAME_MARGIN,
    FRONT_OVERHANG,
    FrameError,
    depth_silhouette,
    fit_object_grid,
    grid_holding_points,
    search_grid,
)
from models.prior.virtual_camera import grid_crop
from models.render import Scene, SceneObject, make_table, render

POSE_WORLD_CAMERA = look_at_pose((-0.62, 0.0, 0.4572), (0.0, 0.0, 0.1))


def _seen(mesh: trimesh.Trimesh):
    axes = axes_facing_camera(POSE_WORLD_CAMERA[:3, 3])
    crop = grid_crop(
        CameraIntrinsics.kinect_v2_colour(0.5), POSE_WORLD_CAMERA, search_grid(64, axes), 128
    )
    scene = Scene(objects=[SceneObject(mesh)], table=make_table((1.0, 0.8), (0.0, 0.0)))
    return axes, crop, render(scene, crop.intrinsics, POSE_WORLD_CAMERA)


@pytest.mark.parametrize(
    ("size_m", "offset_m"),
    [
        ((0.06, 0.06, 0.12), (0.0, 0.0)),
        ((0.04, 0.04, 0.04), (0.02, -0.03)),
        ((0.2, 0.15, 0.25), (0.0, 0.02)),
    ],
)
def test_frame_recovers_a_box_centre_and_extent(size_m, offset_m) -> None:
    box = trimesh.creation.box(size_m)
    box.apply_transform(make_transform(None, (*offset_m, size_m[2] / 2)))
    axes, crop, out = _seen(box)
    grid = fit_object_grid(out.silhouette, crop.intrinsics, POSE_WORLD_CAMERA, axes, 64)
    # Its size within what one view allows: the top's back edge, seen from above, reads as
    # height (up to +35 %).
    assert 0.9 < grid.extent_m / FRAME_MARGIN / max(size_m) < 1.35
    assert max(size_m) / grid.extent_m > 0.5  # the object fills the grid
    # Across the line of sight (world y) the centre is recovered; along it (the camera is on -x)
    # the frame moves toward the camera by FRONT_OVERHANG of the height (room for rounded
    # fronts) and takes the box as deep as it is wide.
    lateral_error = grid.origin_world[1] - offset_m[1]
    assert abs(lateral_error) < 0.05 * max(size_m) + 0.002
    along_error = grid.origin_world[0] - offset_m[0]
    allowed = FRONT_OVERHANG * grid.extent_m / FRAME_MARGIN + abs(size_m[0] - size_m[1]) / 2
    assert -allowed - 0.005 < along_error < 0.005
    inside = grid.world_to_voxel(box.sample(2000, seed=0))
    assert np.all((inside >= 0) & (inside <= 64))  # the whole object is in the grid


def test_frame_of_a_sphere_holds_it() -> None:
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    sphere.apply_translation((0.0, 0.0, 0.05))
    axes, crop, out = _seen(sphere)
    grid = fit_object_grid(out.silhouette, crop.intrinsics, POSE_WORLD_CAMERA, axes, 64)
    voxels = grid.world_to_voxel(sphere.sample(2000, seed=0))
    assert np.mean(np.all((voxels >= 0) & (voxels <= 64), axis=1)) > 0.97
    assert grid.extent_m / FRAME_MARGIN == pytest.approx(0.1, rel=0.15)


def test_empty_silhouette_has_no_frame() -> None:
    axes, crop, _ = _seen(trimesh.creation.box((0.05, 0.05, 0.05)))
    with pytest.raises(FrameError, match="empty silhouette"):
        fit_object_grid(np.zeros((128, 128), bool), crop.intrinsics, POSE_WORLD_CAMERA, axes, 64)


def test_depth_silhouette_is_the_object_above_the_table() -> None:
    box = trimesh.creation.box((0.08, 0.08, 0.1))
    box.apply_translation((0.0, 0.0, 0.05))
    axes, crop, out = _seen(box)
    mask = depth_silhouette(out.depth_m, crop.intrinsics, POSE_WORLD_CAMERA, search_grid(64, axes))
    overlap = np.sum(mask & out.silhouette) / np.sum(mask | out.silhouette)
    assert overlap > 0.9


def test_a_long_object_seen_end_on_is_held_by_the_grid_with_depth() -> None:
    """A 19 cm keyboard-like slab pointing at the camera: the silhouette's frame (the object as
    deep as it is wide) misses its far end; grown to hold the depth points, the grid holds it,
    stands on the table, and a grid that already held them stays as it was."""
    slab = trimesh.creation.box((0.19, 0.06, 0.02))
    slab.apply_translation((0.0, 0.0, 0.01))
    axes, crop, seen = _seen(slab)
    grid = fit_object_grid(seen.silhouette, crop.intrinsics, POSE_WORLD_CAMERA, axes, 64)
    far_end = slab.vertices
    assert not np.all((grid.world_to_voxel(far_end) >= 0) & (grid.world_to_voxel(far_end) <= 64))
    grown = grid_holding_points(grid, far_end)
    inside = grown.world_to_voxel(far_end)
    assert np.all((inside >= 0) & (inside <= 64))
    assert grown.origin_world[2] == 0.0 and grown.axes_world == grid.axes_world
    assert grid_holding_points(grown, far_end) is grown
