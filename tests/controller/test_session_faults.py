"""Device faults in the middle of a session: fault state, robot safe, artifacts kept."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import trimesh

from controller.config import Config
from controller.request import ExploreRequest
from controller.service import TouchshapeService
from tests.fakes.devices import (
    StaleCamera,
    TimingOutGripper,
    assert_went_back_to,
    record_arm_moves,
)
from tests.fakes.perception import CylinderPerception


def config() -> Config:
    base = Config()
    return dataclasses.replace(base, sim=dataclasses.replace(base.sim, object="can"))


async def run_session(service: TouchshapeService, touches: int = 3) -> tuple[dict, list]:
    published: list[tuple[str, dict]] = []
    service._publish = lambda name, body: published.append((name, body))  # type: ignore[method-assign]
    service.start_session(ExploreRequest(max_touches=touches))
    summary = await service.wait_session()
    assert summary is not None
    return summary, [body["state"] for name, body in published if name == "state"]


def assert_recording_verifies(summary: dict) -> None:
    rerun = Path(sys.executable).with_name("rerun")
    result = subprocess.run([str(rerun), "rrd", "verify", summary["artifacts"]["recording"]])
    assert result.returncode == 0


async def test_protective_stop_mid_session(tmp_path: Path) -> None:
    """An obstacle the camera did not see (a bar across the arm's way to its first approach)
    stops the arm; it recovers and goes back to where the stopped move began."""
    seen: dict = {}

    def perception(cfg: Config, devices):
        seen["devices"] = devices
        return CylinderPerception(cfg, devices)

    service = TouchshapeService(config(), perception, logs_dir=tmp_path)
    await service.start()
    try:
        world = seen["devices"].world
        bar = trimesh.creation.box((0.2, 0.03, 0.02))
        bar.apply_translation((0.0, -0.17, 0.25))
        world.object_mesh_world = trimesh.util.concatenate([world.object_mesh_world, bar])
        moves = record_arm_moves(seen["devices"])
        summary, states = await run_session(service)
        arm = await service.devices.arm.state()  # type: ignore[union-attr]
    finally:
        await service.stop()
    assert states[-2:] == ["fault", "idle"]
    assert summary["state"] == "fault" and "ProtectiveStop" in summary["error"]
    assert "retreat failed" not in summary["error"]
    assert not arm.protective_stopped and not arm.is_moving
    stopped = [m for m in moves if m.error is not None]
    assert len(stopped) == 1 and "ProtectiveStop" in stopped[0].error
    # It had gone some way before the bar stopped it; then back to where that move began.
    start = stopped[0].start_world[:3, 3]
    assert np.linalg.norm(stopped[0].end_world[:3, 3] - start) > 0.02
    assert moves[-1] is not stopped[0]
    assert_went_back_to(moves, world.pose_world_tcp(), start)
    assert_recording_verifies(summary)
    assert Path(summary["artifacts"]["summary"]).exists()


async def test_gripper_timeout_mid_touch(tmp_path: Path) -> None:
    cfg = config()

    def perception(c: Config, devices):
        devices.gripper = TimingOutGripper(devices.gripper, c.limits.contact_force_n)
        return CylinderPerception(c, devices)

    service = TouchshapeService(cfg, perception, logs_dir=tmp_path)
    await service.start()
    try:
        summary, states = await run_session(service)
        arm = await service.devices.arm.state()  # type: ignore[union-attr]
    finally:
        await service.stop()
    assert "touch" in states and states[-2:] == ["fault", "idle"]
    assert "DeviceTimeoutError" in summary["error"]
    assert not arm.is_moving
    assert_recording_verifies(summary)


async def test_stale_camera_frames(tmp_path: Path) -> None:
    def perception(c: Config, devices):
        devices.camera = StaleCamera(devices.camera)
        return CylinderPerception(c, devices)

    service = TouchshapeService(config(), perception, logs_dir=tmp_path)
    await service.start()
    try:
        summary, states = await run_session(service)
    finally:
        await service.stop()
    assert states[-3:] == ["capture", "fault", "idle"]
    assert "old" in summary["error"]
    assert_recording_verifies(summary)


async def test_touches_survive_a_fault(tmp_path: Path) -> None:
    """Touches completed before a fault stay on disk, one JSON line each."""
    calls = {"n": 0}

    def perception(c: Config, devices):
        inner = devices.gripper
        fake = TimingOutGripper(inner, -1.0)

        async def move(width_m, *, speed_m_s, force_limit_n, timeout_s):
            if force_limit_n == c.limits.contact_force_n:
                calls["n"] += 1
                if calls["n"] == 2:
                    from drivers.base import DeviceTimeoutError

                    raise DeviceTimeoutError("WSG 50 did not answer")
            return await inner.move(
                width_m, speed_m_s=speed_m_s, force_limit_n=force_limit_n, timeout_s=timeout_s
            )

        fake.move = move  # type: ignore[method-assign]
        devices.gripper = fake
        return CylinderPerception(c, devices)

    service = TouchshapeService(config(), perception, logs_dir=tmp_path)
    await service.start()
    try:
        summary, _ = await run_session(service)
    finally:
        await service.stop()
    assert summary["state"] == "fault" and summary["touches"] == 1
    lines = Path(summary["artifacts"]["touches"]).read_text().splitlines()
    assert [json.loads(line)["touch"] for line in lines] == [1]
