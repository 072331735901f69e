"""The session's safety paths, each at session level on the simulated bench: a force over the
limit, a step past its time limit and an unexpected error each become a fault that takes the
robot back to where the touch began and up; the transition guard; a refused target goes back
to select; a workspace violation is refused before anything moves."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import ClassVar

import numpy as np
import pytest

from controller.config import Config
from controller.perception.protocol import ShapeEstimate, TouchOutcome, TouchTarget
from controller.request import ExploreRequest
from controller.service import TouchshapeService
from controller.session import MAX_REFUSED_IN_A_ROW, ExplorationSession
from controller.states import STEP_TIMEOUT_S, TRANSITIONS, State
from drivers.base import GripperState, TactileFrame
from drivers.factory import Devices, make_devices
from tests.fakes.devices import (
    ArmMove,
    approach_start_world,
    assert_went_back_to,
    record_arm_moves,
)
from tests.fakes.perception import CylinderPerception


def config() -> Config:
    base = Config()
    return dataclasses.replace(base, sim=dataclasses.replace(base.sim, object="can"))


async def explore(
    tmp_path: Path,
    change_devices: Callable[[Config, Devices], None] = lambda cfg, devices: None,
    perception: type[CylinderPerception] = CylinderPerception,
    touches: int = 2,
) -> tuple[dict, list[str], list[ArmMove], Devices]:
    """One session on the sim bench; ``change_devices`` injects faults before it starts.
    Returns the summary, the published states, the arm's moves and the devices."""
    cfg = config()
    seen: dict = {}

    def make_perception(c: Config, devices: Devices) -> CylinderPerception:
        seen["moves"] = record_arm_moves(devices)
        change_devices(c, devices)
        return perception(c, devices)

    service = TouchshapeService(cfg, make_perception, logs_dir=tmp_path)
    await service.start()
    published: list[tuple[str, dict]] = []
    service._publish = lambda name, body: published.append((name, body))  # type: ignore[method-assign]
    devices = service.devices
    assert devices is not None
    try:
        service.start_session(ExploreRequest(max_touches=touches))
        summary = await service.wait_session()
        arm = await devices.arm.state()
    finally:
        await service.stop()
    assert summary is not None
    assert not arm.is_moving and not arm.protective_stopped
    states = [body["state"] for name, body in published if name == "state"]
    return summary, states, seen["moves"], devices


def assert_back_at_the_approach_start_and_up(moves: list[ArmMove], devices: Devices) -> None:
    """The path after a fault on a touch: back along the approach line to where it began (the
    way the pad came, clear), then up above the object."""
    assert devices.world is not None
    cfg = config()
    speed = cfg.limits.approach_speed_m_s
    start = approach_start_world(moves, speed)
    deepest = max(
        (m.end_world[:3, 3] for m in moves if m.speed_m_s <= speed),
        key=lambda p: np.linalg.norm(p - start),
    )
    assert np.linalg.norm(deepest - start) > 0.03  # the pad had gone in towards the object
    final = devices.world.pose_world_tcp()
    assert_went_back_to(moves, final, start)
    top = devices.world.object_mesh_world.bounds[1, 2]
    assert final[2, 3] > start[2] + 0.05 and final[2, 3] > top + cfg.motion.safe_height_margin_m


async def test_a_force_over_the_limit_during_a_touch_is_a_fault(tmp_path: Path) -> None:
    """The fingers report 50 N on the touch (over the 40 N limit): a collision, not a touch."""

    def crush(cfg: Config, devices: Devices) -> None:
        inner = devices.gripper.move

        async def move(width_m: float, **kwargs: float) -> GripperState:
            state = await inner(width_m, **kwargs)  # type: ignore[arg-type]
            if kwargs["force_limit_n"] == cfg.limits.contact_force_n:
                return dataclasses.replace(state, force_n=cfg.limits.max_force_n + 10)
            return state

        devices.gripper.move = move  # type: ignore[method-assign]

    summary, states, moves, devices = await explore(tmp_path, crush)
    assert states[-3:] == ["touch", "fault", "idle"]
    assert summary["error"] == "SessionFault: force 50.0 N over the limit 40.0 N"
    assert summary["touches"] == 0  # not taken as a touch
    assert devices.world is not None
    assert devices.world.gripper_width_m == pytest.approx(config().motion.touch_width_m, abs=1e-4)
    assert_back_at_the_approach_start_and_up(moves, devices)


async def test_a_step_past_its_time_limit_is_a_fault(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The gripper never answers the touch: the touch step times out, the session faults and
    the arm goes back the way it came."""
    monkeypatch.setitem(STEP_TIMEOUT_S, State.TOUCH, 1.0)

    def hang(cfg: Config, devices: Devices) -> None:
        inner = devices.gripper.move

        async def move(width_m: float, **kwargs: float) -> GripperState:
            if kwargs["force_limit_n"] == cfg.limits.contact_force_n:
                await asyncio.Event().wait()
            return await inner(width_m, **kwargs)  # type: ignore[arg-type]

        devices.gripper.move = move  # type: ignore[method-assign]

    summary, states, moves, devices = await explore(tmp_path, hang)
    assert states[-3:] == ["touch", "fault", "idle"]
    assert summary["error"] == "touch timed out after 1.0 s"
    assert_back_at_the_approach_start_and_up(moves, devices)


async def test_an_unexpected_error_in_a_step_is_a_fault_and_the_robot_is_made_safe(
    tmp_path: Path,
) -> None:
    """A bug (not a device error) while the pad presses on the object: the fingers pull the pad
    back, the arm goes back to the approach start and up, and the session ends in fault."""

    def broken_sensor(cfg: Config, devices: Devices) -> None:
        async def read(*, timeout_s: float = 1.0) -> TactileFrame:
            raise RuntimeError("frame buffer index out of range")

        devices.tactile.read = read  # type: ignore[method-assign]

    summary, states, moves, devices = await explore(tmp_path, broken_sensor)
    assert states[-3:] == ["touch", "fault", "idle"]
    assert summary["error"] == (
        "internal error in touch: RuntimeError('frame buffer index out of range')"
    )
    assert devices.world is not None
    assert devices.world.gripper_width_m == pytest.approx(config().motion.touch_width_m, abs=1e-4)
    assert_back_at_the_approach_start_and_up(moves, devices)


def test_the_transition_guard_refuses_every_illegal_transition() -> None:
    cfg = config()
    devices = make_devices(
        arm=cfg.robot.arm,
        gripper=cfg.gripper,
        sensor=cfg.sensor,
        camera=cfg.cameras.rgbd,
        sim=cfg.sim,
        rng=np.random.default_rng(0),
    )
    published: list[tuple[str, dict]] = []
    session = ExplorationSession(
        session_id="guard",
        request=ExploreRequest(),
        config=cfg,
        devices=devices,
        perception=CylinderPerception(cfg, devices),
        recorder=SimpleNamespace(log_state=lambda *args: None),  # type: ignore[arg-type]
        publish=lambda name, body: published.append((name, body)),
    )
    illegal = 0
    for source in State:
        for target in State:
            session.state = source
            if target in TRANSITIONS[source]:
                session._transition(target)
                assert session.state == target
                continue
            illegal += 1
            with pytest.raises(RuntimeError, match=f"illegal transition {source} -> {target}$"):
                session._transition(target)
            assert session.state == source
    assert illegal > 50  # e.g. idle -> touch, done -> capture, fault -> select
    legal = sum(len(targets) for targets in TRANSITIONS.values())
    assert len(published) == legal  # a refused transition publishes nothing


class FirstTargetUnderTheTable(CylinderPerception):
    """Proposes a target the planner must refuse (below the table top) first, ignoring the
    planner's check, then the cylinder's targets; remembers what the check said of it later."""

    refused = TouchTarget(np.array([0.0, -0.05, -0.02]), np.array([0.0, 1.0, 0.0]))

    def __init__(self, cfg: Config, devices: Devices) -> None:
        super().__init__(cfg, devices)
        self.calls = 0
        self.refused_allowed_later: list[bool] = []

    def select(
        self,
        estimate: ShapeEstimate,
        request: ExploreRequest,
        outcomes: list[TouchOutcome],
        allowed: Callable[[TouchTarget], bool],
        feasible: object = None,
        robot_seconds: object = None,
    ) -> TouchTarget | None:
        self.calls += 1
        if self.calls == 1:
            return self.refused
        self.refused_allowed_later.append(allowed(self.refused))
        return super().select(estimate, request, outcomes, allowed)


async def test_a_refused_target_goes_back_to_select(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    made: list[FirstTargetUnderTheTable] = []

    class Recorded(FirstTargetUnderTheTable):
        def __init__(self, cfg: Config, devices: Devices) -> None:
            super().__init__(cfg, devices)
            made.append(self)

    with caplog.at_level(logging.WARNING, logger="controller.session"):
        summary, states, moves, devices = await explore(tmp_path, perception=Recorded, touches=1)
    assert states[:6] == ["capture", "reconstruct", "select", "approach", "select", "approach"]
    assert summary["state"] == "done" and summary["touches"] == 1, summary["error"]
    refusal = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert len(refusal) == 1 and "above the table" in refusal[0], refusal
    # Excluded from then on (the planner's check says no), and the touch after it happened.
    assert made[0].refused_allowed_later and not any(made[0].refused_allowed_later)
    # The touch after it is the cylinder's first target, on the -y side.
    start = approach_start_world(moves, config().limits.approach_speed_m_s)
    assert start[1] < -0.1
    # Done, the arm rests at that approach start or above it, not back in where it touched.
    assert devices.world is not None
    final = devices.world.pose_world_tcp()[:3, 3]
    assert np.linalg.norm(final[:2] - start[:2]) < 0.001 and final[2] >= start[2] - 0.001


class OnlyOutsideTheWorkspace(CylinderPerception):
    """One target whose approach start lies outside the workspace box (x > 0.40 m), proposed
    without asking the planner; then nothing."""

    def select(
        self,
        estimate: ShapeEstimate,
        request: ExploreRequest,
        outcomes: list[TouchOutcome],
        allowed: Callable[[TouchTarget], bool],
        feasible: object = None,
        robot_seconds: object = None,
    ) -> TouchTarget | None:
        if getattr(self, "proposed", False):
            return None
        self.proposed = True
        return TouchTarget(np.array([0.37, 0.0, 0.05]), np.array([-1.0, 0.0, 0.0]))


async def test_a_workspace_violation_is_refused_before_anything_moves(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="controller.session"):
        summary, states, moves, _ = await explore(tmp_path, perception=OnlyOutsideTheWorkspace)
    refusal = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert len(refusal) == 1 and "outside the workspace box" in refusal[0], refusal
    assert states == ["capture", "reconstruct", "select", "approach", "select", "done", "idle"]
    assert summary["touches"] == 0
    assert moves == []  # nothing moved


class AlwaysOutsideTheWorkspace(CylinderPerception):
    """Proposes the same unreachable target every time, without asking the planner."""

    def select(
        self,
        estimate: ShapeEstimate,
        request: ExploreRequest,
        outcomes: list[TouchOutcome],
        allowed: Callable[[TouchTarget], bool],
        feasible: object = None,
        robot_seconds: object = None,
    ) -> TouchTarget | None:
        return TouchTarget(np.array([0.37, 0.0, 0.05]), np.array([-1.0, 0.0, 0.0]))


async def test_a_policy_that_keeps_proposing_refused_targets_ends_the_session(
    tmp_path: Path,
) -> None:
    """select -> approach -> select ... cannot run forever: after MAX_REFUSED_IN_A_ROW refusals
    the session stops, says why, and nothing moved."""
    summary, states, moves, _ = await explore(tmp_path, perception=AlwaysOutsideTheWorkspace)
    assert summary["state"] == "done"
    assert summary["stop_reason"].startswith("no safe, reachable target is left")
    assert states.count("approach") == MAX_REFUSED_IN_A_ROW
    assert len(summary["skipped_targets"]) == MAX_REFUSED_IN_A_ROW
    assert moves == []


class TimesItsTargets(CylinderPerception):
    """Asks the session what its targets would cost the robot, as the efficient policy does,
    and what the planner-refused target under the table would."""

    seconds: ClassVar[list[float | None]] = []

    def select(
        self,
        estimate: ShapeEstimate,
        request: ExploreRequest,
        outcomes: list[TouchOutcome],
        allowed: Callable[[TouchTarget], bool],
        feasible: object = None,
        robot_seconds: Callable[[TouchTarget], float | None] | None = None,
    ) -> TouchTarget | None:
        assert robot_seconds is not None
        target = super().select(estimate, request, outcomes, allowed)
        assert target is not None
        self.seconds += [robot_seconds(target), robot_seconds(FirstTargetUnderTheTable.refused)]
        return target


async def test_the_session_gives_the_policy_the_planners_robot_time(tmp_path: Path) -> None:
    """From home the first touch pays a transit around the object; the second starts next to
    where the first left the arm (the cylinder's targets are 10 degrees apart): it costs less.
    A target the planner refuses costs nothing: it has no time."""
    TimesItsTargets.seconds = []
    summary, _, _, _ = await explore(tmp_path, perception=TimesItsTargets, touches=2)
    assert summary["touches"] == 2, summary["error"]
    first, refused, second, refused_again = TimesItsTargets.seconds
    assert refused is None and refused_again is None
    assert first is not None and second is not None
    assert 0 < second < first
