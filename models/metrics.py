"""Shape metrics: voxel IoU, Chamfer distance and F-score in millimetres.

Definitions (also in docs/prior.md):

* Voxel IoU at threshold t (default 0.5): |pred >= t AND gt| / |pred >= t OR gt|, per sample over
  all voxels; 1.0 when both are empty.
* Chamfer distance (mm): sample ``n`` points (default 10,000) uniformly on each surface, then
  CD = mean over predicted points of the distance to the nearest ground-truth point + mean over
  ground-truth points of the distance to the nearest predicted point. Distances are *not* squared.
* F-score at d mm (Tatarchenko et al. 2019): harmonic mean of precision (predicted points within d
  of the ground truth) and recall (ground-truth points within d of the prediction).

Predicted surfaces are world meshes: every estimate's, voxels or fused field, through one
extraction (``ShapeEstimate.surface_mesh``, :func:`models.touch.fused.prior_surface`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

SURFACE_SAMPLES = 10_000


def voxel_iou(
    prediction: torch.Tensor | np.ndarray,
    target: torch.Tensor | np.ndarray,
    threshold: float = 0.5,
) -> float:
    """Mean over the batch (first axis) of the IoU of ``prediction >= threshold`` with ``target``.

    Both are (B, ...) arrays; ``target`` holds 0/1.
    """
    prediction = torch.as_tensor(prediction)
    target = torch.as_tensor(target)
    pred = (prediction >= threshold).flatten(1)
    true = (target > 0.5).flatten(1)
    intersection = (pred & true).sum(1).float()
    union = (pred | true).sum(1).float()
    iou = torch.where(union > 0, intersection / union.clamp(min=1), torch.ones_like(union))
    return float(iou.mean())


def sample_surface(
    mesh: trimesh.Trimesh, count: int = SURFACE_SAMPLES, seed: int = 0
) -> np.ndarray:
    """``count`` points (metres) uniformly on a mesh's surface, reproducible for a seed."""
    if len(mesh.faces) == 0:
        return np.zeros((0, 3))
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    return np.asarray(points)


@dataclass(frozen=True)
class SurfaceMetrics:
    """Chamfer distance (mm, unsquared, sum of both directions) and F-scores."""

    chamfer_mm: float
    fscore_2mm: float
    fscore_5mm: float


def surface_metrics(predicted_points: np.ndarray, true_points: np.ndarray) -> SurfaceMetrics:
    """Metrics between two point samples in metres; empty prediction -> inf Chamfer, 0 F-score."""
    if len(predicted_points) == 0 or len(true_points) == 0:
        return SurfaceMetrics(float("inf"), 0.0, 0.0)
    to_true, _ = cKDTree(true_points).query(predicted_points)
    to_pred, _ = cKDTree(predicted_points).query(true_points)
    to_true_mm, to_pred_mm = to_true * 1e3, to_pred * 1e3

    def fscore(d_mm: float) -> float:
        precision = float(np.mean(to_true_mm <= d_mm))
        recall = float(np.mean(to_pred_mm <= d_mm))
        return 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)

    return SurfaceMetrics(
        chamfer_mm=float(to_true_mm.mean() + to_pred_mm.mean()),
        fscore_2mm=fscore(2.0),
        fscore_5mm=fscore(5.0),
    )


def surfaces_metrics(
    predicted_mesh_world: trimesh.Trimesh,
    true_mesh_world: trimesh.Trimesh,
    count: int = SURFACE_SAMPLES,
    seed: int = 0,
) -> SurfaceMetrics:
    """Chamfer / F-score of a predicted surface against the true one (world meshes)."""
    predicted = sample_surface(predicted_mesh_world, count, seed)
    return surface_metrics(predicted, sample_surface(true_mesh_world, count, seed + 1))


def distance_to_mesh(points: np.ndarray, mesh: trimesh.Trimesh, candidates: int = 8) -> np.ndarray:
    """Distance (metres) from each point to a mesh's surface: the exact point-triangle distance
    to the faces around the ``candidates`` nearest vertices (enough for a fine, even mesh);
    inf for an empty mesh."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(mesh.faces) == 0:
        return np.full(len(points), np.inf)
    if len(points) == 0:
        return np.zeros(0)
    _, nearest = cKDTree(mesh.vertices).query(points, k=min(candidates, len(mesh.vertices)))
    nearest = nearest.reshape(len(points), -1)
    faces_of_vertex = mesh.vertex_faces  # (V, max degree), -1 padded
    faces = faces_of_vertex[nearest].reshape(len(points), -1)
    point_index = np.repeat(np.arange(len(points)), faces.shape[1])
    faces = faces.ravel()
    valid = faces >= 0
    closest = trimesh.triangles.closest_point(
        mesh.triangles[faces[valid]], points[point_index[valid]]
    )
    distance = np.linalg.norm(closest - points[point_index[valid]], axis=1)
    out = np.full(len(points), np.inf)
    np.minimum.at(out, point_index[valid], distance)
    return out
