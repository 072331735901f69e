"""The object's size a session reports: the estimate's occupied extent along its grid axes."""

from __future__ import annotations

import numpy as np
import trimesh

from controller.perception.protocol import ShapeEstimate
from controller.scoring import object_size_cm
from models.geometry import VoxelGrid, axes_facing_camera
from models.shapes import voxelize


def test_sizes_along_the_grid_axes_with_the_truth() -> None:
    # A grid yawed 30 degrees: the box is axis-aligned with the grid, not with the world.
    axes = axes_facing_camera((-0.62 * np.cos(0.5), -0.62 * np.sin(0.5), 0.46))
    grid = VoxelGrid(64, 0.26, (0.0, 0.0, 0.0), axes)
    box = trimesh.creation.box((0.06, 0.10, 0.14))
    pose = np.eye(4)
    pose[:3, :3] = np.asarray(axes).T  # box x, y, z along the grid's axes
    pose[:3, 3] = (0.0, 0.0, 0.07)
    box.apply_transform(pose)
    true = ShapeEstimate(grid=grid, probabilities=voxelize(box, grid).astype(np.float32))
    empty = ShapeEstimate(grid=grid, probabilities=np.zeros((64,) * 3, np.float32))

    sizes = object_size_cm(empty, true, box)

    voxel_cm = 100 * grid.voxel_size_m
    assert sizes["vision"] is None
    np.testing.assert_allclose(sizes["final"], [6.0, 10.0, 14.0], atol=voxel_cm)
    np.testing.assert_allclose(sizes["true"], [6.0, 10.0, 14.0], atol=0.05)
    assert "true" not in object_size_cm(true, true)
