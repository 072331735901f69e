"""Choosing the prior from what vision sees: ``prior = "auto"``.

Every committed prior predicts the object; the one whose shape best explains the image wins. The
score is the agreement (IoU) between the silhouette seen in the crop (the sketch net's; with
depth, the returns above the table) and the silhouette of the predicted occupancy projected
through the same camera: a prior that decodes the wrong kind of shape (a box for a mug) covers the
object's outline badly. No extra training is needed, and the choice is made per view.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace

import numpy as np
from scipy import ndimage

from models.camera import CameraIntrinsics
from models.geometry import VoxelGrid, invert_transform, transform_points
from models.prior.shape_prior import PriorPrediction, ShapePrior, SketchCache

AUTO = "auto"
"""The prior name that asks for the choice."""


def projected_silhouette(prediction: PriorPrediction, pose_world_camera: np.ndarray) -> np.ndarray:
    """The predicted occupancy (v > 0.5) seen through the prediction's crop camera (bool)."""
    crop = prediction.crop.intrinsics
    occupied = np.argwhere(prediction.probabilities > 0.5) + 0.5
    mask = np.zeros((crop.height, crop.width), dtype=bool)
    if len(occupied) == 0:
        return mask
    points_camera = transform_points(
        invert_transform(pose_world_camera), prediction.grid.voxel_to_world(occupied)
    )
    z = points_camera[:, 2]
    u = np.rint(crop.fx * points_camera[:, 0] / z + crop.cx).astype(int)
    v = np.rint(crop.fy * points_camera[:, 1] / z + crop.cy).astype(int)
    inside = (z > 0) & (u >= 0) & (u < crop.width) & (v >= 0) & (v < crop.height)
    mask[v[inside], u[inside]] = True
    # A voxel covers about voxel_size * f / z pixels: close the gaps between projected centres.
    radius = int(np.ceil(0.5 * prediction.grid.voxel_size_m * crop.fx / float(np.median(z))))
    return ndimage.binary_closing(mask, iterations=max(1, radius)) | mask


def silhouette_agreement(
    prediction: PriorPrediction,
    pose_world_camera: np.ndarray,
    seen: np.ndarray | None = None,
) -> float:
    """IoU of the projected prediction with the seen silhouette (default: the prediction's
    ``seen_silhouette``, which is the depth's with RGB-D, else the sketch net's)."""
    if seen is None:
        seen = prediction.seen_silhouette
    seen_mask = prediction.silhouette > 0.5 if seen is None else np.asarray(seen, dtype=bool)
    projected = projected_silhouette(prediction, pose_world_camera)
    union = np.count_nonzero(projected | seen_mask)
    return float(np.count_nonzero(projected & seen_mask) / union) if union else 0.0


def choose_prior(
    priors: Mapping[str, ShapePrior],
    colour_rgb: np.ndarray,
    intrinsics: CameraIntrinsics,
    pose_world_camera: np.ndarray,
    grid: VoxelGrid,
    *,
    depth_m: np.ndarray | None = None,
) -> tuple[PriorPrediction, dict[str, float]]:
    """The prediction of the prior whose shape best explains the image (its ``prior`` is the
    name it has in ``priors``), and every prior's score (ties go to the first in order)."""
    if not priors:
        raise ValueError("no priors to choose from")
    # Each prediction carries the name it was asked for (a loaded prior may call itself else).
    # Priors that share a sketch net (general and box) run it once on a crop they share.
    sketch_cache: SketchCache = {}
    predictions = {
        name: replace(
            prior.predict(
                colour_rgb,
                intrinsics,
                pose_world_camera,
                grid,
                depth_m=depth_m,
                sketch_cache=sketch_cache,
            ),
            prior=name,
        )
        for name, prior in priors.items()
    }
    scores = {
        name: silhouette_agreement(prediction, pose_world_camera)
        for name, prediction in predictions.items()
    }
    best = max(scores, key=lambda name: scores[name])
    return predictions[best], scores
