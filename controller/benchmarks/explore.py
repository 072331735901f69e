"""The exploration benchmark (issue 5, items 5 and 6): shape error versus number of touches.

Per object, on the simulated bench: the bench Kinect's frame -> the prior's vision estimate
(shared by all methods) -> for each method, ``touches`` times: select a touch -> simulated touch
(GelSight image -> height map -> voxel constraints, ``LearnedPerception.interpret``) -> refine;
the estimate is scored after 0, 1, ..., N touches against the true mesh.

Methods (policy + update):

* ``active-prior``: the paper's active policy + latent refinement through the prior;
* ``random-prior``: the random policy (target uniform in the predicted bounding box) + latent
  refinement; the mean curve over ``random_runs`` seeded runs (each run's curve is kept);
* ``active-direct``: the active policy + Direct Edit of the vision estimate (no prior);
* ``oracle-prior``: among the ``oracle_candidates`` best feasible active windows and as many
  feasible random touches, the touch whose simulated touch + refinement leaves the lowest
  Chamfer distance (:func:`models.touch.policy.oracle_select` with the ground truth: the paper's human
  upper bound).

Simulated touch (no arm motion): the flange is placed so the pad faces the target from
``START_STANDOFF_M`` on the approach line with the fingers nearly closed, then the fingers open
to the full stroke with the contact force limit, so the pad sweeps along the line through the
target: stopped by force (contact) or a miss after the whole stroke (54 mm of pad travel). Where
a tool part would be in the object there, or the gel already pressed, the start backs off in
``START_BACKOFF_STEP_M`` steps up to ``MAX_START_STANDOFF_M``; a target without such a start is
refused through the policy's ``allowed`` check, as the robot's motion planner refuses
unreachable ones (the bench checks against the true object, the only one it has).

Metrics (:mod:`models.metrics`): Chamfer distance in mm (mean nearest distance pred->gt plus
gt->pred over 10,000 surface samples each, unsquared; null for an empty prediction), F-score at
2 and 5 mm, and voxel IoU at 0.5 against the voxelised true mesh in the registered grid.
Timings: ``select_s`` is the policy's wall time without the bench's start checks (the oracle's
is its whole choice, simulated candidate touches included), ``refine_s`` one refinement.
Item 6: select and refine latency at 64^3 and 128^3 by :func:`controller.benchmarks.touch_latency.touch_latency`.

Deterministic for a seed: object yaws, camera and GelSight noise and random policies are drawn
from generators seeded by (seed, object name, method, run, touch); torch runs on one thread
(the CLI sets it).
"""

from __future__ import annotations

import asyncio
import logging
import math
import multiprocessing
import time
import zlib
from collections.abc import Callable, Coroutine, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np
import torch
import trimesh
from numpy.typing import NDArray

from controller.config import Config
from controller.motion.planner import pad_pose_facing, tcp_pose_for_pad
from controller.perception.learned import REPEAT_RADIUS_M, LearnedPerception
from controller.perception.protocol import (
    ShapeEstimate,
    TouchMeasurement,
    TouchOutcome,
    TouchTarget,
)
from controller.request import ExploreRequest
from drivers.base import RGBDFrame, TactileFrame
from drivers.sim.camera import SimKinect
from drivers.sim.gelsight import SimGelSight, gel_pad_spec
from drivers.sim.gripper import SimWSG50
from drivers.sim.world import SimWorld
from models.geometry import invert_transform, make_transform, rotation_about_axis
from models.metrics import mesh_metrics, voxel_iou
from models.prior.dataset import voxelize
from models.prior.evaluation import EvalObject
from models.prior.shape_prior import ShapePrior
from models.shapes import fits_extent, load_mesh_file
from models.tactile.lut import GelSightCalibration
from models.tactile.sim import GelSightSimulator
from models.touch.constraints import VoxelConstraints
from models.touch.policy import oracle_select
from models.touch.refinement import TouchLossKind, touch_loss

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
T = TypeVar("T")

METHODS: dict[str, tuple[Literal["active", "random", "oracle"], Literal["prior", "direct"]]] = {
    "active-prior": ("active", "prior"),
    "random-prior": ("random", "prior"),
    "active-direct": ("active", "direct"),
    "oracle-prior": ("oracle", "prior"),
}
METRICS = ("chamfer_mm", "fscore_5mm", "fscore_2mm", "iou")

TOUCH_START_WIDTH_M = 0.002
"""Finger opening at the start of a sweep: nearly closed, so the pad can travel 54 mm."""
START_STANDOFF_M = 0.025
"""Pad distance before the target where the sweep starts (then 29 mm of travel past it)."""
START_BACKOFF_STEP_M = 0.005
START_FREE_TRAVEL_M = 0.003
"""The pad must travel this far from the start before anything can stop it: the free rays of
a contact are pulled back 2 mm (``free_pad_points``) and must stay in front of the start."""
MAX_START_STANDOFF_M = 0.045
"""The farthest start: the pad still sweeps 9 mm past the target."""
FREE_AIR_POSE_WORLD_TCP = make_transform(None, (0.0, 0.0, 0.5))
"""Where the gripper is homed: fingers pointing up, 50 cm above the object point."""
MAX_OBJECT_HEIGHT_M, MAX_OBJECT_WIDTH_M = 0.25, 0.20
"""Mesh files larger than this are scaled down to fit the 26 cm voxel grid."""


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


# --- the simulated bench --------------------------------------------------------------------------


class SimTouchBench:
    """The simulated bench with one object: its camera frame, and touches made by placing the
    tool directly and opening the fingers (module docstring). The simulated devices are driven
    through a private event loop, so the benchmark stays synchronous; call :meth:`close`."""

    def __init__(self, config: Config, object_mesh_world: trimesh.Trimesh, seed: int) -> None:
        self.config = config
        self.world = SimWorld(
            object_mesh_world,
            sim=config.sim,
            arm=config.robot.arm,
            gripper=config.gripper,
            sensor=config.sensor,
        )
        self._gel = GelSightSimulator(gel_pad_spec(config.sensor))
        self.gripper = SimWSG50(self.world, config.gripper, self._gel)
        self.gelsight = SimGelSight(self.world, self._gel, np.random.default_rng((seed, 1)))
        self.camera = SimKinect(self.world, config.cameras.rgbd, np.random.default_rng((seed, 2)))
        self._loop = asyncio.new_event_loop()
        self.reference = self._run(self._connect())

    def _run(self, coroutine: Coroutine[Any, Any, T]) -> T:
        return self._loop.run_until_complete(coroutine)

    async def _connect(self) -> TactileFrame:
        for device in (self.camera, self.gelsight, self.gripper):
            await device.connect()
        self._place_tool(FREE_AIR_POSE_WORLD_TCP, TOUCH_START_WIDTH_M)
        await self.gripper.home()
        return await self.gelsight.reference()

    def close(self) -> None:
        self._loop.close()

    def frame(self) -> RGBDFrame:
        """One bench Kinect frame (colour, noisy depth)."""
        return self._run(self.camera.read())

    def _place_tool(self, pose_world_tcp: FloatArray, width_m: float) -> None:
        world = self.world
        world.pose_base_flange = invert_transform(world.pose_world_base) @ pose_world_tcp
        world.gripper_width_m = width_m

    def approach_start(self, target: TouchTarget) -> FloatArray | None:
        """Pad pose (world, 4x4) where the sweep toward ``target`` starts, or None when no
        start within ``MAX_START_STANDOFF_M`` is clear."""
        standoff = START_STANDOFF_M
        while standoff <= MAX_START_STANDOFF_M + 1e-9:
            pose_world_pad = pad_pose_facing(
                target.target_world, -np.asarray(target.direction_world), standoff
            )
            if self._clear(pose_world_pad):
                return pose_world_pad
            standoff += START_BACKOFF_STEP_M
        return None

    def allowed(self, target: TouchTarget) -> bool:
        """The policy's feasibility callback: the bench can start a sweep toward ``target``."""
        return self.approach_start(target) is not None

    def _clear(self, pose_world_pad: FloatArray) -> bool:
        """No rigid tool part in the object or the table and the gel untouched, with the pad
        here and ``START_FREE_TRAVEL_M`` further on, and its centre outside a closed object."""
        world = self.world
        pose_world_tcp = tcp_pose_for_pad(pose_world_pad, world.tool, TOUCH_START_WIDTH_M)
        for width in (TOUCH_START_WIDTH_M, TOUCH_START_WIDTH_M + 2 * START_FREE_TRAVEL_M):
            if world.tool_collision(pose_world_tcp, width) is not None:
                return False
        mesh = world.object_mesh_world
        if mesh.is_watertight and mesh.contains(pose_world_pad[None, :3, 3])[0]:
            return False
        advanced = pose_world_pad.copy()
        advanced[:3, 3] += START_FREE_TRAVEL_M * pose_world_pad[:3, 2]
        indentation = self._gel.indentation_mm(world.scene_mesh_world, advanced)
        return not np.any(indentation > 0)

    def touch(self, target: TouchTarget, noise_seed: Sequence[int]) -> TouchMeasurement | None:
        """Sweep the pad through ``target`` along its direction; None if no start is clear.
        ``noise_seed`` seeds this touch's GelSight image noise."""
        start = self.approach_start(target)
        if start is None:
            return None
        self.gelsight.rng = np.random.default_rng(list(noise_seed))
        return self._run(self._sweep(target, start))

    async def _sweep(
        self, target: TouchTarget, pose_world_pad_start: FloatArray
    ) -> TouchMeasurement:
        config = self.config
        width = TOUCH_START_WIDTH_M
        self._place_tool(tcp_pose_for_pad(pose_world_pad_start, self.world.tool, width), width)
        speed = config.motion.finger_speed_m_s
        state = await self.gripper.move(
            config.gripper.stroke_m,
            speed_m_s=speed,
            force_limit_n=config.limits.contact_force_n,
            timeout_s=2.0 * config.gripper.stroke_m / speed + 1.0,
        )
        tactile = await self.gelsight.read()
        return TouchMeasurement(
            target=target,
            contact=state.blocked,
            tactile=tactile,
            reference=self.reference,
            pose_world_pad=self.world.pose_world_pad(),
            pad_start_world=pose_world_pad_start[:3, 3].copy(),
            force_n=state.force_n,
        )


# --- the benchmark --------------------------------------------------------------------------------


@dataclass(frozen=True)
class ExploreSettings:
    """What the benchmark runs (the CLI's options)."""

    touches: int = 10
    methods: tuple[str, ...] = tuple(METHODS)
    random_runs: int = 10
    oracle_candidates: int = 4
    input_mode: Literal["rgb", "rgbd"] = "rgb"
    prior: str = "general"
    seed: int = 0
    timing_resolutions: tuple[int, ...] = (64, 128)
    """Item 6: select / refine latency at these resolutions (empty: none)."""

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
        calibration: GelSightCalibration,
        prior: ShapePrior,
        obj: EvalObject,
        settings: ExploreSettings,
    ) -> None:
        self.config, self.calibration, self.prior = config, calibration, prior
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
        self.grid = perception.grid
        self.truth = voxelize(self.mesh_world, self.grid).astype(np.float32)
        self.metric_seed = _seed(settings.seed, self.key, 7)
        frame = self.bench.frame()
        self.vision = perception.reconstruct(frame, self.request("active", "prior"))
        self.vision_metrics = self.metrics(self.vision)

    def perception(self, seed: int) -> LearnedPerception:
        return LearnedPerception(
            self.config,
            camera_position_world=self.config.cameras.rgbd.pose_world_camera()[:3, 3],
            calibration=self.calibration,
            priors={self.settings.prior: self.prior},
            seed=seed,
        )

    def request(self, policy: str, update: str) -> ExploreRequest:
        return ExploreRequest(
            max_touches=self.settings.touches,
            policy="random" if policy == "random" else "active",
            update="direct" if update == "direct" else "prior",
            input=self.settings.input_mode,
            prior=self.settings.prior,
        )

    def metrics(self, estimate: ShapeEstimate) -> dict[str, float | None]:
        surface = mesh_metrics(
            estimate.probabilities, self.grid, self.mesh_world, seed=self.metric_seed
        )
        return {
            "chamfer_mm": _finite(surface.chamfer_mm),
            "fscore_5mm": surface.fscore_5mm,
            "fscore_2mm": surface.fscore_2mm,
            "iou": voxel_iou(estimate.probabilities[None], self.truth[None]),
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
        outcome = perception.interpret(measurement)
        start = time.perf_counter()
        refined = perception.refine(estimate, [*outcomes, outcome], request)
        refine_s = time.perf_counter() - start
        constraints = VoxelConstraints.none(self.grid.resolution)
        for touched in (*outcomes, outcome):
            constraints = constraints.merged(touched.constraints)
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
        return TouchTrial(outcome, refined, self.metrics(refined), refine_s, loss, flipped)

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


class _TimedCheck:
    """A feasibility callback that adds up the time spent in it (seconds)."""

    def __init__(self, check: Callable[[TouchTarget], bool]) -> None:
        self.check = check
        self.seconds = 0.0

    def __call__(self, target: TouchTarget) -> bool:
        start = time.perf_counter()
        try:
            return self.check(target)
        finally:
            self.seconds += time.perf_counter() - start


def _explore(run: ObjectRun, method: str, run_index: int, tick: Callable[[], None]) -> dict:
    """One method's curves on one object (one seeded run)."""
    settings = run.settings
    policy, update = METHODS[method]
    method_index = list(METHODS).index(method)
    perception = run.perception(_seed(settings.seed, run.key, method_index, run_index))
    request = run.request(policy, update)
    estimate = run.vision
    outcomes: list[TouchOutcome] = []
    curves: dict[str, list] = {key: [value] for key, value in run.vision_metrics.items()}
    curves.update(
        select_s=[], refine_s=[], contact=[], imprint=[], touch_loss=[], flipped=[], target=[]
    )
    for touch in range(settings.touches):
        noise = (settings.seed, run.key, method_index, run_index, touch)
        trial = partial(
            run.trial, perception, estimate, outcomes, request=request, noise_seed=noise
        )
        start = time.perf_counter()
        if policy == "oracle":
            chosen = choose_oracle_trial(
                run.oracle_candidates(perception, estimate, outcomes), trial
            )
            select_s = time.perf_counter() - start
        else:
            allowed = _TimedCheck(run.bench.allowed)
            target = perception.select(estimate, request, outcomes, allowed)
            select_s = time.perf_counter() - start - allowed.seconds
            chosen = None if target is None else trial(target)
        tick()
        if chosen is None:
            log.info("%s: no feasible touch after %d", method, touch)
            break
        estimate = chosen.estimate
        outcomes.append(chosen.outcome)
        for key, value in chosen.metrics.items():
            curves[key].append(value)
        curves["select_s"].append(select_s)
        curves["refine_s"].append(chosen.refine_s)
        curves["contact"].append(bool(chosen.outcome.measurement.contact))
        curves["imprint"].append(len(chosen.outcome.contact_points_world) > 0)
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


def _mean_curve(curves: Sequence[Sequence[float | None]]) -> list[float | None]:
    """Pointwise mean over the finite values (None where there are none)."""
    out: list[float | None] = []
    for values in zip(*curves, strict=True):
        finite = [v for v in values if v is not None and math.isfinite(v)]
        out.append(float(np.mean(finite)) if finite else None)
    return out


def _mean_runs(runs: list[dict]) -> dict:
    """The mean curves of several seeded runs, with the runs themselves."""
    mean: dict[str, Any] = {key: _mean_curve([r[key] for r in runs]) for key in METRICS}
    made = min(r["touches_made"] for r in runs)  # timings: over the touches every run made
    for key in ("select_s", "refine_s"):
        mean[key] = _mean_curve([r[key][:made] for r in runs])
    mean["touches_made"] = float(np.mean([r["touches_made"] for r in runs]))
    mean["runs"] = runs
    return mean


def _change_pct(curve: Sequence[float | None]) -> float | None:
    first, last = curve[0], curve[-1]
    if first is None or last is None or first <= 0:
        return None
    return 100.0 * (last - first) / first


def _touch_statistics(results: Sequence[dict]) -> dict[str, Any]:
    """How the touches of some results ended: a GelSight imprint (contact points), a force stop
    without one (the housing or another rigid part met the object first, or a flat face filled
    the pad: only the sweep is known free), or a miss; how much the refinements did: the
    median ratio of the touch loss after / before refining and the mean voxels flipped; and how
    many touches repeated an earlier one."""
    runs = [run for r in results for run in r.get("runs", [r])]
    contact = [c for run in runs for c in run["contact"]]
    imprint = [i for run in runs for i in run["imprint"]]
    ratios = [after / before for run in runs for before, after in run["touch_loss"] if before > 0]
    flipped = [f for run in runs for f in run["flipped"]]
    repeated = sum(_repeats(run["target"]) for run in runs)
    return {
        "imprint": int(sum(imprint)),
        "force_only": int(sum(c and not i for c, i in zip(contact, imprint, strict=True))),
        "miss": int(sum(not c for c in contact)),
        "touch_loss_after_over_before_median": float(np.median(ratios)) if ratios else None,
        "flipped_voxels_mean": float(np.mean(flipped)) if flipped else None,
        "repeated_targets": repeated,
    }


def _repeats(targets: Sequence[Sequence[float]]) -> int:
    """Touches aimed within ``REPEAT_RADIUS_M`` of an earlier touch's target, same direction."""
    count = 0
    for n, touch in enumerate(targets):
        point, direction = np.asarray(touch[:3]), np.asarray(touch[3:])
        count += any(
            np.linalg.norm(point - np.asarray(earlier[:3])) < REPEAT_RADIUS_M
            and float(direction @ np.asarray(earlier[3:])) > 0.99
            for earlier in targets[:n]
        )
    return count


def summarise(objects: Sequence[dict], methods: Sequence[str], touches: int) -> dict:
    """Mean curves per method over objects, the mean % change of Chamfer after ``touches``
    touches versus none, median timings, and the issue's bar where its methods ran."""
    summary: dict[str, Any] = {"objects": len(objects), "touches": touches, "methods": {}}
    for method in methods:
        results = [obj["methods"][method] for obj in objects]
        entry: dict[str, Any] = {key: _mean_curve([r[key] for r in results]) for key in METRICS}
        changes = [c for c in (_change_pct(r["chamfer_mm"]) for r in results) if c is not None]
        entry["chamfer_change_pct"] = float(np.mean(changes)) if changes else None
        entry["empty_predictions_at_end"] = sum(r["chamfer_mm"][-1] is None for r in results)
        for key in ("select_s", "refine_s"):
            values = [v for r in results for v in r[key] if v is not None]
            entry[f"{key}_median"] = float(np.median(values)) if values else None
        entry["touches"] = _touch_statistics(results)
        summary["methods"][method] = entry
    curves = {m: summary["methods"][m]["chamfer_mm"] for m in methods}
    bar: dict[str, Any] = {}
    if "active-prior" in curves:
        change = summary["methods"]["active-prior"]["chamfer_change_pct"]
        bar["active_prior_chamfer_change_pct"] = change
        bar["active_prior_lowers_chamfer_30pct"] = change is not None and change <= -30.0
        active = curves["active-prior"]

        def below(other: list[float | None], counts: Sequence[int]) -> bool:
            return all(
                active[n] is not None and other[n] is not None and active[n] < other[n]
                for n in counts
            )

        if "random-prior" in curves:
            bar["active_beats_random_from_3"] = below(
                curves["random-prior"], range(min(3, touches), touches + 1)
            )
        if "active-direct" in curves:
            bar["active_beats_direct_at_end"] = below(curves["active-direct"], [touches])
    summary["bar"] = bar
    return summary


def latency_figures(
    prior: ShapePrior,
    latent: Any,
    resolutions: Sequence[int],
    learning_rate: float,
    iterations: int,
) -> list[dict]:
    """Item 6: select and refine latency per resolution (:func:`touch_latency`). The prior's
    own resolution uses its decoder and an object's vision latent; another resolution uses an
    untrained decoder of the preset with that resolution (the refinement's cost does not depend
    on the weights; the selection's does, and v ~ 0.5 everywhere is its worst case)."""
    from controller.benchmarks.touch_latency import touch_latency
    from models.prior.networks import PRESETS

    figures = []
    for resolution in resolutions:
        if resolution == prior.preset.voxel_resolution:
            decoder, decode, code = f"{prior.name} ({prior.preset.name})", prior.decode, latent
        else:
            presets = [p for p in PRESETS.values() if p.voxel_resolution == resolution]
            if not presets:
                raise ValueError(f"no network preset predicts {resolution}^3 voxels")
            other = ShapePrior.untrained(presets[0].name)
            decoder, decode, code = f"untrained {presets[0].name}", other.decode, None
        entry = touch_latency(
            resolution, decode, code, iterations=iterations, learning_rate=learning_rate
        )
        entry["decoder"] = decoder
        figures.append(entry)
    return figures


def _object_row(
    config: Config,
    calibration: GelSightCalibration,
    prior: ShapePrior,
    obj: EvalObject,
    settings: ExploreSettings,
    tick: Callable[[], None] = lambda: None,
) -> tuple[dict, Any]:
    """One object's JSON row and its vision latent (``tick`` after every touch)."""
    run = ObjectRun(config, calibration, prior, obj, settings)
    try:
        methods = {}
        for method in settings.methods:
            runs = settings.random_runs if method == "random-prior" else 1
            results = [_explore(run, method, r, tick) for r in range(runs)]
            methods[method] = _mean_runs(results) if method == "random-prior" else results[0]
    finally:
        run.close()
    row = {"name": obj.name, "category": obj.category, "yaw_deg": run.yaw_deg, "methods": methods}
    return row, run.vision.latent


def _object_row_in_worker(threads: int, *args: Any) -> tuple[dict, Any]:
    torch.set_num_threads(threads)
    return _object_row(*args)


def run_explore_benchmark(
    config: Config,
    objects: Sequence[EvalObject],
    settings: ExploreSettings,
    *,
    prior: ShapePrior,
    calibration: GelSightCalibration,
    workers: int = 1,
    progress: bool = True,
) -> dict:
    """The benchmark's JSON: per object and method the curves after 0..N touches (``chamfer_mm``,
    ``fscore_5mm``, ``fscore_2mm``, ``iou``), per touch ``select_s``, ``refine_s``, ``contact``
    and more (docs/explore.md); a ``summary`` (:func:`summarise`) and the item-6 ``timing``.
    ``workers`` > 1 runs objects in that many processes (each with this process's torch
    thread count); every object is seeded by its name, so the result does not change."""
    from tqdm import tqdm

    prior.check_grid(config.voxel_grid.grid(config.cameras.rgbd.pose_world_camera()[:3, 3]))
    touches_per_object = settings.touches * sum(
        settings.random_runs if m == "random-prior" else 1 for m in settings.methods
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
            results.append(_object_row(config, calibration, prior, obj, settings, bar.update))
    else:
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(workers, mp_context=context) as pool:
            futures = [
                pool.submit(
                    _object_row_in_worker,
                    torch.get_num_threads(),
                    *(config, calibration, prior, obj, settings),
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
    models = config.models
    timing = latency_figures(
        prior,
        first_latent,
        settings.timing_resolutions,
        models.refine_learning_rate,
        models.refine_iterations_per_touch,
    )
    return {
        "prior": prior.name,
        "preset": prior.preset.name,
        "input": settings.input_mode,
        "touches": settings.touches,
        "methods_run": list(settings.methods),
        "random_runs": settings.random_runs,
        "oracle_candidates": settings.oracle_candidates,
        "seed": settings.seed,
        "refine_learning_rate": models.refine_learning_rate,
        "refine_iterations_per_touch": models.refine_iterations_per_touch,
        "refine_loss": models.refine_loss,
        "chamfer": "mm, unsquared: mean NN distance pred->gt + gt->pred, 10k samples each; "
        "null for an empty prediction",
        "objects": rows,
        "summary": summarise(rows, settings.methods, settings.touches),
        "timing": timing,
    }


def plot_curves(result: dict, path: Path) -> None:
    """The paper's figure: mean Chamfer distance versus number of touches, one curve per
    method (PNG, matplotlib Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(6.0, 4.0), dpi=120)
    for method, entry in result["summary"]["methods"].items():
        curve = [np.nan if v is None else v for v in entry["chamfer_mm"]]
        axes.plot(range(len(curve)), curve, marker="o", markersize=3, label=method)
    axes.set_xlabel("number of touches")
    axes.set_ylabel("mean Chamfer distance (mm)")
    axes.set_title(
        f"{result['summary']['objects']} objects, prior {result['prior']} ({result['input']})"
    )
    axes.grid(alpha=0.3)
    axes.legend()
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    plt.close(figure)


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
