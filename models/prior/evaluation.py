"""Evaluation of a shape prior on the bench: render each object, predict, compare with the truth.

Each object stands on the bench table at the object point and is seen by the deployment camera
(full Kinect v2 colour frame, time-of-flight depth noise for RGB-D) in ``views`` random yaws.
Held-out procedural shapes use shape seeds from :data:`models.prior.dataset.EVAL_SEED_START` on,
never used for training data. Metrics per view: voxel IoU at 0.5 against the voxelised true mesh
in the registered grid, Chamfer distance (mm, unsquared, pred->gt + gt->pred means over 10,000
surface samples each) and F-scores at 2 and 5 mm (see :mod:`models.metrics`); an object's numbers
are the means over its views.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import trimesh

from models.camera import CameraIntrinsics
from models.geometry import VoxelGrid, axes_facing_camera, make_transform, rotation_about_axis
from models.metrics import mesh_metrics, voxel_iou
from models.prior.dataset import EVAL_SEED_START, shape_rngs
from models.prior.shape_prior import ShapePrior
from models.procedural import ALL_CATEGORIES, procedural_shape
from models.render import Scene, apply_kinect_depth_noise, render
from models.shapes import voxelize


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
    categories: Sequence[str], shapes_per_category: int, first_seed: int = EVAL_SEED_START
) -> list[EvalObject]:
    """Procedural shapes with seeds ``first_seed ..`` (>= EVAL_SEED_START: never trained on)."""
    if first_seed < EVAL_SEED_START:
        raise ValueError(f"held-out shape seeds start at {EVAL_SEED_START}")
    objects = []
    for category in categories:
        for n in range(shapes_per_category):
            seed = first_seed + n
            shape_rng, _ = shape_rngs(ALL_CATEGORIES.index(category), seed)
            mesh = procedural_shape(category, shape_rng)
            objects.append(EvalObject(f"{category}_{seed}", category, mesh))
    return objects


def evaluate_prior(
    prior: ShapePrior,
    objects: Sequence[EvalObject],
    camera: BenchCamera,
    *,
    views: int = 4,
    input_mode: Literal["rgb", "rgbd"] = "rgb",
    seed: int = 0,
    progress: bool = True,
) -> dict:
    """Per-object and mean metrics, as ``{"objects": [...], "mean": {...}, "per_category":
    {...}}`` with ``iou``, ``chamfer_mm``, ``fscore_2mm``, ``fscore_5mm``."""
    from tqdm import tqdm

    n = prior.preset.voxel_resolution
    grid = VoxelGrid(
        n, prior.grid_extent_m, (0.0, 0.0, 0.0), axes_facing_camera(camera.pose_world_camera[:3, 3])
    )
    rows = []
    bar = tqdm(
        total=len(objects) * views, desc=f"eval {prior.name} {input_mode}", disable=not progress
    )
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
            prediction = prior.predict(
                frame.colour_rgb, camera.intrinsics, camera.pose_world_camera, grid, depth_m=depth
            )
            # An object-frame prior decodes in the grid it fitted to the object.
            truth = voxelize(mesh_world, prediction.grid)
            surface = mesh_metrics(
                prediction.probabilities,
                prediction.grid,
                mesh_world,
                seed=int(rng.integers(1 << 31)),
            )
            per_view.append(
                {
                    "iou": voxel_iou(
                        prediction.probabilities[None], truth[None].astype(np.float32)
                    ),
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
        row.update({key: _mean([v[key] for v in per_view]) for key in per_view[0]})
        row["empty_views"] = int(sum(math.isnan(v["chamfer_mm"]) for v in per_view))
        rows.append(row)
    bar.close()
    per_category = {
        category: _summary([r for r in rows if r["category"] == category])
        for category in dict.fromkeys(r["category"] for r in rows)
    }
    return {
        "prior": prior.name,
        "preset": prior.preset.name,
        "input": input_mode,
        "views": views,
        "chamfer": "mm, unsquared: mean NN distance pred->gt + gt->pred, 10k samples each; "
        "null where every view's prediction was empty (empty_views counts them)",
        "objects": rows,
        "per_category": per_category,
        "mean": _summary(rows),
    }


def _mean(values: Sequence[float]) -> float | None:
    """Mean over the finite values; None (JSON null) when there are none."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(finite)) if finite else None


def _summary(rows: Sequence[dict]) -> dict:
    summary: dict = {
        key: _mean([r[key] for r in rows])
        for key in ("iou", "chamfer_mm", "fscore_2mm", "fscore_5mm")
    }
    summary["objects"] = len(rows)
    summary["empty_views"] = int(sum(r["empty_views"] for r in rows))
    return summary
