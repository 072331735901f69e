"""The exploration state machine on the simulated bench, with a geometric test perception."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from controller.config import Config
from controller.request import ExploreRequest
from controller.service import TouchshapeService
from controller.states import TRANSITIONS, State
from tests.fakes.perception import make_cylinder_perception

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


async def test_abort_during_approach_stops_and_retreats(tmp_path: Path) -> None:
    config = sim_config()
    config = dataclasses.replace(config, sim=dataclasses.replace(config.sim, real_time_factor=1.0))
    service = TouchshapeService(config, make_cylinder_perception, logs_dir=tmp_path)
    await service.start()
    try:
        published: list[tuple[str, dict]] = []
        service._publish = lambda name, body: published.append((name, body))  # type: ignore[method-assign]
        service.start_session(ExploreRequest(max_touches=2))
        while not any(b.get("state") == "approach" for n, b in published if n == "state"):
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.2)
        assert await service.abort_session()
        summary = await service.wait_session()
        arm = await service.devices.arm.state()  # type: ignore[union-attr]
    finally:
        await service.stop()
    assert summary is not None and summary["state"] == "aborted"
    assert not arm.is_moving and not arm.protective_stopped
    states = [b["state"] for n, b in published if n == "state"]
    assert states[-2:] == ["aborted", "idle"]
