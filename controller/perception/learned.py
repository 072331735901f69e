"""The paper's perception, assembled for the controller (implements ``Perception``).

reconstruct: the shape prior (2.5D sketches -> voxels through a 200-d latent) on the camera frame.
select: the active policy (least summed confidence |v - 0.5| over a sensor window, yaws every 90
and pitches every 10 degrees) on the estimate with the touches' measurements written in, or the
random policy; the first candidate the motion planner accepts (the efficient policy: of the first
few it accepts, the most uncertainty per robot-second). interpret: GelSight height map ->
contact points -> voxel constraints along every ray of the pad (or the emptied sweep of a miss
or a force stop without imprint). refine: the latent updated by the touch loss over all touches
so far (threshold form, anchored to the vision latent: ``[models]`` config and
docs/explore.md), the measurements then written in; or the Direct Edit baseline on the vision
estimate.
"""

from __future__ import annotations

import logging
import math
import os
import threading
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from controller.config import Config, ModelsConfig
from controller.perception.protocol import (
    RobotSeconds,
    ShapeEstimate,
    TargetFilter,
    TouchMeasurement,
    TouchOutcome,
    TouchTarget,
)
from controller.request import ExploreRequest
from drivers.base import RGBDFrame
from drivers.factory import Devices
from drivers.tool import ToolModel
from models.geometry import VoxelGrid, make_transform, transform_points
from models.prior.auto import AUTO
from models.prior.carving import SEEN_EMPTY_PROBABILITY
from models.prior.networks import LATENT_DIM
from models.prior.shape_prior import ShapePrior, available_priors
from models.tactile.lut import (
    GelSightLUT,
    build_lut_from_datapack,
    default_datapack_path,
    load_datapack,
)
from models.tactile.reconstruction import (
    TactileReconstructor,
    check_height_map,
    contact_geometry,
)
from models.touch.constraints import (
    TouchResult,
    VoxelConstraints,
    constraints_from_touches,
    free_pad_points,
    pad_grid_world,
)
from models.touch.fused import FusedShape, FusionSettings
from models.touch.global_fit import (
    GlobalSettings,
    GlobalState,
    ShapeMean,
    committee_probabilities,
    global_step,
)
from models.touch.observations import SurfaceObservations, observations_of
from models.touch.policy import (
    above_table_filter,
    all_of,
    facing_surface_filter,
    normal_approach,
    not_repeated_filter,
    predicted_bounding_box_world,
    random_touch,
    touch_candidates,
)
from models.touch.posed_prior import Pose, SignedDistanceGrid
from models.touch.refinement import Decode, RefinementResult, direct_edit, refine_latent
from models.vision import VisionSettings, estimate_from_frame

log = logging.getLogger(__name__)

MAX_APPROACH_ANGLE_DEG = 45.0
"""Approach within this angle of the predicted surface normal (the paper: along the normal).
The gel's window protrudes far enough that the gel meets a face tilted up to ~50 degrees first
(``drivers.tool``)."""
CONTACT_STRIDE_PX = 8
"""Every 8th pixel of the contact patch becomes a constraint ray (0.24 mm apart: far below a
voxel, so no information is lost)."""
FREE_RAY_SPACING_M = 0.002
TABLE_CONTACT_M = 0.002
"""Contact points this close to the table top are the table's (on the bench a random touch can
press the gel onto the table beside a flat object)."""
STOP_POINT_SPACING_M = 0.002
RANDOM_POLICY_TRIES = 50
EFFICIENT_CANDIDATES = 4
"""How many allowed windows, least confident first, the efficient policy times with the planner
(each a full touch plan, ~0.1 s)."""
FUSED_UPDATES = ("global", "fused")
"""The updates that bend the prior's surface through every measurement (docs/touch.md)."""
REPEAT_RADIUS_M = 0.005
REPEAT_ANGLE_DEG = 25.0
"""A target this close to an earlier one, approached within this angle of its direction, is not
chosen again: the earlier touch already answered what it could. The angle spans more than one
step of the policy's 10-degree directions, and the approach is aimed along the estimated normal
(docs/touch.md): at 10 degrees the README main job pressed its first patch twice, the second
approach 12 degrees from the first."""
FORCE_ONLY_REPEAT_RADIUS_M = 0.015
FORCE_ONLY_REPEAT_ANGLE_DEG = 30.0
"""A target this close to a touch stopped by force without an imprint, approached within this
angle of its direction, is not chosen: a rigid part met the object there before the gel, and
from nearly the same pose it would again (the pad is 19 x 14 mm)."""


def load_calibration(config: Config) -> GelSightLUT:
    """The sensor's calibration file, or one built from the real presses shipped with taxim
    (what the simulated GelSight's optics were fitted on)."""
    if config.sensor.calibration_file:
        return GelSightLUT.load(config.sensor.calibration_file)
    pack = load_datapack(default_datapack_path())
    return build_lut_from_datapack(pack, list(range(len(pack.images_bgr))), source="taxim dataPack")


class LearnedPerception:
    """Prior + GelSight + constraints + policy + refinement for one robot."""

    def __init__(
        self,
        config: Config,
        *,
        camera_position_world: np.ndarray,
        calibration: GelSightLUT,
        priors: dict[str, ShapePrior] | None = None,
        seed: int = 0,
    ) -> None:
        self.config = config
        self.grid = config.voxel_grid.grid(tuple(camera_position_world))
        self.calibration = calibration
        self._priors = dict(priors or {})
        self._priors_lock = threading.Lock()
        self._rng = np.random.default_rng(seed)
        self._reconstructors: dict[int, TactileReconstructor] = {}
        sensor = config.sensor
        self.pad_size_m = (sensor.pad_width_mm * 1e-3, sensor.pad_height_mm * 1e-3)
        self.tool = ToolModel(config.gripper, sensor)

    def prior(self, name: str) -> ShapePrior:
        """A named prior, loaded once."""
        with self._priors_lock:
            if name not in self._priors:
                models = self.config.models
                self._priors[name] = ShapePrior.load(
                    name,
                    preset=models.preset,
                    weights_dir=models.weights_dir or None,
                    device=models.device,
                )
                self._priors[name].check_grid(self.grid)
            return self._priors[name]

    def prior_names(self) -> frozenset[str]:
        """The priors of the configured preset in the weights folder, any given loaded, and
        ``auto`` (the best of them for each image)."""
        models = self.config.models
        listed = available_priors(models.weights_dir or None)
        names = {n for n, specs in listed.items() if models.preset in {s.preset for s in specs}}
        names |= set(self._priors)
        return frozenset(names | {AUTO}) if names else frozenset()

    def warm_up(self, prior_name: str) -> None:
        """Load the prior (for ``auto`` every prior of the preset: bad weights fail here, at
        start-up) and run one refinement step on a dummy touch: the first ``torch.optim.Adam``
        of a process imports ``torch._dynamo`` (~1.3 s here), which would otherwise land on the
        first touch."""
        names = sorted(self.prior_names() - {AUTO}) if prior_name == AUTO else [prior_name]
        loaded = [self.prior(name) for name in names]
        # No prior at all: the error that lists what the weights folder has.
        prior = loaded[0] if loaded else self.prior(prior_name)
        resolution = self.grid.resolution
        dummy = VoxelConstraints.from_voxels(resolution, [(0, 0, 0)], np.zeros((0, 3)))
        latent = torch.zeros(LATENT_DIM, device=prior.device)
        refine_latent(
            prior.decode, latent, dummy, iterations=1, loss=self.config.models.refine_loss
        )

    # --- Perception -----------------------------------------------------------------------------

    def reconstruct(self, frame: RGBDFrame, request: ExploreRequest) -> ShapeEstimate:
        names = self.prior_names() - {AUTO} if request.prior == AUTO else {request.prior}
        vision = estimate_from_frame(
            {name: self.prior(name) for name in sorted(names)},
            frame.colour_rgb,
            frame.intrinsics,
            frame.pose_world_camera,
            self.grid,
            depth_m=frame.depth_m,
            input_mode=request.input,
            settings=self.vision_settings,
        )
        prediction = vision.prediction
        if request.prior == AUTO:
            log.info(
                "prior auto: %s (silhouette agreement %s)", prediction.prior, vision.prior_scores
            )
        if vision.symmetry is not None:
            log.info("symmetry completion: %s", vision.symmetry.summary())
        # The fused updates (global, fused) start from the depth fused into the prior; the
        # paper's updates (latent, Direct Edit) from the prior's voxels.
        fused = request.update in FUSED_UPDATES and vision.fused is not None
        return ShapeEstimate(
            grid=prediction.grid,
            probabilities=vision.probabilities if fused else prediction.probabilities,
            latent=prediction.latent,
            prior=prediction.prior,
            sketches={
                "depth_m": prediction.depth_m,
                "normals": ((prediction.normals_camera + 1.0) * 127.5).astype(np.uint8),
                "silhouette": (prediction.silhouette * 255).astype(np.uint8),
            },
            vision_probabilities=prediction.probabilities,
            vision_latent=prediction.latent,
            camera_observations=vision.camera_observations,
            fused=vision.fused if fused else None,
            seen_empty=prediction.seen_empty,
            input=vision.input,
        )

    def select(
        self,
        estimate: ShapeEstimate,
        request: ExploreRequest,
        outcomes: list[TouchOutcome],
        allowed: Callable[[TouchTarget], bool],
        feasible: TargetFilter | None = None,
        robot_seconds: RobotSeconds | None = None,
    ) -> TouchTarget | None:
        # What the touches measured is known: the policy sees it written into the estimate, so
        # the windows they answered are confident and are not chosen again.
        grid = estimate.grid
        policy_probabilities = estimate.probabilities
        if self.config.models.fusion_policy == "committee" and estimate.global_state is not None:
            policy_probabilities = committee_probabilities(
                estimate.global_state,
                estimate.probabilities,
                grid,
                self.config.models.fusion_prior_std_m,
            )
        known = direct_edit(policy_probabilities, self.constraints(outcomes, grid))
        filters = [] if feasible is None else [feasible]
        feasible = all_of(
            *filters,
            above_table_filter(
                self.config.motion.approach_distance_m, self.config.limits.table_clearance_m
            ),
            facing_surface_filter(estimate.probabilities, grid, MAX_APPROACH_ANGLE_DEG),
            not_repeated_filter(
                [
                    (o.measurement.target.target_world, o.measurement.target.direction_world)
                    for o in outcomes
                ],
                REPEAT_RADIUS_M,
                REPEAT_ANGLE_DEG,
            ),
            not_repeated_filter(
                [
                    (o.measurement.target.target_world, o.measurement.target.direction_world)
                    for o in outcomes
                    if o.measurement.contact and len(o.contact_points_world) == 0
                ],
                FORCE_ONLY_REPEAT_RADIUS_M,
                FORCE_ONLY_REPEAT_ANGLE_DEG,
            ),
        )
        if request.policy in ("active", "efficient"):
            # The paper's policy takes the least confident allowed window; the efficient one
            # times the EFFICIENT_CANDIDATES least confident and takes the most uncertainty
            # per robot-second (a window's expected reduction: its uncertainty, all windows
            # being the pad's size).
            timed = robot_seconds if request.policy == "efficient" else None
            best: TouchTarget | None = None
            best_rate, count = -math.inf, 0
            for candidate in touch_candidates(known, grid, feasible):
                target = TouchTarget(
                    candidate.target_world,
                    candidate.approach_direction_world,
                    candidate.score,
                    candidate.uncertainty,
                )
                aimed = self._aimed_along_normal(estimate, target, feasible)
                for choice in (aimed, target):
                    if choice is None or not allowed(choice):
                        continue
                    if timed is None:
                        return choice
                    seconds = timed(choice)
                    if seconds is None:
                        continue
                    count += 1
                    if choice.uncertainty / seconds > best_rate:
                        best, best_rate = choice, choice.uncertainty / seconds
                    break
                if count >= EFFICIENT_CANDIDATES:
                    break
            return best
        box = predicted_bounding_box_world(estimate.probabilities, grid)
        if box is None:
            return None
        for _ in range(RANDOM_POLICY_TRIES):
            candidate = random_touch(box[0], box[1], grid, self._rng, feasible)
            if candidate is None:
                return None
            target = TouchTarget(candidate.target_world, candidate.approach_direction_world)
            if allowed(target):
                return target
        return None

    def interpret(self, measurement: TouchMeasurement) -> TouchOutcome:
        reconstruction = self._reconstructor(measurement).reconstruct(measurement.tactile.image_bgr)
        check_height_map(
            reconstruction.height_mm,
            measurement.tactile.image_bgr.shape[:2],
            contact=measurement.contact,
        )
        pose_world_pad = measurement.pose_world_pad
        direction = pose_world_pad[:3, 2]
        start = measurement.pad_start_world
        contact = None
        if measurement.contact:
            contact = contact_geometry(
                reconstruction.height_mm,
                reconstruction.contact_mask,
                reconstruction.mm_per_px,
                stride_px=CONTACT_STRIDE_PX,
            )
        if contact is not None:
            points = contact.points_world_m(pose_world_pad)
            free = free_pad_points(pose_world_pad, points, self.pad_size_m, FREE_RAY_SPACING_M)
        else:
            # A miss, or stopped by force with no imprint: a rigid part met the object first,
            # or a face larger than the pad pressed the gel evenly (photometric stereo sees
            # slopes, not uniform depth). Only the sweep up to the stop is known to be free.
            points = np.zeros((0, 3))
            free = np.zeros((0, 3))
        # A stop right at the start can leave points behind the start plane (the gel sinks in):
        # they tell nothing about the sweep.
        points = points[(points - start) @ direction >= 0]
        free = free[(free - start) @ direction >= 0]
        # Where the gel pressed the table (world z = 0), it measured the table, not the object.
        points = points[points[:, 2] > TABLE_CONTACT_M]
        if len(points):
            touch = TouchResult.from_contact(points, direction, start, free)
        else:
            touch = self._sweep(measurement)
        return TouchOutcome(
            measurement=measurement,
            contact_points_world=points,
            height_map_mm=reconstruction.height_mm,
            touch=touch,
        )

    def refine(
        self, estimate: ShapeEstimate, outcomes: list[TouchOutcome], request: ExploreRequest
    ) -> ShapeEstimate:
        if request.update in FUSED_UPDATES and estimate.vision_probabilities is not None:
            touches = [o.touch for o in outcomes if o.touch is not None]
            return self.refine_fused(estimate, touches, request)
        return self.refine_with(estimate, self.constraints(outcomes, estimate.grid), request)

    def refine_fused(
        self, estimate: ShapeEstimate, touches: list[TouchResult], request: ExploreRequest
    ) -> ShapeEstimate:
        """The fused update from all touches so far (however measured). With ``update =
        "global"`` the prior's latent (and pose, where ``GlobalSettings.pose_fit``) is first
        fitted to every touch, and that fit becomes the mean once it has predicted a touch it
        had not seen
        (``models.touch.global_fit``); then the mean's surface is bent through every
        measurement (``models.touch.fused``)."""
        base_grid = estimate.grid
        observations = SurfaceObservations.merged(
            [estimate.camera_observations, observations_of(touches)]
        )
        if estimate.fused is not None:
            # Vision's shape as at the last touch: its distance is computed already.
            vision_distance = estimate.fused.prior.moved_to(base_grid)
        else:
            vision_distance = SignedDistanceGrid.from_probabilities(
                estimate.vision_probabilities, base_grid
            )
        state = estimate.global_state
        latent, pose, prior = estimate.latent, Pose(), vision_distance
        if request.update == "global" and estimate.vision_latent is not None and touches:
            vision_latent = torch.as_tensor(estimate.vision_latent)
            if state is None:
                vision = ShapeMean(
                    vision_latent, estimate.vision_probabilities, vision_distance, Pose()
                )
                state = GlobalState.start(vision)
            state = global_step(
                state,
                self._decoder(estimate, request),
                vision_latent,
                touches,
                observations,
                self.global_settings,
                estimate.seen_empty,
            )
            if state.decisions and state.decisions[-1].touch == len(touches) - 1:
                log.info(state.decisions[-1].summary())
            latent, pose, prior = state.mean.latent, state.mean.pose, state.mean.distance
        fused = FusedShape.from_distance(prior, observations, self.fusion_settings, pose)
        return replace(
            estimate,
            probabilities=self._fused_probabilities(fused, base_grid),
            latent=latent,
            fused=fused,
            global_state=state,
        )

    def _fused_probabilities(self, fused: FusedShape, grid: VoxelGrid) -> np.ndarray:
        """What the policy, the safety bound and voxels.npz read: P(inside) with the field's
        uncertainty (``fusion_policy = "variance"`` or ``"committee"``), or with the prior's
        everywhere ("window": the paper's |v - 0.5| policy on the fused shape, touched or not)."""
        return fused.probabilities(grid, use_variance=self.config.models.fusion_policy != "window")

    @property
    def vision_settings(self) -> VisionSettings:
        return vision_settings(self.config.models)

    @property
    def fusion_settings(self) -> FusionSettings:
        models = self.config.models
        return FusionSettings(
            support_m=models.fusion_support_m, prior_std_m=models.fusion_prior_std_m
        )

    @property
    def global_settings(self) -> GlobalSettings:
        models = self.config.models
        return GlobalSettings(
            learning_rate=models.global_learning_rate,
            iterations=models.global_iterations,
            patience=models.global_patience or None,
            camera_constraints=models.global_camera_constraints,
        )

    def refine_with(
        self, estimate: ShapeEstimate, constraints: VoxelConstraints, request: ExploreRequest
    ) -> ShapeEstimate:
        """:meth:`refine` from the voxel constraints of all touches so far (however measured)."""
        if request.update == "direct" or estimate.latent is None:
            probabilities = direct_edit(estimate.vision_probabilities, constraints)
            return replace(estimate, probabilities=probabilities)
        models = self.config.models
        result = self._refine_latent(estimate, constraints, request)
        # The prior spreads the touches over the shape; what they measured is then written in,
        # so the reported shape agrees with every contact and every free sweep.
        probabilities = result.voxels.numpy().astype(np.float32)
        if models.refine_write_measurements:
            probabilities = direct_edit(probabilities, constraints)
        return replace(estimate, probabilities=probabilities, latent=result.latent)

    # --- helpers --------------------------------------------------------------------------------

    def _aimed_along_normal(
        self, estimate: ShapeEstimate, target: TouchTarget, feasible: TargetFilter
    ) -> TouchTarget | None:
        """``target`` approached along the fused shape's inward normal there
        (:func:`models.touch.policy.normal_approach`), if feasible; None without a fused shape,
        with ``aim_along_normal`` off, or where the normal gives no approach."""
        if estimate.fused is None or not self.config.models.aim_along_normal:
            return None
        direction = normal_approach(estimate.fused.sdf, target.target_world, target.direction_world)
        if direction is None or not bool(feasible(target.target_world[None], direction)[0]):
            return None
        return replace(target, direction_world=direction)

    def _decoder(self, estimate: ShapeEstimate, request: ExploreRequest) -> Decode:
        """The estimate's prior's decoder; space the camera saw empty stays empty in every
        shape the latent decodes to."""
        decode = self.prior(estimate.prior or request.prior).decode
        if estimate.seen_empty is None:
            return decode
        seen_empty = torch.as_tensor(estimate.seen_empty)

        def decode_carved(latent: torch.Tensor) -> torch.Tensor:
            probabilities = decode(latent)
            return torch.where(
                seen_empty, probabilities.clamp(max=SEEN_EMPTY_PROBABILITY), probabilities
            )

        return decode_carved

    def _refine_latent(
        self, estimate: ShapeEstimate, constraints: VoxelConstraints, request: ExploreRequest
    ) -> RefinementResult:
        """The estimate's latent refined by the touch loss (``[models]`` settings), anchored to
        the vision latent."""
        models = self.config.models
        return refine_latent(
            self._decoder(estimate, request),
            torch.as_tensor(estimate.latent),
            constraints,
            learning_rate=models.refine_learning_rate,
            iterations=models.refine_iterations_per_touch,
            loss=models.refine_loss,
            anchor_latent=(
                None if estimate.vision_latent is None else torch.as_tensor(estimate.vision_latent)
            ),
            anchor_weight=models.refine_anchor_weight,
        )

    def constraints(self, outcomes: list[TouchOutcome], grid: VoxelGrid) -> VoxelConstraints:
        """The voxel constraints of all touches so far in ``grid`` (the estimate's)."""
        return constraints_from_touches([o.touch for o in outcomes if o.touch is not None], grid)

    def _reconstructor(self, measurement: TouchMeasurement) -> TactileReconstructor:
        """One reconstructor per reference frame (its set-up cost is paid once a session)."""
        key = id(measurement.reference)
        if key not in self._reconstructors:
            self._reconstructors = {
                key: TactileReconstructor(self.calibration, measurement.reference.image_bgr)
            }
        return self._reconstructors[key]

    def _sweep(self, measurement: TouchMeasurement) -> TouchResult:
        """The pad's sweep from the approach start to where it stopped: all empty. Stopped by
        force (``stop_constraints``), the object also reaches one of the points where the
        fingers can first meet it (``ToolModel.leading_points_pad``), unless a rigid part of
        the tool reached the table, which may have stopped them, or the opening is unknown."""
        end = measurement.pose_world_pad
        start = make_transform(end[:3, :3], measurement.pad_start_world)
        spacing = FREE_RAY_SPACING_M
        sweep = (
            pad_grid_world(start, self.pad_size_m, spacing),
            pad_grid_world(end, self.pad_size_m, spacing),
        )
        width_m = measurement.gripper_width_m
        if not measurement.contact or not self.config.models.stop_constraints or width_m is None:
            return TouchResult.from_miss(*sweep)
        pose_world_tcp = end @ np.linalg.inv(self.tool.pose_tcp_pad(width_m))
        for box in self.tool.rigid_boxes(width_m):
            if box.lowest_world_z_m(pose_world_tcp) < TABLE_CONTACT_M:
                return TouchResult.from_miss(*sweep)
        points_pad, directions_pad = self.tool.leading_points_pad(width_m, STOP_POINT_SPACING_M)
        return TouchResult.from_miss(
            *sweep, transform_points(end, points_pad), directions_pad @ end[:3, :3].T
        )


def vision_settings(
    models: ModelsConfig, *, pose_fit: bool = False, symmetry: bool = True
) -> VisionSettings:
    """How a session's start is made (and ``eval prior`` scores it): the depth fused with the
    touches' kernel and prior deviation, without the prior's pose fit unless asked."""
    fusion = FusionSettings(
        support_m=models.fusion_support_m, prior_std_m=models.fusion_prior_std_m, pose_fit=pose_fit
    )
    variance = models.fusion_policy != "window"
    return VisionSettings(fusion=fusion, symmetry=symmetry, use_variance=variance)


def limit_compute_threads(threads: int = 0) -> int:
    """Set this process's torch threads and numpy's BLAS threads (threadpoolctl) to ``threads``
    (0: half the cores, at most 4: the 3D convolutions of one latent gain little beyond);
    returns the number set. Process-wide: the service's perception is the process's compute."""
    if threads < 0:
        raise ValueError(f"compute threads must be >= 0, not {threads}")
    if threads == 0:
        threads = max(1, min(4, (os.cpu_count() or 1) // 2))
    torch.set_num_threads(threads)
    threadpool_limits(limits=threads, user_api="blas")
    return threads


def make_perception(config: Config, devices: Devices | None = None) -> LearnedPerception:
    """The perception the service uses (``touchshape serve`` / ``explore``; ``replay`` has no
    devices: it needs none), with its compute threads set (``ModelsConfig.compute_threads``)."""
    limit_compute_threads(config.models.compute_threads)
    camera_position = config.cameras.rgbd.pose_world_camera()[:3, 3]
    perception = LearnedPerception(
        config,
        camera_position_world=camera_position,
        calibration=load_calibration(config),
        seed=config.sim.seed,
    )
    # Loads the prior too: bad weights fail at start-up, not mid-session.
    perception.warm_up(config.models.prior)
    return perception
