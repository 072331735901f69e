"""How far can touches lower the Chamfer distance at all? Bounds for the exploration benchmark.

Per object, with the exploration benchmark's set-up (:class:`ObjectRun`: the bench camera's
frame, the prior's vision estimate, the voxelised truth; every estimate measured through
``ShapeEstimate.surface_mesh``, the same 1.5 mm extraction for every update):

* ``floor_mm``: the Chamfer distance of the true voxels themselves (the voxelised mesh through
  that extraction): what a perfect voxel estimate at this resolution scores. The fused update
  is not bound by it: its surface passes through the measured points, between voxel centres.
* ``latent_fit_mm``: the prior's latent fitted to the whole true volume (Adam on the binary
  cross-entropy, from the vision latent). Latent refinement cannot beat the best shape the
  latent can express, and this is close to it: complete knowledge of the shape, not 10 touches.
* ``ideal_touches_fused_mm``: the curve after 0..K touches of an idealised sensor, with the
  fused update exactly as the pipeline makes it (``LearnedPerception.refine_fused``, the
  config's ``[models]`` fusion settings): the prior's surface bent through every measured
  point by the Gaussian-process correction (``models.touch.fused``; the latent refinement and
  the pose fit first where the config enables them).
* ``ideal_touches_global_mm``: the same touches with the global update (the default: the
  prior's latent fitted to every touch, taken once it predicts a held-out touch, then the fused
  correction on that mean; ``models.touch.global_fit``).
* ``ideal_touches_mm``: the same touches with the prior update (``LearnedPerception.refine_with``
  on the merged voxel constraints of all touches so far).

The fused and global curves start where a session starts (``start_mm``: with depth, the camera's
points fused into the prior, as ``bench explore`` starts them); the prior update's from the
prior's voxels (``vision_mm``), as it refines them.

Each ideal touch is a pad-sized range image (a :class:`TouchResult`, world-frame rays): every
ray of the pad, 1 mm apart, measures its first hit on the true mesh within ``IDEAL_DEPTH_M`` of
the target, at a random surface point approached along the true normal. That is far more than
a GelSight touch gives: the gel images only where it is pressed, a few square millimetres at
the contact force, and the target is not known to lie on the surface. Both updates see the same
touches (the same seeds). ``ideal_oracle_touches[_fused]_mm``: each touch the best of K random
targets by the truth.

A touch policy or a refinement that lowers the error by more than the ideal touches do would
have to know more than they measure; the latent fit bounds every latent refinement.
"""

from __future__ import annotations

import math
import multiprocessing
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from functools import partial
from typing import Any, Literal, NamedTuple

import numpy as np
import torch
import trimesh

from controller.benchmarks.explore import ExploreSettings, ObjectRun, with_threads
from controller.benchmarks.explore_summary import change_pct
from controller.config import Config
from controller.motion.poses import pad_pose_facing
from controller.perception.learned import LearnedPerception
from controller.perception.protocol import ShapeEstimate
from models.prior.evaluation import EvalObject
from models.prior.evaluation import _mean as finite_mean
from models.prior.shape_prior import ShapePrior
from models.tactile.lut import GelSightLUT
from models.touch.constraints import (
    TouchResult,
    constraints_from_touches,
    pad_grid_world,
    touch_constraints,
)
from models.touch.refinement import Decode, decode_volume

IDEAL_RAY_SPACING_M = 0.001
IDEAL_STANDOFF_M = 0.03
"""Rays start this far in front of the target, along the normal."""
IDEAL_DEPTH_M = 0.02
"""A ray measures hits up to this far beyond the target; past it, it is free to there."""
TARGET_POOL_SAMPLES = 10_000
MIN_TARGET_HEIGHT_M = 0.01
MAX_DOWNWARD_NORMAL_Z = -0.5
"""Targets on the bottom (normals pointing down more than this) are left out, as the pipeline's
table filter leaves out approaches from below."""
UPDATES = ("global", "fused", "prior")
"""The shape updates the ideal touches are refined by (:func:`refiner`)."""
CURVE_KEYS = {
    ("prior", False): "ideal_touches",
    ("prior", True): "ideal_oracle_touches",
    ("fused", False): "ideal_touches_fused",
    ("fused", True): "ideal_oracle_touches_fused",
    ("global", False): "ideal_touches_global",
    ("global", True): "ideal_oracle_touches_global",
}
"""(update, oracle) -> the row's curve key (``<key>_mm``) and the summary's."""

Refine = Callable[[ShapeEstimate, list[TouchResult]], ShapeEstimate]
"""``refine(estimate, touches)``: ``estimate`` refined by all touches so far (the newest last)."""


@dataclass(frozen=True)
class BoundsSettings:
    """What the bounds measure (the CLI's options)."""

    touch_counts: tuple[int, ...] = (10, 30)
    fit_steps: int = 300
    fit_learning_rate: float = 1e-2
    oracle_candidates: int = 0
    """Also the ideal touches chosen by the truth among this many random targets each (0: no)."""
    prior: str = "auto"
    seed: int = 0
    updates: tuple[str, ...] = UPDATES
    """The shape updates with ideal touches (``global``, ``fused``, ``prior``)."""
    input_mode: Literal["auto", "rgb", "rgbd"] = "auto"
    """The camera input vision starts from (``auto``: RGB-D where the camera gives depth)."""

    def __post_init__(self) -> None:
        if not self.touch_counts or min(self.touch_counts) < 1:
            raise ValueError("touch counts must be >= 1")
        unknown = [u for u in self.updates if u not in UPDATES]
        if unknown or not self.updates or len(set(self.updates)) != len(self.updates):
            raise ValueError(f"updates {self.updates}: distinct, from {', '.join(UPDATES)}")
        if self.fit_steps < 0 or self.oracle_candidates < 0:
            raise ValueError("fit_steps and oracle_candidates must be >= 0")


def ideal_touch(
    mesh_world: trimesh.Trimesh,
    point_world: np.ndarray,
    normal_world: np.ndarray,
    pad_size_m: tuple[float, float],
) -> TouchResult:
    """An ideal range-imaging touch at a surface point (module doc): world-frame rays, those
    that hit ending on the true surface, the others free to ``IDEAL_DEPTH_M`` beyond it."""
    pose_world_pad = pad_pose_facing(point_world, normal_world, IDEAL_STANDOFF_M)
    direction = pose_world_pad[:3, 2]
    origins = pad_grid_world(pose_world_pad, pad_size_m, IDEAL_RAY_SPACING_M)
    reach = IDEAL_STANDOFF_M + IDEAL_DEPTH_M
    ends = origins + reach * direction
    hit = np.zeros(len(origins), dtype=bool)
    locations, ray_index, _ = mesh_world.ray.intersects_location(
        origins, np.repeat(direction[None], len(origins), axis=0), multiple_hits=False
    )
    for location, ray in zip(locations, ray_index, strict=True):
        if (location - origins[ray]) @ direction <= reach:
            hit[ray], ends[ray] = True, location
    if not hit.any():
        return TouchResult.from_miss(origins, ends)
    return TouchResult.from_contact(ends[hit], direction, origins[0], ends[~hit])


def ideal_targets(
    mesh_world: trimesh.Trimesh, count: int, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """``count`` random surface points (area-uniform) and their outward normals, off the
    bottom; (count, 3) each. The first of a seeded order of a fixed pool, so a shorter run
    touches the first targets of a longer one."""
    points, faces = trimesh.sample.sample_surface(mesh_world, TARGET_POOL_SAMPLES, seed=seed)
    normals = mesh_world.face_normals[faces]
    keep = (points[:, 2] > MIN_TARGET_HEIGHT_M) & (normals[:, 2] > MAX_DOWNWARD_NORMAL_Z)
    points, normals = points[keep], normals[keep]
    if count > len(points):
        raise ValueError(f"{count} targets asked, the surface pool has {len(points)}")
    chosen = np.random.default_rng(seed).permutation(len(points))[:count]
    return points[chosen], normals[chosen]


def fit_latent_to_volume(
    decode: Decode, latent: torch.Tensor, truth: torch.Tensor, steps: int, learning_rate: float
) -> torch.Tensor:
    """The latent whose decoded volume best matches ``truth`` (N, N, N) in binary
    cross-entropy, by Adam from ``latent``; detached."""
    variable = latent.detach().clone().requires_grad_(True)
    optimiser = torch.optim.Adam([variable], lr=learning_rate)
    with torch.enable_grad():
        for _ in range(steps):
            probabilities = decode_volume(decode, variable).clamp(1e-6, 1 - 1e-6)
            loss = torch.nn.functional.binary_cross_entropy(probabilities, truth)
            (variable.grad,) = torch.autograd.grad(loss, variable)
            optimiser.step()
    return variable.detach()


def _chamfer_mm(run: ObjectRun, probabilities: np.ndarray) -> float | None:
    volume = np.asarray(probabilities, dtype=np.float32)
    return run.metrics(replace(run.vision, probabilities=volume))["chamfer_mm"]


class IdealCurve(NamedTuple):
    """One ideal touch curve (:func:`ideal_touch_curve`)."""

    chamfer_mm: list[float | None]
    """After 0..K touches (None: an empty prediction)."""
    touches: list[TouchResult]
    """The touches made."""
    estimate: ShapeEstimate
    """The estimate after the last touch."""


def curve_start(run: ObjectRun, update: str) -> tuple[ShapeEstimate, float | None]:
    """Where ``update``'s curve starts, and its Chamfer distance: the fused and global updates
    from the session's start (the camera's depth fused in, where the input has it), the prior
    update from the prior's voxels."""
    if update in ("fused", "global"):
        return run.vision_fused, run.vision_fused_metrics["chamfer_mm"]
    return run.vision, run.vision_metrics["chamfer_mm"]


def ideal_touch_curve(
    run: ObjectRun,
    refine: Refine,
    start: tuple[ShapeEstimate, float | None],
    pad_size_m: tuple[float, float],
    touches: int,
    candidates_per_touch: int,
    seed: int,
) -> IdealCurve:
    """Chamfer distance after 0..``touches`` ideal touches from the ``start`` estimate (and its
    distance), each the best of ``candidates_per_touch`` random targets by the truth (1: no
    choice), refined by ``refine`` with all touches so far and scored by ``run.metrics``."""
    points, normals = ideal_targets(run.mesh_world, touches * candidates_per_touch, seed)
    (estimate, start_mm), made = start, []
    chamfers = [start_mm]
    for touch in range(touches):
        trials = []
        for index in range(touch * candidates_per_touch, (touch + 1) * candidates_per_touch):
            touched = ideal_touch(run.mesh_world, points[index], normals[index], pad_size_m)
            refined = refine(estimate, [*made, touched])
            error = run.metrics(refined)["chamfer_mm"]
            trials.append((math.inf if error is None else error, index, touched, refined))
        error, _, touched, estimate = min(trials, key=lambda trial: trial[:2])
        chamfers.append(None if math.isinf(error) else error)  # inf: an empty prediction
        made.append(touched)
    return IdealCurve(chamfers, made, estimate)


def refiner(run: ObjectRun, perception: LearnedPerception, update: str) -> Refine:
    """The pipeline's refinement by ``update``: ``global`` or ``fused``
    (:meth:`LearnedPerception.refine_fused` on the touches) or ``prior``
    (:meth:`LearnedPerception.refine_with` on their merged voxel constraints in the estimate's
    grid)."""
    if update in ("fused", "global"):
        fused_request = run.request("active", update)

        def refine_fused(estimate: ShapeEstimate, touches: list[TouchResult]) -> ShapeEstimate:
            return perception.refine_fused(estimate, touches, fused_request)

        return refine_fused
    if update != "prior":
        raise ValueError(f"unknown update {update!r}; choose from {', '.join(UPDATES)}")
    prior_request = run.request("active", "prior")

    def refine_prior(estimate: ShapeEstimate, touches: list[TouchResult]) -> ShapeEstimate:
        constraints = constraints_from_touches(touches, run.grid)
        return perception.refine_with(estimate, constraints, prior_request)

    return refine_prior


def object_bounds(
    config: Config,
    calibration: GelSightLUT,
    priors: Mapping[str, ShapePrior],
    obj: EvalObject,
    settings: BoundsSettings,
) -> dict[str, Any]:
    """One object's row of the bounds JSON."""
    touches = max(settings.touch_counts)
    explore = ExploreSettings(
        touches=touches, input_mode=settings.input_mode, prior=settings.prior, seed=settings.seed
    )
    run = ObjectRun(config, calibration, priors, obj, explore)
    prior = run.prior
    try:
        vision = run.vision
        assert vision.latent is not None
        fitted = fit_latent_to_volume(
            prior.decode,
            torch.as_tensor(vision.latent),
            torch.from_numpy(run.truth),
            settings.fit_steps,
            settings.fit_learning_rate,
        )
        with torch.no_grad():
            fitted_probabilities = prior.decode(fitted).numpy()
        row: dict[str, Any] = {
            "name": obj.name,
            "category": obj.category,
            "vision_mm": run.vision_metrics["chamfer_mm"],
            "start_mm": run.vision_fused_metrics["chamfer_mm"],
            "floor_mm": _chamfer_mm(run, run.truth),
            "latent_fit_mm": _chamfer_mm(run, fitted_probabilities),
        }
        perception = run.perception(settings.seed)
        pad_size_m = perception.pad_size_m
        made: list[TouchResult] = []
        for update in settings.updates:
            # The same seeds for every update: they see the same touches.
            refine = refiner(run, perception, update)
            curve = partial(ideal_touch_curve, run, refine, curve_start(run, update), pad_size_m)
            ideal = curve(touches, 1, run.metric_seed)
            row[f"{CURVE_KEYS[update, False]}_mm"], made = ideal.chamfer_mm, ideal.touches
            if settings.oracle_candidates > 1:
                oracle = curve(touches, settings.oracle_candidates, run.metric_seed + 1)
                row[f"{CURVE_KEYS[update, True]}_mm"] = oracle.chamfer_mm
        constraints = [touch_constraints(touch, run.grid) for touch in made]
        row["ideal_voxels_per_touch"] = {
            "occupied": float(np.mean([len(c.occupied) for c in constraints])),
            "empty": float(np.mean([len(c.empty) for c in constraints])),
        }
        return row
    finally:
        run.close()


def summarise_bounds(rows: Sequence[dict[str, Any]], touch_counts: Sequence[int]) -> dict:
    """Means over objects; ``*_change_pct`` are means of the per-object changes: the floor's
    and the latent fit's from vision's voxels, each curve's from its own start (its first
    value)."""
    summary: dict[str, Any] = {
        key: finite_mean([row[key] for row in rows if key in row])
        for key in ("vision_mm", "start_mm", "floor_mm", "latent_fit_mm")
    }
    for key, name in (("floor_mm", "floor"), ("latent_fit_mm", "latent_fit")):
        summary[f"{name}_change_pct"] = finite_mean(
            [change_pct(row["vision_mm"], row[key]) for row in rows]
        )
    for key in CURVE_KEYS.values():
        curves = [row[f"{key}_mm"] for row in rows if f"{key}_mm" in row]
        if curves:
            summary[key] = {
                str(count): {
                    "chamfer_mm": finite_mean([curve[count] for curve in curves]),
                    "change_pct": finite_mean([change_pct(c[0], c[count]) for c in curves]),
                }
                for count in touch_counts
            }
    return summary


def run_bounds(
    config: Config,
    objects: Sequence[EvalObject],
    settings: BoundsSettings,
    *,
    priors: Mapping[str, ShapePrior],
    calibration: GelSightLUT,
    workers: int = 1,
) -> dict[str, Any]:
    """The bounds JSON: per object ``vision_mm``, ``floor_mm``, ``latent_fit_mm``, the ideal
    touch curves of every update (``ideal_touches_fused_mm``, ``ideal_touches_mm``, after 0..K
    touches; the oracle's with ``oracle_candidates``) and a ``summary`` (docs/explore.md)."""
    args = [(config, calibration, priors, obj, settings) for obj in objects]
    if workers <= 1:
        rows = [object_bounds(*a) for a in args]
    else:
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(workers, mp_context=context) as pool:
            futures = [
                pool.submit(with_threads, torch.get_num_threads(), object_bounds, *a) for a in args
            ]
            rows = [future.result() for future in futures]
    models = config.models
    fusion = LearnedPerception(
        config,
        camera_position_world=config.cameras.rgbd.pose_world_camera()[:3, 3],
        calibration=calibration,
    ).fusion_settings
    return {
        "prior": settings.prior,
        "seed": settings.seed,
        "fit": {"steps": settings.fit_steps, "learning_rate": settings.fit_learning_rate},
        "oracle_candidates": settings.oracle_candidates,
        "updates": list(settings.updates),
        "input": settings.input_mode,
        "ideal_touch": {
            "ray_spacing_mm": IDEAL_RAY_SPACING_M * 1e3,
            "depth_beyond_target_mm": IDEAL_DEPTH_M * 1e3,
            "pad_mm": [config.sensor.pad_width_mm, config.sensor.pad_height_mm],
        },
        "refinement": {
            "loss": models.refine_loss,
            "learning_rate": models.refine_learning_rate,
            "iterations_per_touch": models.refine_iterations_per_touch,
            "anchor_weight": models.refine_anchor_weight,
            "write_measurements": models.refine_write_measurements,
            "fusion": asdict(fusion),
        },
        "chamfer": "mm, unsquared: mean NN distance pred->gt + gt->pred, 10k samples each",
        "objects": rows,
        "summary": summarise_bounds(rows, settings.touch_counts),
    }
