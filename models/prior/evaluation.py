"""Evaluation of a shape prior on the bench: render each object, predict, compare with the truth.

Each object stands on the bench table at the object point and is seen by the deployment camera
(full Kinect v2 colour frame, time-of-flight depth noise for RGB-D) in ``views`` random yaws.
Held-out procedural shapes use shape seeds from :data:`models.prior.dataset.EVAL_SEED_START` on,
never used for training data. Metrics per view: voxel IoU at 0.5 against the voxelised true mesh
in the registered grid, Chamfer distance (mm, unsquared, pred->gt + gt->pred means over 10,000
surface samples each), F-scores at 2 and 5 mm (see :mod:`models.metrics`), and the object's size:
the extent of the predicted occupancy (v > 0.5) along each grid axis against the true mesh's,
as a relative error; an object's numbers are the means over its views (its size error the median).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import trimesh

from models.camera import CameraIntrinsics
from models.families import SHAPE_GROUPS
from models.geometry import (
    VoxelGrid,
    axes_facing_camera,
    extent_along_axes_m,
    make_transform,
    occupied_extent_m,
    rotation_about_axis,
)
from models.metrics import surfaces_metrics, voxel_iou
from models.prior.auto import AUTO
from models.prior.dataset import EVAL_SEED_START, generated_shape, shape_rngs
from models.prior.shape_prior import ShapePrior
from models.render import Scene, apply_kinect_depth_noise, render
from models.shapes import voxelize
from models.vision import VisionSettings, estimate_from_frame


@dataclass(frozen=True)
class EvalObject:
    """An object to evaluate: a mesh in the table frame and its name / category."""

    name: str
    category: str
    mesh: trimesh.Trimesh


@dataclass(frozen=True)
class BenchCamera:
    """The bench camera used for evaluation (the deployment camera)."""

    intrinsics: CameraIntrinsics
    pose_world_camera: np.ndarray
    object_albedo_rgb: tuple[float, float, float] = (0.75, 0.35, 0.25)
    table_size_m: tuple[float, float] = (1.2, 0.8)


def held_out_objects(
    categories: Sequence[str],
    shapes_per_category: int,
    first_seed: int = EVAL_SEED_START,
    *,
    size_range_m: tuple[float, float] | None = None,
) -> list[EvalObject]:
    """Generated shapes (categories or families) with seeds ``first_seed ..`` (>=
    EVAL_SEED_START: never trained on). With ``size_range_m`` each is scaled to a largest
    extent drawn in that range (e.g. 3-6 cm: the small objects)."""
    if first_seed < EVAL_SEED_START:
        raise ValueError(f"held-out shape seeds start at {EVAL_SEED_START}")
    objects = []
    for category in categories:
        for n in range(shapes_per_category):
            seed = first_seed + n
            shape_rng, _ = shape_rngs(SHAPE_GROUPS.index(category), seed)
            mesh = generated_shape(category, shape_rng)
            if size_range_m is not None:
                mesh.apply_scale(shape_rng.uniform(*size_range_m) / float(np.max(mesh.extents)))
            objects.append(EvalObject(f"{category}_{seed}", category, mesh))
    return objects


def extent_errors(
    probabilities: np.ndarray, grid: VoxelGrid, mesh_world: trimesh.Trimesh
) -> np.ndarray:
    """Relative error of the predicted occupancy's extent along each grid axis (x, y, z) against
    the true mesh's (NaN for an empty prediction)."""
    predicted = occupied_extent_m(probabilities, grid)
    if predicted is None:
        return np.full(3, np.nan)
    true = extent_along_axes_m(mesh_world.vertices, grid.axes_world)
    return (predicted - true) / true


def evaluate_prior(
    priors: Mapping[str, ShapePrior],
    objects: Sequence[EvalObject],
    camera: BenchCamera,
    *,
    views: int = 4,
    input_mode: Literal["rgb", "rgbd"] = "rgb",
    settings: VisionSettings | None = None,
    seed: int = 0,
    progress: bool = True,
) -> dict:
    """Per-object and mean metrics, as ``{"objects": [...], "mean": {...}, "per_category":
    {...}}`` with ``iou``, ``chamfer_mm``, ``fscore_2mm``, ``fscore_5mm`` and the size errors.
    One prior is evaluated as it is; several are chosen from per view (``prior = "auto"``).
    What is scored is the estimate a session starts from (:func:`models.vision.estimate_from_frame`:
    with RGB-D, the depth fused into the prior), its surface through the session's extraction."""
    from tqdm import tqdm

    first = next(iter(priors.values()))
    name = first.name if len(priors) == 1 else AUTO
    grid = VoxelGrid(
        first.preset.voxel_resolution,
        first.grid_extent_m,
        (0.0, 0.0, 0.0),
        axes_facing_camera(camera.pose_world_camera[:3, 3]),
    )
    rows = []
    bar = tqdm(total=len(objects) * views, desc=f"eval {name} {input_mode}", disable=not progress)
    for index, obj in enumerate(objects):
        rng = np.random.default_rng((seed, index))
        per_view = []
        for _ in range(views):
            yaw = rng.uniform(0.0, 2.0 * math.pi)
            mesh_world = obj.mesh.copy()
            mesh_world.apply_transform(make_transform(rotation_about_axis((0, 0, 1), yaw)))
            scene = Scene.bench(mesh_world, camera.object_albedo_rgb, camera.table_size_m)
            frame = render(scene, camera.intrinsics, camera.pose_world_camera, rng=rng)
            depth = None
            if input_mode == "rgbd":
                depth = apply_kinect_depth_noise(
                    frame.depth_m, frame.normals_camera, rng, intrinsics=camera.intrinsics
                )
            estimate = estimate_from_frame(
                priors,
                frame.colour_rgb,
                camera.intrinsics,
                camera.pose_world_camera,
                grid,
                depth_m=depth,
                input_mode=input_mode,
                settings=settings,
            )
            # An object-frame prior decodes in the grid it fitted to the object.
            truth = voxelize(mesh_world, estimate.grid)
            surface = surfaces_metrics(
                estimate.surface_mesh(), mesh_world, seed=int(rng.integers(1 << 31))
            )
            errors = extent_errors(estimate.probabilities, estimate.grid, mesh_world)
            per_view.append(
                {
                    "size_error": float(np.max(np.abs(errors))),
                    "extent_error_xyz": errors.tolist(),
                    "prior": estimate.prediction.prior,
                    "symmetry": None if estimate.symmetry is None else estimate.symmetry.kind,
                    "iou": voxel_iou(estimate.probabilities[None], truth[None].astype(np.float32)),
                    # An empty prediction has no surface: no Chamfer distance (counted separately).
                    "chamfer_mm": surface.chamfer_mm
                    if math.isfinite(surface.chamfer_mm)
                    else np.nan,
                    "fscore_2mm": surface.fscore_2mm,
                    "fscore_5mm": surface.fscore_5mm,
                }
            )
            bar.update()
        row: dict = {"name": obj.name, "category": obj.category}
        row.update({key: _mean([v[key] for v in per_view]) for key in SCORES})
        row["size_error"] = _median([v["size_error"] for v in per_view])
        row["extent_error_xyz"] = [
            _median([v["extent_error_xyz"][axis] for v in per_view]) for axis in range(3)
        ]
        row["priors_chosen"] = sorted({v["prior"] for v in per_view})
        row["symmetry_views"] = sum(v["symmetry"] is not None for v in per_view)
        # Per view (the same views for every prior: they depend on the seed and the object
        # only), so the automatic choice can be checked against each single prior's.
        row["views"] = [
            {
                "prior": v["prior"],
                "iou": round(v["iou"], 4),
                "chamfer_mm": round(v["chamfer_mm"], 2) if math.isfinite(v["chamfer_mm"]) else None,
            }
            for v in per_view
        ]
        row["empty_views"] = int(sum(math.isnan(v["chamfer_mm"]) for v in per_view))
        rows.append(row)
    bar.close()
    per_category = {
        category: summarise_rows([r for r in rows if r["category"] == category])
        for category in dict.fromkeys(r["category"] for r in rows)
    }
    return {
        "prior": name,
        "preset": first.preset.name,
        "input": input_mode,
        "views": views,
        "chamfer": "mm, unsquared: mean NN distance pred->gt + gt->pred, 10k samples each; "
        "null where every view's prediction was empty (empty_views counts them)",
        "objects": rows,
        "per_category": per_category,
        "mean": summarise_rows(rows),
    }


SCORES = ("iou", "chamfer_mm", "fscore_2mm", "fscore_5mm")


def _median(values: Sequence[float]) -> float | None:
    """Median over the finite values; None (JSON null) when there are none."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.median(finite)) if finite else None


def _mean(values: Sequence[float]) -> float | None:
    """Mean over the finite values; None (JSON null) when there are none."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(finite)) if finite else None


def summarise_rows(rows: Sequence[dict]) -> dict:
    """Mean scores, median size error and counts of per-object rows."""
    summary: dict = {key: _mean([r[key] for r in rows]) for key in SCORES}
    summary["size_error_median"] = _median([r["size_error"] for r in rows])
    summary["objects"] = len(rows)
    summary["empty_views"] = int(sum(r["empty_views"] for r in rows))
    return summary
