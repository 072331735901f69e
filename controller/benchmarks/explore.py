"""The exploration benchmark: shape error versus number of touches, per touch policy and
update, on the simulated bench (docs/explore.md).
"""

from __future__ import annotations

import logging
import math
import multiprocessing
import zlib
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np
import torch

from controller.benchmarks.explore_summary import METRICS, mean_runs, summarise
from controller.benchmarks.robot_time import PlannedArm
from controller.benchmarks.sim_touch import TOUCH_START_WIDTH_M, SimTouchBench
from controller.benchmarks.timing import Stopwatch
from controller.benchmarks.touch_latency import latency_figures
from controller.config import Config
from controller.perception.learned import FUSED_UPDATES, LearnedPerception
from controller.perception.protocol import ShapeEstimate, TouchOutcome, TouchTarget
from controller.request import ExploreRequest
from controller.targets import rolls_avoiding_rim_stops, window_leading_roll
from models.geometry import make_transform, rotation_about_axis
from models.metrics import (
    SURFACE_SAMPLES,
    distance_to_mesh,
    sample_surface,
    surface_metrics,
    voxel_iou,
)
from models.prior.evaluation import EvalObject
from models.prior.shape_prior import ShapePrior
from models.shapes import fits_extent, load_mesh_file, voxelize
from models.tactile.lut import GelSightLUT
from models.touch.policy import oracle_select
from models.touch.refinement import TouchLossKind, touch_loss

log = logging.getLogger(__name__)

T = TypeVar("T")

Policy = Literal["active", "efficient", "random", "oracle"]
Update = Literal["global", "fused", "prior", "direct"]
METHODS: dict[str, tuple[Policy, Update]] = {
    "active-fused": ("active", "fused"),
    "random-fused": ("random", "fused"),
    "oracle-fused": ("oracle", "fused"),
    "active-prior": ("active", "prior"),
    "random-prior": ("random", "prior"),
    "active-direct": ("active", "direct"),
    "oracle-prior": ("oracle", "prior"),
    "active-global": ("active", "global"),
    "random-global": ("random", "global"),
    "efficient-global": ("efficient", "global"),
    "efficient-fused": ("efficient", "fused"),
    "oracle-global": ("oracle", "global"),
}
"""Method name -> (touch policy, shape update). A method's seeds depend on its position here."""
MAX_OBJECT_HEIGHT_M, MAX_OBJECT_WIDTH_M = 0.25, 0.20
"""Mesh files larger than this are scaled down to fit the voxel grid."""


# --- objects --------------------------------------------------------------------------------------


def file_objects(
    paths: Sequence[str | Path], *, up_axis: str = "z", fit_size_m: float | None = None
) -> list[EvalObject]:
    """Mesh files as benchmark objects, upright (``up_axis`` -> +z) with their bottom centre at
    the object point. Without ``fit_size_m`` (largest extent, metres) the file's units are
    taken as metres, and a mesh too large for the voxel grid is scaled down to fit it."""
    objects = []
    for path in paths:
        mesh = load_mesh_file(path, up_axis=up_axis, fit_max_extent_m=fit_size_m)
        if not fits_extent(mesh, MAX_OBJECT_HEIGHT_M, MAX_OBJECT_WIDTH_M):
            ex, ey, ez = np.maximum(mesh.extents, 1e-9)
            factor = min(MAX_OBJECT_WIDTH_M / ex, MAX_OBJECT_WIDTH_M / ey, MAX_OBJECT_HEIGHT_M / ez)
            log.warning(
                "%s: %s m does not fit the grid; scaled by %.4g", path, mesh.extents, factor
            )
            mesh.apply_scale(factor)
        objects.append(EvalObject(Path(path).stem, "file", mesh))
    return objects


# --- the benchmark --------------------------------------------------------------------------------


@dataclass(frozen=True)
class ExploreSettings:
    """What the benchmark runs (the CLI's options)."""

    touches: int = 10
    methods: tuple[str, ...] = tuple(METHODS)
    random_runs: int = 10
    oracle_candidates: int = 4
    input_mode: Literal["auto", "rgb", "rgbd"] = "auto"
    prior: str = "auto"
    seed: int = 0
    timing_resolutions: tuple[int, ...] = (64, 128)
    """Select and refine latency at these resolutions (:func:`latency_figures`; empty: none)."""
    select_lag: bool = False
    """Choose each target from the estimate before the last touch's refinement, with every
    touch written in, as a session does while that refinement overlaps the arm's motion
    (``[motion] refine_while_moving``, docs/controller.md). False: from the latest estimate, as
    a session that refines first."""

    def __post_init__(self) -> None:
        unknown = [m for m in self.methods if m not in METHODS]
        if unknown or not self.methods:
            raise ValueError(f"unknown method(s) {unknown}; choose from {', '.join(METHODS)}")
        if self.touches < 1 or self.random_runs < 1 or self.oracle_candidates < 1:
            raise ValueError("touches, random_runs and oracle_candidates must be >= 1")


@dataclass
class TouchTrial:
    """One touch made on the bench and the estimate refined with it."""

    outcome: TouchOutcome
    estimate: ShapeEstimate
    metrics: dict[str, float | None]
    refine_s: float
    loss: tuple[float, float] = (0.0, 0.0)
    """The touch loss of all touches so far on the estimate before and after refining."""
    flipped_voxels: int = 0
    """Voxels the refinement moved across 0.5."""
    stopped_by: str | None = None
    """What stopped the fingers (``SimTouchBench.stopped_by``)."""


def _seed(*parts: int) -> int:
    """A 32-bit seed from integer parts (numpy's SeedSequence hashing)."""
    return int(np.random.SeedSequence(list(parts)).generate_state(1)[0])


def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


class ObjectRun:
    """What every method shares on one object: the bench, the vision estimate, the truth."""

    def __init__(
        self,
        config: Config,
        calibration: GelSightLUT,
        priors: Mapping[str, ShapePrior],
        obj: EvalObject,
        settings: ExploreSettings,
    ) -> None:
        self.config, self.calibration, self.priors = config, calibration, dict(priors)
        self.settings = settings
        # Seeds from the name: a run on a subset of objects repeats the full run's numbers.
        self.key = zlib.crc32(obj.name.encode())
        rng = np.random.default_rng((settings.seed, self.key))
        self.yaw_deg = float(rng.uniform(0.0, 360.0))
        self.mesh_world = obj.mesh.copy()
        self.mesh_world.apply_transform(
            make_transform(rotation_about_axis((0, 0, 1), math.radians(self.yaw_deg)))
        )
        self.bench = SimTouchBench(config, self.mesh_world, _seed(settings.seed, self.key))
        perception = self.perception(_seed(settings.seed, self.key))
        self.metric_seed = _seed(settings.seed, self.key, 7)
        frame = self.bench.frame()
        # The fused update starts where a session does (RGB-D: the depth fused into the prior);
        # the paper's updates from the prior's voxels.
        self.vision_fused = perception.reconstruct(frame, self.request("active", "fused"))
        self.vision = replace(
            self.vision_fused, probabilities=self.vision_fused.vision_probabilities, fused=None
        )
        # The estimate's grid: registered, or fitted to the object by an object-frame prior.
        self.grid = self.vision.grid
        self.truth = voxelize(self.mesh_world, self.grid).astype(np.float32)
        self.true_points = sample_surface(self.mesh_world, SURFACE_SAMPLES, self.metric_seed + 1)
        self.vision_metrics = self.metrics(self.vision)
        self.vision_fused_metrics = (
            self.metrics(self.vision_fused)
            if self.vision_fused.fused is not None
            else self.vision_metrics
        )
        self.prior = perception.prior(self.vision.prior)
        """The prior vision used (``auto`` chose it): its decoder refines the shape."""

    def perception(self, seed: int) -> LearnedPerception:
        return LearnedPerception(
            self.config,
            camera_position_world=self.config.cameras.rgbd.pose_world_camera()[:3, 3],
            calibration=self.calibration,
            priors=self.priors,
            seed=seed,
        )

    def request(self, policy: Policy, update: Update) -> ExploreRequest:
        return ExploreRequest(
            max_touches=self.settings.touches,
            policy="active" if policy == "oracle" else policy,
            update=update,
            input=self.settings.input_mode,
            prior=self.settings.prior,
        )

    def metrics(
        self, estimate: ShapeEstimate, outcomes: Sequence[TouchOutcome] = ()
    ) -> dict[str, float | None]:
        """The estimate's surface (:meth:`ShapeEstimate.surface_mesh`, every update through the
        same extraction) against the truth, and the touch fidelity: the median distance (mm)
        from every contact point so far to that surface (None before a contact)."""
        mesh = estimate.surface_mesh()
        predicted = sample_surface(mesh, SURFACE_SAMPLES, self.metric_seed)
        surface = surface_metrics(predicted, self.true_points)
        contacts = [o.contact_points_world for o in outcomes if len(o.contact_points_world)]
        fidelity = None
        if contacts:
            fidelity = _finite(
                1e3 * float(np.median(distance_to_mesh(np.concatenate(contacts), mesh)))
            )
        return {
            "chamfer_mm": _finite(surface.chamfer_mm),
            "fscore_5mm": surface.fscore_5mm,
            "fscore_2mm": surface.fscore_2mm,
            "iou": voxel_iou(estimate.probabilities[None], self.truth[None]),
            "touch_fidelity_mm": fidelity,
        }

    def trial(
        self,
        perception: LearnedPerception,
        estimate: ShapeEstimate,
        outcomes: list[TouchOutcome],
        target: TouchTarget,
        request: ExploreRequest,
        noise_seed: Sequence[int],
    ) -> TouchTrial | None:
        """Touch ``target`` on the bench, interpret it and refine with all touches so far."""
        measurement = self.bench.touch(target, noise_seed)
        if measurement is None:
            return None
        stopped_by = self.bench.stopped_by(measurement)
        outcome = perception.interpret(measurement)
        refine = Stopwatch()
        refined = refine(perception.refine, estimate, [*outcomes, outcome], request)
        constraints = perception.constraints([*outcomes, outcome], self.grid)
        loss = tuple(
            float(
                touch_loss(
                    torch.from_numpy(e.probabilities), constraints, self.config.models.refine_loss
                )
            )
            for e in (estimate, refined)
        )
        before, after = estimate.probabilities > 0.5, refined.probabilities > 0.5
        flipped = int(np.count_nonzero(before != after))
        metrics = self.metrics(refined, [*outcomes, outcome])
        return TouchTrial(outcome, refined, metrics, refine.wall_s[0], loss, flipped, stopped_by)

    def oracle_candidates(
        self, perception: LearnedPerception, estimate: ShapeEstimate, outcomes: list[TouchOutcome]
    ) -> list[TouchTarget]:
        """The best ``oracle_candidates`` feasible active windows plus as many feasible random
        touches, through the pipeline's own selection (and its feasibility filters)."""
        count = self.settings.oracle_candidates
        candidates: list[TouchTarget] = []
        for policy in ("active", "random"):
            found: list[TouchTarget] = []

            def collect(target: TouchTarget, found: list[TouchTarget] = found) -> bool:
                if len(found) < count and self.bench.allowed(target):
                    found.append(target)
                return len(found) >= count  # True ends the selection

            perception.select(estimate, self.request(policy, "prior"), outcomes, collect)
            candidates += found
        return candidates

    def close(self) -> None:
        self.bench.close()


def choose_oracle_trial(
    candidates: Sequence[TouchTarget], trial: Callable[[TouchTarget], TouchTrial | None]
) -> TouchTrial | None:
    """The oracle: the candidate whose trial leaves the lowest Chamfer distance (a failed touch
    or an empty prediction counts as infinite), or None when no candidate could be touched."""
    trials: dict[int, TouchTrial | None] = {}

    def error_after(candidate: TouchTarget) -> float:
        result = trial(candidate)
        trials[id(candidate)] = result
        chamfer = None if result is None else result.metrics["chamfer_mm"]
        return math.inf if chamfer is None else chamfer

    if not candidates:
        return None
    best, _ = oracle_select(candidates, error_after)  # type: ignore[arg-type]
    return trials[id(best)]


def _explore(run: ObjectRun, method: str, run_index: int, tick: Callable[[], None]) -> dict:
    """One method's curves on one object (one seeded run)."""
    settings = run.settings
    policy, update = METHODS[method]
    method_index = list(METHODS).index(method)
    perception = run.perception(_seed(settings.seed, run.key, method_index, run_index))
    request = run.request(policy, update)
    # RGB-D: the fused update starts from vision with the camera's depth fused in (as a
    # session's reconstruct gives it), so its curve measures what the touches add.
    fused = update in FUSED_UPDATES
    estimate = run.vision_fused if fused else run.vision
    start = run.vision_fused_metrics if fused else run.vision_metrics
    outcomes: list[TouchOutcome] = []
    curves: dict[str, list] = {key: [value] for key, value in start.items()}
    curves.update(
        select_s=[],
        refine_s=[],
        robot_s=[],
        contact=[],
        imprint=[],
        stopped_by=[],
        touch_loss=[],
        flipped=[],
        target=[],
    )
    arm = PlannedArm(run.config, run.bench.world.tool, run.bench.world.pose_world_base)
    chosen_from = estimate  # what the policy reads: the latest estimate, or the one before it
    for touch in range(settings.touches):
        noise = (settings.seed, run.key, method_index, run_index, touch)
        trial = partial(
            run.trial, perception, estimate, outcomes, request=request, noise_seed=noise
        )
        # The policy's time with the planner's checks, without the bench's start checks; the
        # oracle's whole choice (the oracle is not planned: it has no robot time).
        select, checks = Stopwatch(), Stopwatch()
        arm.set_estimate(chosen_from)
        if policy == "oracle":
            candidates = select(run.oracle_candidates, perception, chosen_from, outcomes)
            chosen = select(choose_oracle_trial, candidates, trial)
        else:
            allowed = partial(
                _allowed_by_bench_and_planner, partial(checks, run.bench.allowed), arm
            )
            target = select(
                perception.select,
                chosen_from,
                request,
                outcomes,
                allowed,
                robot_seconds=arm.seconds,
            )
            if target is not None:  # as a session does (the bench's tool placed by the pad)
                occupied = chosen_from.occupied_points_world()
                tool = run.bench.world.tool
                rolls = rolls_avoiding_rim_stops(target, outcomes)
                roll = window_leading_roll(target, occupied, tool, TOUCH_START_WIDTH_M, rolls)
                target = replace(target, roll_rad=roll)
            chosen = None if target is None else trial(target)
        select_s = sum(select.wall_s) - sum(checks.wall_s)
        tick()
        if chosen is None:
            log.info("%s: no feasible touch after %d", method, touch)
            break
        chosen_from = estimate if settings.select_lag else chosen.estimate
        estimate = chosen.estimate
        outcomes.append(chosen.outcome)
        for key, value in chosen.metrics.items():
            curves[key].append(value)
        curves["select_s"].append(select_s)
        curves["refine_s"].append(chosen.refine_s)
        if policy != "oracle":
            curves["robot_s"].append(arm.touch(chosen.outcome.measurement.target))
        curves["contact"].append(bool(chosen.outcome.measurement.contact))
        curves["imprint"].append(len(chosen.outcome.contact_points_world) > 0)
        curves["stopped_by"].append(chosen.stopped_by)
        curves["touch_loss"].append(list(chosen.loss))
        curves["flipped"].append(chosen.flipped_voxels)
        target = chosen.outcome.measurement.target
        curves["target"].append(
            np.round(np.concatenate([target.target_world, target.direction_world]), 4).tolist()
        )
    curves["touches_made"] = len(outcomes)
    for key in METRICS:  # no more touches: the estimate stays as it is
        curves[key] += [curves[key][-1]] * (settings.touches + 1 - len(curves[key]))
    return curves


def _allowed_by_bench_and_planner(
    bench_allowed: Callable[[TouchTarget], bool], arm: PlannedArm, target: TouchTarget
) -> bool:
    """A target the bench can start a sweep toward and the session's planner reaches."""
    return bench_allowed(target) and arm.allowed(target)


def _object_row(
    config: Config,
    calibration: GelSightLUT,
    priors: Mapping[str, ShapePrior],
    obj: EvalObject,
    settings: ExploreSettings,
    tick: Callable[[], None] = lambda: None,
) -> tuple[dict, Any]:
    """One object's JSON row and its vision latent (``tick`` after every touch)."""
    run = ObjectRun(config, calibration, priors, obj, settings)
    try:
        methods = {}
        for method in settings.methods:
            runs = settings.random_runs if METHODS[method][0] == "random" else 1
            results = [_explore(run, method, r, tick) for r in range(runs)]
            methods[method] = mean_runs(results) if METHODS[method][0] == "random" else results[0]
    finally:
        run.close()
    row = {
        "name": obj.name,
        "category": obj.category,
        "yaw_deg": run.yaw_deg,
        "prior": run.vision.prior,
        "input": run.vision.input,
        "methods": methods,
    }
    return row, run.vision.latent


def with_threads(threads: int, function: Callable[..., T], *args: Any) -> T:
    """``function(*args)`` on ``threads`` torch threads: an object's job in a worker process."""
    torch.set_num_threads(threads)
    return function(*args)


def run_explore_benchmark(
    config: Config,
    objects: Sequence[EvalObject],
    settings: ExploreSettings,
    *,
    priors: Mapping[str, ShapePrior],
    calibration: GelSightLUT,
    workers: int = 1,
    progress: bool = True,
) -> dict:
    """The benchmark's JSON: per object and method the curves after 0..N touches (``chamfer_mm``,
    ``fscore_5mm``, ``fscore_2mm``, ``iou``), per touch ``select_s``, ``refine_s``, ``contact``
    and more (docs/explore.md); a ``summary`` (:func:`summarise`) and the ``timing``
    (:func:`latency_figures`).
    ``workers`` > 1 runs objects in that many processes (each with this process's torch
    thread count); every object is seeded by its name, so the result does not change.
    ``priors`` are the loaded priors by name (``settings.prior`` one of them, or ``auto``)."""
    from tqdm import tqdm

    for prior in priors.values():
        prior.check_grid(config.voxel_grid.grid(config.cameras.rgbd.pose_world_camera()[:3, 3]))
    touches_per_object = settings.touches * sum(
        settings.random_runs if METHODS[m][0] == "random" else 1 for m in settings.methods
    )
    bar = tqdm(
        total=len(objects) * touches_per_object,
        desc="explore",
        unit="touch",
        disable=not progress,
    )
    results: list[tuple[dict, Any]] = []
    if workers <= 1:
        for obj in objects:
            bar.set_postfix_str(obj.name)
            results.append(_object_row(config, calibration, priors, obj, settings, bar.update))
    else:
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(workers, mp_context=context) as pool:
            futures = [
                pool.submit(
                    with_threads,
                    torch.get_num_threads(),
                    _object_row,
                    *(config, calibration, priors, obj, settings),
                )
                for obj in objects
            ]
            for future in as_completed(futures):
                future.result()
                bar.update(touches_per_object)
            results = [future.result() for future in futures]
    bar.close()
    rows = [row for row, _ in results]
    first_latent = results[0][1] if results else None
    first = priors[rows[0]["prior"]] if rows else next(iter(priors.values()))
    models = config.models
    timing = latency_figures(
        first,
        first_latent,
        settings.timing_resolutions,
        models.refine_learning_rate,
        models.refine_iterations_per_touch,
    )
    return {
        "prior": settings.prior,
        "preset": first.preset.name,
        "input": settings.input_mode,
        "touches": settings.touches,
        "methods_run": list(settings.methods),
        "random_runs": settings.random_runs,
        "oracle_candidates": settings.oracle_candidates,
        "seed": settings.seed,
        "select_lag": settings.select_lag,
        "refine_learning_rate": models.refine_learning_rate,
        "refine_iterations_per_touch": models.refine_iterations_per_touch,
        "refine_loss": models.refine_loss,
        "chamfer": "mm, unsquared: mean NN distance pred->gt + gt->pred, 10k samples each; "
        "null for an empty prediction",
        "objects": rows,
        "summary": summarise(rows, settings.methods, settings.touches),
        "timing": timing,
    }


def with_refinement(
    config: Config,
    learning_rate: float | None,
    iterations: int | None,
    loss: TouchLossKind | None = None,
) -> Config:
    """``config`` with the refinement's learning rate / iterations / loss replaced where given."""
    models = config.models
    return replace(
        config,
        models=replace(
            models,
            refine_learning_rate=(
                models.refine_learning_rate if learning_rate is None else learning_rate
            ),
            refine_iterations_per_touch=(
                models.refine_iterations_per_touch if iterations is None else iterations
            ),
            refine_loss=models.refine_loss if loss is None else loss,
        ),
    )
