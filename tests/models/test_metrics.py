"""Voxel IoU, Chamfer distance and F-score definitions, on the estimates' surfaces."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from models.geometry import VoxelGrid
from models.metrics import sample_surface, surface_metrics, surfaces_metrics, voxel_iou
from models.shapes import voxelize
from models.touch.fused import prior_surface


def test_voxel_iou() -> None:
    truth = np.zeros((1, 4, 4, 4), np.float32)
    truth[0, :2] = 1  # 32 voxels
    prediction = np.zeros_like(truth)
    prediction[0, 1:3] = 0.7  # 32 voxels above 0.5, 16 shared
    assert voxel_iou(prediction, truth) == pytest.approx(16 / 48)
    assert voxel_iou(truth, truth) == 1.0
    assert voxel_iou(np.zeros_like(truth), np.zeros_like(truth)) == 1.0
    assert voxel_iou(prediction, truth, threshold=0.8) == 0.0


def test_chamfer_is_unsquared_sum_of_both_directions_in_mm(rng: np.random.Generator) -> None:
    points = rng.uniform(-0.05, 0.05, (2000, 3))
    points[:, 2] = 0.0
    shifted = points + np.array([0.0, 0.0, 0.003])  # a parallel plane 3 mm away
    metrics = surface_metrics(shifted, points)
    assert metrics.chamfer_mm == pytest.approx(6.0, rel=1e-6)
    assert metrics.fscore_2mm == 0.0 and metrics.fscore_5mm == 1.0
    assert surface_metrics(points, points).chamfer_mm == 0.0
    assert surface_metrics(np.zeros((0, 3)), points).chamfer_mm == float("inf")


def test_a_voxel_estimates_surface_lies_on_the_voxelised_mesh() -> None:
    """The extraction every estimate's score goes through (``prior_surface``)."""
    grid = VoxelGrid(32, 0.16, axes_world=((0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)))
    box = trimesh.creation.box(extents=(0.08, 0.06, 0.1))
    box.apply_translation((0.01, -0.005, 0.05))
    occupancy = voxelize(box, grid).astype(np.float32)
    surface = prior_surface(occupancy, grid)
    assert surface.is_watertight and surface.volume > 0  # outward normals
    paper_axes = VoxelGrid(32, 0.16)  # a_x = (-1, 0, 0): a left-handed index frame
    assert prior_surface(voxelize(box, paper_axes).astype(np.float32), paper_axes).volume > 0
    assert np.allclose(surface.bounds, box.bounds, atol=grid.voxel_size_m)
    metrics = surfaces_metrics(surface, box, count=10_000)
    assert metrics.chamfer_mm < 1e3 * grid.voxel_size_m  # within a voxel (5 mm) on average
    assert metrics.fscore_5mm > 0.9
    assert len(sample_surface(trimesh.Trimesh(), 10)) == 0
