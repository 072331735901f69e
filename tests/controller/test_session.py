"""The exploration state machine on the simulated bench, with a geometric test perception."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from controller.config import Config
from controller.recording import SessionRecorder
from controller.request import ExploreRequest
from controller.service import TouchshapeService
from controller.states import TRANSITIONS, State
from drivers.factory import Devices
from models.touch.observations import SurfaceObservations
from tests.fakes.devices import approach_start_world, assert_went_back_to, record_arm_moves
from tests.fakes.perception import CylinderPerception, make_cylinder_perception

WORKING_ORDER = ["capture", "reconstruct", "select", "approach", "touch", "refine"]


def sim_config(object_name: str = "can") -> Config:
    config = Config()
    return dataclasses.replace(config, sim=dataclasses.replace(config.sim, object=object_name))


def rerun_verify(path: str) -> None:
    rerun = Path(sys.executable).with_name("rerun")
    result = subprocess.run([str(rerun), "rrd", "verify", path], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr


async def run_one(service: TouchshapeService, request: ExploreRequest) -> dict:
    published: list[tuple[str, dict]] = []
    service._publish = lambda name, body: published.append((name, body))  # type: ignore[method-assign]
    service.start_session(request)
    summary = await service.wait_session()
    assert summary is not None
    return {"summary": summary, "published": published}


async def test_a_session_touches_and_records(tmp_path: Path) -> None:
    service = TouchshapeService(sim_config(), make_cylinder_perception, logs_dir=tmp_path)
    await service.start()
    try:
        result = await run_one(service, ExploreRequest(max_touches=3))
    finally:
        await service.stop()
    summary = result["summary"]
    assert summary["state"] == "done", summary
    assert summary["touches"] == 3 and summary["contacts"] >= 2
    states = [body["state"] for name, body in result["published"] if name == "state"]
    assert states[: len(WORKING_ORDER)] == WORKING_ORDER
    assert states[-2:] == ["done", "idle"]
    for name, body in result["published"]:
        if name == "state" and body["previous"] != "idle":
            assert State(body["state"]) in TRANSITIONS[State(body["previous"])]
    touches = [
        json.loads(line) for line in Path(summary["artifacts"]["touches"]).read_text().splitlines()
    ]
    assert [t["touch"] for t in touches] == [1, 2, 3]
    rerun_verify(summary["artifacts"]["recording"])
    assert Path(summary["artifacts"]["summary"]).exists()
    assert Path(summary["artifacts"]["mesh"]).stat().st_size > 0
    # Scored against the simulation's ground truth after reconstruct and each of 3 touches.
    assert len(summary["metrics"]["chamfer_mm"]) == 4
    voxels = np.load(summary["artifacts"]["voxels"])
    assert voxels["probabilities"].shape == (64, 64, 64)
    # The test perception keeps no rays: the observations file is there, and empty.
    assert SurfaceObservations.load(summary["artifacts"]["observations"]).is_empty


async def test_without_a_sim_world_nothing_is_scored_or_logged_as_truth(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Devices without a sim world (as real ones are built): no ground-truth scores, no true
    mesh in the recording, no simulated times; the session itself runs as before."""
    truth: list[object] = []
    log_setup = SessionRecorder.log_setup

    def spy(self: SessionRecorder, pose: np.ndarray, grid: object, mesh: object = None) -> None:
        truth.append(mesh)
        log_setup(self, pose, grid, mesh)  # type: ignore[arg-type]

    monkeypatch.setattr(SessionRecorder, "log_setup", spy)

    def perception(config: Config, devices: Devices) -> CylinderPerception:
        made = CylinderPerception(config, devices)  # it reads the object from the world first
        devices.world = None
        return made

    service = TouchshapeService(sim_config(), perception, logs_dir=tmp_path)
    await service.start()
    try:
        summary = (await run_one(service, ExploreRequest(max_touches=1)))["summary"]
    finally:
        await service.stop()
    assert summary["state"] == "done" and summary["touches"] == 1, summary["error"]
    assert summary["metrics"] == {}
    assert "per_touch_sim_s" not in summary
    assert truth == [None]


async def test_abort_during_approach_stops_and_retreats(tmp_path: Path) -> None:
    """Aborted while the arm moves (the simulation sleeping at every control step, at four
    times real speed) with the pad 20 mm along its approach line: the arm stops, goes back
    along the line to where the approach began, and up above the object."""
    config = sim_config()
    sim = dataclasses.replace(config.sim, real_time_factor=0.25)
    config = dataclasses.replace(config, sim=sim)
    speed = config.limits.approach_speed_m_s
    service = TouchshapeService(config, make_cylinder_perception, logs_dir=tmp_path)
    await service.start()
    assert service.devices is not None and service.devices.world is not None
    world = service.devices.world
    moves = record_arm_moves(service.devices)

    def approached_m() -> float:
        slow = [m for m in moves if m.speed_m_s <= speed]
        return 0.0 if not slow else float(np.linalg.norm(slow[-1].end_world - slow[0].start_world))

    try:
        published: list[tuple[str, dict]] = []
        service._publish = lambda name, body: published.append((name, body))  # type: ignore[method-assign]
        service.start_session(ExploreRequest(max_touches=2))
        async with asyncio.timeout(60):
            while approached_m() < 0.02:
                await asyncio.sleep(0.01)
        assert await service.abort_session()
        summary = await service.wait_session()
        arm = await service.devices.arm.state()
    finally:
        await service.stop()
    assert summary is not None and summary["state"] == "aborted"
    assert not arm.is_moving and not arm.protective_stopped
    states = [b["state"] for n, b in published if n == "state"]
    assert states[-3:] == ["approach", "aborted", "idle"]
    start = approach_start_world(moves, speed)
    final = world.pose_world_tcp()
    assert_went_back_to(moves, final, start)
    top = world.object_mesh_world.bounds[1, 2]
    assert final[2, 3] > start[2] + 0.05 and final[2, 3] > top + config.motion.safe_height_margin_m
