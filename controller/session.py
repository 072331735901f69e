"""One exploration session: the finite-state controller of the paper's loop.

idle -> capture -> reconstruct -> select -> approach -> touch -> refine -> select ... -> done,
plus fault and aborted from any working state (see ``TRANSITIONS``). Each state is an async
step with a timeout. Perception runs in worker threads so the event loop (Zenoh replies, force
monitoring) never waits on it. Every transition is published and recorded.

The refinement overlaps the arm's motion to the next target (``motion.refine_while_moving``);
its estimate is taken at the approach start, which is checked again (docs/controller.md).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
from collections.abc import Awaitable, Callable
from functools import partial
from typing import Any

import numpy as np

from controller.config import Config
from controller.motion.executor import HomeError, MotionExecutor, UnexpectedForceError
from controller.motion.planner import MotionPlanner, TouchGeometry
from controller.motion.poses import home_pose_world_tcp, rolls_preferring
from controller.motion.safety import POSSIBLE_OCCUPANCY, Obstacles, SafetyViolation
from controller.perception.protocol import (
    Perception,
    ShapeEstimate,
    TouchMeasurement,
    TouchOutcome,
    TouchTarget,
    contact_counts,
)
from controller.recording import SessionRecorder, record_in_thread
from controller.request import ExploreRequest
from controller.scoring import GroundTruthScores
from controller.session_files import (
    GELSIGHT_REFERENCE_FILE,
    outcome_record,
    save_camera_frame,
    save_tactile_frame,
    touch_inputs_record,
    touch_rays,
)
from controller.session_times import SessionTimes
from controller.states import (
    STEP_TIMEOUT_S,
    TRANSITIONS,
    SessionFault,
    State,
    check_force_or_fault,
)
from controller.targets import (
    onto_measured,
    pad_path_m,
    pad_paths_meet,
    repeat_reason,
    rolls_avoiding_rim_stops,
    skip_record,
    window_leading_roll,
)
from drivers.base import DeviceError, TactileFrame
from drivers.factory import Devices
from drivers.tool import ToolModel
from models.geometry import ur_pose_to_matrix
from models.object_bound import ObjectBound
from models.tactile.reconstruction import HeightMapError
from models.touch.constraints import touch_constraints

log = logging.getLogger(__name__)


MAX_SKIPPED_RECORDS = 200
MAX_REFUSED_IN_A_ROW = 20
"""Targets the planner refused at the approach one after another before the session stops:
the checks at select passed them, so the policy could propose such targets without end."""


Publish = Callable[[str, dict[str, Any]], None]


class ExplorationSession:
    """Runs one session on connected devices; ``run`` returns the summary."""

    def __init__(
        self,
        *,
        session_id: str,
        request: ExploreRequest,
        config: Config,
        devices: Devices,
        perception: Perception,
        recorder: SessionRecorder,
        publish: Publish,
        publish_shape: Callable[[ShapeEstimate], None] = lambda estimate: None,
        home_clear_of: Obstacles | None = None,
    ) -> None:
        """``home_clear_of``: given, the session first takes the arm home clear of these (after
        a fault or an abort the arm is wherever the interruption left it)."""
        self.session_id = session_id
        self.request = request
        self.config = config
        self.devices = devices
        self.perception = perception
        self.recorder = recorder
        self.publish = publish
        self.publish_shape = publish_shape
        self.pose_world_base = ur_pose_to_matrix(config.robot.arm.pose_world_base)
        self.tool = ToolModel(config.gripper, config.sensor)
        self.planner = MotionPlanner.for_config(config, self.tool, self.pose_world_base)
        self.home_world_tcp = home_pose_world_tcp(config.robot.arm)
        self.home_clear_of = home_clear_of
        self.state = State.IDLE
        self.touch_count = 0
        self.estimate: ShapeEstimate | None = None
        self.vision_estimate: ShapeEstimate | None = None
        """The estimate from the camera alone, before any touch."""
        self.outcomes: list[TouchOutcome] = []
        self.outcome_touches: list[int] = []
        """The touch number of each outcome (a refused touch has none)."""
        world = devices.world
        self.times = SessionTimes(sim_clock=None if world is None else (lambda: world.clock.now_s))
        self.error: str | None = None
        self.metrics: dict[str, list[float]] = {}
        """Ground-truth scores after reconstruct and each refine (simulation only)."""
        self._scores = (
            None
            if world is None
            else GroundTruthScores.published(world, recorder, publish, session_id)
        )
        self.motion = MotionExecutor(
            devices=devices,
            config=config,
            planner=self.planner,
            times=self.times,
            recorder=recorder,
        )
        self._device, self._compute = self.motion.device, self.motion.compute
        self.pose_world_tcp = self.motion.pose_world_tcp
        self._frame = None
        self._reference: TactileFrame | None = None
        self._target: TouchTarget | None = None
        self._touch: TouchGeometry | None = None
        self._rejected: list[np.ndarray] = []
        self._came_from: list[np.ndarray] = []
        """Poses the arm passed through to the current approach start (oldest first)."""
        self.measured: ObjectBound | None = None
        """Where the object may be, from the measurements (``models.object_bound``)."""
        self.bound: ObjectBound | None = None
        """``measured`` and the shape estimate: what motions keep clear of."""
        self.stop_reason: str | None = None
        self._refused_in_a_row = 0
        self._refining: asyncio.Future[ShapeEstimate] | None = None
        """The refinement running while the arm moves (``_take_refined`` takes it)."""
        self.skipped: list[dict[str, Any]] = []
        """Targets not touched because no safe motion reaches them, with the reason."""
        self.unexpected_forces: list[dict[str, Any]] = []
        """Approaches stopped by a force the gel did not explain (``UnexpectedForceError``)."""

    # --- the loop -------------------------------------------------------------------------------

    async def run(self, abort: asyncio.Event) -> dict[str, Any]:
        """Run to done, fault or aborted; the robot is stopped and clear of the object after."""
        steps: dict[State, Callable[[], Awaitable[State]]] = {
            State.CAPTURE: self._capture,
            State.RECONSTRUCT: self._reconstruct,
            State.SELECT: self._select,
            State.APPROACH: self._approach,
            State.TOUCH: self._touch_step,
            State.REFINE: self._refine,
        }
        self.times.start()
        self._transition(State.CAPTURE)
        while self.state in steps:
            step = asyncio.create_task(steps[self.state](), name=f"{self.session_id}:{self.state}")
            aborted = asyncio.create_task(abort.wait())
            try:
                done, _ = await asyncio.wait(
                    {step, aborted},
                    timeout=STEP_TIMEOUT_S[self.state],
                    return_when=asyncio.FIRST_COMPLETED,
                )
            finally:
                aborted.cancel()
            if step not in done:
                step.cancel()
                await asyncio.gather(step, return_exceptions=True)
                if aborted in done:
                    await self._make_safe()
                    self._transition(State.ABORTED, "abort requested")
                else:
                    await self._fault(
                        f"{self.state} timed out after {STEP_TIMEOUT_S[self.state]} s"
                    )
                break
            try:
                next_state = step.result()
            except (DeviceError, SessionFault, TimeoutError) as error:
                await self._fault(f"{type(error).__name__}: {error}")
                break
            except Exception as error:  # a bug: still make the robot safe and keep the data
                log.exception("session step %s failed", self.state)
                await self._fault(f"internal error in {self.state}: {error!r}")
                break
            self._transition(next_state)
        if self.state == State.DONE:
            await self._take_refined()
            self.times.mark(touch=False)
            # The arm rests at the last approach start, clear of the object: going up above it
            # is a courtesy, and a refused retreat there is no error.
            await self._make_safe(report_failure=False)
        else:  # the robot is safe: the last touch's refinement is still the session's result
            await self._take_refined(after_stop=True)
        if self._scores is not None:
            self.metrics = await self._scores.collect()
        return self.summary()

    def _transition(self, state: State, detail: str = "") -> None:
        if state not in TRANSITIONS[self.state]:
            raise RuntimeError(f"illegal transition {self.state} -> {state}")
        previous, self.state = self.state, state
        log.info("session %s: %s -> %s %s", self.session_id, previous, state, detail)
        self.recorder.log_state(state, previous, detail)
        self.publish(
            "state",
            {
                "session": self.session_id,
                "state": str(state),
                "previous": str(previous),
                "touch": self.touch_count,
                "time": time.time(),
                **({"detail": detail} if detail else {}),
            },
        )

    # --- steps ----------------------------------------------------------------------------------

    async def _capture(self) -> State:
        devices, device = self.devices, self._device
        if self.home_clear_of is not None:
            try:
                await self.motion.go_home(self.home_world_tcp, self.home_clear_of)
            except HomeError as error:
                raise SessionFault(str(error)) from None
        gripper_state = await device(devices.gripper.state())
        if abs(gripper_state.width_m - self.config.motion.touch_width_m) > 1e-4:
            await self.motion.open_fingers_to_touch_width()
        self._reference = await device(devices.tactile.reference())
        self._frame = await device(devices.camera.read())
        folder = self.recorder.artifacts_dir
        await record_in_thread(
            partial(self.recorder.log_camera, self._frame),
            partial(save_camera_frame, folder, self._frame),
            partial(save_tactile_frame, folder, GELSIGHT_REFERENCE_FILE, self._reference),
        )
        if np.any(self._frame.depth_m > 0):
            self.measured = await self._compute(
                ObjectBound.from_depth,
                self._frame.depth_m,
                self._frame.intrinsics,
                self._frame.pose_world_camera,
                self.config.voxel_grid.object_point_world,
            )
        arm = await device(devices.arm.state())
        pose_world_tcp = self.pose_world_tcp(arm)
        self.recorder.log_robot(
            pose_world_tcp, pose_world_tcp @ self.tool.pose_tcp_pad(gripper_state.width_m)
        )
        return State.RECONSTRUCT

    async def _reconstruct(self) -> State:
        self.estimate = await self._compute(self.perception.reconstruct, self._frame, self.request)
        self.vision_estimate = self.estimate
        if self.measured is None:  # no depth: the object-fitted cube is where it may be
            object_point = self.config.voxel_grid.object_point_world
            self.measured = ObjectBound.from_box(self.estimate.grid, object_point)
        await self._add_estimate_to_bound()
        await self._record_shape()
        self.times.mark(touch=False)
        return State.SELECT

    async def _select(self) -> State:
        assert self.estimate is not None
        if self.touch_count >= self.request.max_touches:
            return self._stop("the touch budget is spent")
        if self._refused_in_a_row >= MAX_REFUSED_IN_A_ROW:
            return self._stop(f"no safe, reachable target is left ({MAX_REFUSED_IN_A_ROW} refused)")
        if self._refining is not None and self._refining.done():
            await self._take_refined()
        obstacles = self.obstacles()
        arm = await self._device(self.devices.arm.state())
        pose, joints = self.pose_world_tcp(arm), arm.joints_rad
        seconds_to = partial(
            self.planner.seconds_to_touch, pose, joints, obstacles, self._came_from
        )

        def robot_seconds(target: TouchTarget) -> float | None:  # the efficient policy's cost
            target = self._onto_measured(target) or target
            return seconds_to(target.target_world, target.direction_world)

        def allowed(target: TouchTarget) -> bool:
            moved = self._onto_measured(target)
            if moved is None:
                reason: str | None = "the pad's path misses where the object may be"
            else:
                target = moved
                reason = repeat_reason(target, self._rejected, self.outcomes)
            if reason is None:
                try:
                    self.planner.check_touch(
                        target.target_world, target.direction_world, joints, obstacles
                    )
                except SafetyViolation as violation:
                    reason = str(violation)
            if reason is not None:
                self._skip(target, reason, "select")
            return reason is None

        self._target = await self._compute(
            self.perception.select,
            self.estimate,
            self.request,
            self.outcomes,
            allowed,
            self._meets_measured,
            robot_seconds,
        )
        if self._target is None:
            return self._stop("no safe, reachable target is left")
        # A perception that ignored ``allowed`` may propose a sure miss: the planner still
        # checks it on the approach.
        target = self._onto_measured(self._target) or self._target
        roll = await self._compute(self._window_leading_roll, target, self.estimate)
        self._target = dataclasses.replace(target, roll_rad=roll)
        threshold = self.config.models.policy_stop_uncertainty
        if self._target.uncertainty < threshold:
            return self._stop(
                f"the policy's uncertainty {self._target.uncertainty:.3f} is below {threshold}"
            )
        return State.APPROACH

    def _window_leading_roll(self, target: TouchTarget, estimate: ShapeEstimate) -> float:
        occupied = estimate.occupied_points_world()
        rolls = rolls_avoiding_rim_stops(target, self.outcomes)
        width = self.config.motion.touch_width_m
        return window_leading_roll(target, occupied, self.tool, width, rolls)

    def _stop(self, reason: str) -> State:
        log.info("session %s stops: %s", self.session_id, reason)
        self.stop_reason = reason
        return State.DONE

    def _onto_measured(self, target: TouchTarget) -> TouchTarget | None:
        return onto_measured(target, self.measured, pad_path_m(self.config))

    def _meets_measured(self, targets_world: np.ndarray, direction: np.ndarray) -> np.ndarray:
        return pad_paths_meet(self.measured, targets_world, direction, pad_path_m(self.config))

    def _skip(self, target: TouchTarget, reason: str, stage: str) -> None:
        if len(self.skipped) < MAX_SKIPPED_RECORDS:
            self.skipped.append(skip_record(target, self.touch_count + 1, stage, reason))

    async def _approach(self) -> State:
        assert self._target is not None and self.estimate is not None
        target = self._target
        obstacles = self.obstacles()
        arm = await self._device(self.devices.arm.state())
        pose_world_tcp = self.pose_world_tcp(arm)
        plan = partial(
            self.planner.plan_touch,
            pose_world_tcp,
            arm.joints_rad,
            target.target_world,
            target.direction_world,
            obstacles,
            came_from=self._came_from,
            rolls_rad=rolls_preferring(target.roll_rad),
        )
        try:
            touch_plan = await self._compute(plan)
        except SafetyViolation as violation:
            return self._drop(target, f"refused: {violation}")
        self._touch, waypoints = touch_plan.touch, touch_plan.transit
        self._refused_in_a_row = 0
        came_from = [pose_world_tcp]
        for waypoint in waypoints:
            await self.motion.move(waypoint)
            came_from.append(waypoint.pose_world_tcp)
        # The approach start is left after the touch: the way here is known to be clear.
        self._came_from = came_from[:-1] if waypoints else self._came_from
        if self._refining is not None:
            await self._take_refined()
            try:  # the refined estimate adds to the bound the approach keeps clear of
                joints = (await self._device(self.devices.arm.state())).joints_rad
                check = partial(self.planner.check_touch, rolls_rad=(touch_plan.roll_rad,))
                await self._compute(
                    check, target.target_world, target.direction_world, joints, self.obstacles()
                )
            except SafetyViolation as violation:
                return self._drop(target, f"refused after refining: {violation}")
        try:
            touched = await self.motion.move_until_contact(touch_plan.approach)
        except UnexpectedForceError as error:
            return await self._unexpected_force(target, error)
        if touched:
            log.info("the pad touched on the approach: the surface is nearer than estimated")
        return State.TOUCH

    def _drop(self, target: TouchTarget, reason: str) -> State:
        """A target given up at its approach: not proposed again, recorded; back to select."""
        log.warning("target %s dropped: %s", np.round(target.target_world, 3), reason)
        self._rejected.append(target.target_world)
        self._refused_in_a_row += 1
        self._skip(target, reason, "approach")
        return State.SELECT

    async def _unexpected_force(self, target: TouchTarget, error: UnexpectedForceError) -> State:
        """A rigid part met the object on the approach: back out along the approach line to
        its start, record the event, drop the target, go on (a failed retreat is a fault)."""
        log.warning("session %s: %s; backing out", self.session_id, error)
        if (failure := await self.motion.make_safe(self.obstacles(), lift=False)) is not None:
            raise SessionFault(f"{error}; {failure}")
        backed_out_to, _ = await self.motion.arm_pose()
        event = {"touch": self.touch_count + 1, **error.record(target, backed_out_to)}
        self.unexpected_forces.append(event)
        self.recorder.log_event(f"{error}; backed out, target dropped")
        self.publish("event", {"session": self.session_id, "unexpected_force": event})
        return self._drop(target, str(error))

    async def _touch_step(self) -> State:
        assert self._touch is not None and self._target is not None
        assert self._reference is not None
        devices, device = self.devices, self._device
        # Also after a contact on the approach: that one only stopped the arm at a light force.
        gripper = await self.motion.press_fingers(timeout_s=STEP_TIMEOUT_S[State.TOUCH] / 2)
        contact = gripper.blocked
        check_force_or_fault(gripper.force_n, self.config)
        tactile = await device(devices.tactile.read())
        arm = await device(devices.arm.state())
        pose_world_tcp = self.pose_world_tcp(arm)
        pose_world_pad = pose_world_tcp @ self.tool.pose_tcp_pad(gripper.width_m)
        self.recorder.log_robot(pose_world_tcp, pose_world_pad)
        # Back off: fingers to the approach width, then the arm out along the approach line
        # from where it stopped (before the stand-off when the pad touched on the approach).
        await self.motion.open_fingers_to_touch_width()
        retract = await self._compute(
            self.planner.plan_retract, self._touch, pose_world_tcp, arm.joints_rad
        )
        await self.motion.move(retract)

        measurement = TouchMeasurement(
            target=self._target,
            contact=contact,
            tactile=tactile,
            reference=self._reference,
            pose_world_pad=pose_world_pad,
            pad_start_world=self._touch.pad_start_world,
            force_n=gripper.force_n,
            gripper_width_m=gripper.width_m,
        )
        # The raw inputs first: a touch a replay can re-interpret, whatever becomes of it here.
        number = self.touch_count + 1
        inputs = touch_inputs_record(self.session_id, number, measurement)
        folder = self.recorder.artifacts_dir
        await record_in_thread(
            partial(save_tactile_frame, folder, inputs["gelsight_image"], tactile)
        )
        try:
            outcome = await self._compute(self.perception.interpret, measurement)
        except HeightMapError as error:
            # A bad measurement: this touch tells nothing; the shape stays as it is.
            self.touch_count += 1
            self.recorder.set_touch(self.touch_count)
            log.error("touch %d refused: %s; going on without it", self.touch_count, error)
            await record_in_thread(
                partial(self.recorder.log_touch, {**inputs, "refused": str(error)}, None)
            )
            body = {"session": self.session_id, "touch": self.touch_count, "contact": contact}
            self.publish("touch", {**body, "error": f"refused: {error}"})
            return self._select_or_done()
        self.outcomes.append(outcome)
        self.outcome_touches.append(number)
        if outcome.touch is not None and self.measured is not None:
            # What the gel swept through without meeting anything is free.
            free = touch_constraints(outcome.touch, self.measured.grid).empty_ijk()
            self.measured = await self._compute(self.measured.carve, free)
            await self._add_estimate_to_bound()
        self.touch_count += 1
        self.recorder.set_touch(self.touch_count)
        record = {**inputs, **outcome_record(outcome)}
        await record_in_thread(
            partial(self.recorder.log_tactile, tactile.image_bgr, outcome.height_map_mm),
            partial(self.recorder.log_touch_patch, outcome.touch),
            partial(
                self.recorder.log_touch,
                record,
                touch_rays(self._touch.pad_start_world, outcome, self._touch.pad_reach_world),
            ),
        )
        self.publish("touch", record)
        return State.REFINE

    async def _refine(self) -> State:
        assert self.estimate is not None
        refine = partial(self.perception.refine, self.estimate, list(self.outcomes), self.request)
        self._refining = asyncio.ensure_future(self._compute(refine))
        if not self.config.motion.refine_while_moving:
            await self._take_refined()
        return self._select_or_done()

    async def _take_refined(self, *, after_stop: bool = False) -> None:
        """Make the refinement running in the background the estimate (and add it to the
        bound, record and score it). ``after_stop``: the session has ended in a fault or an
        abort, the robot is safe; a failed refinement is logged, not raised."""
        if self._refining is None:
            return
        assert self.estimate is not None
        previous = self.estimate.probabilities
        try:  # a cancelled step leaves the refinement running, to be taken after the stop
            estimate = await asyncio.shield(self._refining)
        except asyncio.CancelledError:
            raise
        except Exception:
            self._refining = None
            if not after_stop:
                raise
            log.exception("session %s: the last refinement failed", self.session_id)
            return
        self._refining, self.estimate = None, estimate
        flipped = int(np.count_nonzero((self.estimate.probabilities > 0.5) != (previous > 0.5)))
        self.recorder.log_metric("voxels_flipped", flipped)
        await self._add_estimate_to_bound()
        await self._record_shape()
        self.times.mark()

    def _select_or_done(self) -> State:
        """After a touch: the next one, or done when the touch budget is spent."""
        if self.touch_count >= self.request.max_touches:
            return self._stop("the touch budget is spent")
        return State.SELECT

    # --- motion ---------------------------------------------------------------------------------

    def obstacles(self) -> Obstacles:
        """What motions keep clear of: where the object may be, and the estimate."""
        return Obstacles.of_estimate(self.estimate, self.bound, self.measured)

    async def _add_estimate_to_bound(self) -> None:
        """The estimate adds to where the object may be (and never removes from it)."""
        assert self.estimate is not None and self.measured is not None
        points = self.estimate.occupied_points_world(POSSIBLE_OCCUPANCY)
        self.bound = await self._compute(self.measured.with_points, points)

    async def _make_safe(self, *, report_failure: bool = True) -> None:
        """Stop, retreat the way the interrupted motion came and lift (``MotionExecutor``)."""
        obstacles = self.obstacles()
        failure = await self.motion.make_safe(obstacles, report_failure=report_failure)
        if failure is not None:
            self.error = (self.error or "") + f" ({failure})"

    async def _fault(self, message: str) -> None:
        self.error = message
        log.error("session %s fault: %s", self.session_id, message)
        await self._make_safe()
        self._transition(State.FAULT, message)

    # --- helpers --------------------------------------------------------------------------------

    async def _record_shape(self) -> None:
        estimate = self.estimate
        assert estimate is not None
        await record_in_thread(
            partial(self.publish_shape, estimate),
            # The surface takes ~1 s (marching cubes at 1.5 mm): after the publish.
            partial(self.recorder.log_estimate, estimate, vision=self.touch_count == 0),
        )
        if self._scores is not None:
            self._scores.add(estimate, self.touch_count)

    def finish(self) -> None:
        """Back to idle once the service has saved the session's artifacts."""
        self._transition(State.IDLE)

    def summary(self) -> dict[str, Any]:
        return {
            "session": self.session_id,
            "state": str(self.state),
            "touches": self.touch_count,
            **contact_counts(self.outcomes),
            "error": self.error,
            "stop_reason": self.stop_reason,
            "skipped_targets": self.skipped,
            "unexpected_forces": self.unexpected_forces,
            "request": self.request.__dict__,
            **self.times.summary(),
            "metrics": self.metrics,
        }
