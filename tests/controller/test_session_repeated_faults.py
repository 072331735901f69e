"""Faults in a row never walk the arm away: a fault's retreat goes back to where the interrupted
motion started (or nowhere), and the session after a fault starts from a checked home. Each
test runs faulting sessions in a row, then a valid one that runs normally."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from controller.config import Config
from controller.motion.poses import home_pose_world_tcp
from controller.perception.protocol import ShapeEstimate
from controller.request import ExploreRequest
from controller.service import TouchshapeService
from drivers.base import DeviceTimeoutError, RGBDFrame
from drivers.factory import Devices
from models.prior.shape_prior import PriorNotFoundError
from tests.fakes.devices import record_arm_moves
from tests.fakes.perception import CylinderPerception

FAULTS_IN_A_ROW = 10
APPROACH_FAULTS_IN_A_ROW = 3
"""Each of these moves the arm (home, across, down, part of an approach, back, up): three show
the same path repeats without making the default suite slow."""
TCP_TOLERANCE_M = 0.005


def config() -> Config:
    base = Config()
    return dataclasses.replace(base, sim=dataclasses.replace(base.sim, object="can"))


class PriorMissingPerception(CylinderPerception):
    """Reconstruct fails while ``failing`` is set, as a prior whose weights are missing does."""

    failing = True

    def reconstruct(self, frame: RGBDFrame, request: ExploreRequest) -> ShapeEstimate:
        if self.failing:
            raise PriorNotFoundError("no prior named 'nosuchprior'")
        return super().reconstruct(frame, request)


async def run(service: TouchshapeService, touches: int = 1) -> dict:
    service.start_session(ExploreRequest(max_touches=touches))
    summary = await service.wait_session()
    assert summary is not None
    return summary


def tcp_position(devices: Devices | None) -> np.ndarray:
    assert devices is not None and devices.world is not None
    return devices.world.pose_world_tcp()[:3, 3].copy()


async def test_faults_in_reconstruct_leave_the_arm_where_it_was(tmp_path: Path) -> None:
    """The issue's case: each fault used to retreat 60 mm further from wherever the arm was."""
    made: list[PriorMissingPerception] = []

    def perception(cfg: Config, devices: Devices) -> PriorMissingPerception:
        made.append(PriorMissingPerception(cfg, devices))
        return made[-1]

    service = TouchshapeService(config(), perception, logs_dir=tmp_path)
    await service.start()
    service._publish = lambda name, body: None  # type: ignore[method-assign]
    try:
        positions = []
        for _ in range(FAULTS_IN_A_ROW):
            summary = await run(service)
            assert summary["state"] == "fault" and "PriorNotFoundError" in summary["error"]
            positions.append(tcp_position(service.devices))
        made[0].failing = False
        valid = await run(service)
    finally:
        await service.stop()
    drift = np.linalg.norm(np.array(positions) - positions[0], axis=1)
    assert drift.max() <= TCP_TOLERANCE_M, drift
    assert valid["state"] == "done", valid["error"]
    assert valid["touches"] == 1 and valid["contacts"] == 1


async def test_faults_on_the_approach_each_start_from_home(tmp_path: Path) -> None:
    """A device error part-way along every approach: each fault goes back to the approach start
    and up; the next session goes home (through the planner) before it captures, so every
    session takes the same path and ends in the same place."""
    cfg = config()
    home = home_pose_world_tcp(cfg.robot.arm)[:3, 3]
    seen: dict = {"failing": True, "approach_steps": 0, "capture_at": []}

    def perception(c: Config, devices: Devices) -> CylinderPerception:
        seen["moves"] = record_arm_moves(devices)
        arm, camera = devices.arm, devices.camera
        recorded_move, inner_read = arm.move_linear, camera.read

        async def move_linear(
            pose_base_tcp: np.ndarray,
            *,
            speed_m_s: float,
            acceleration_m_s2: float,
            timeout_s: float,
        ) -> None:
            # The approach's 0.5 mm steps run at the approach speed: fail the fifth of each.
            if seen["failing"] and speed_m_s <= c.limits.approach_speed_m_s:
                seen["approach_steps"] += 1
                if seen["approach_steps"] % 5 == 0:
                    raise DeviceTimeoutError("UR5 did not confirm the move")
            await recorded_move(
                pose_base_tcp,
                speed_m_s=speed_m_s,
                acceleration_m_s2=acceleration_m_s2,
                timeout_s=timeout_s,
            )

        async def read(*, timeout_s: float = 2.0) -> RGBDFrame:
            seen["capture_at"].append(tcp_position(devices))
            return await inner_read(timeout_s=timeout_s)

        arm.move_linear = move_linear  # type: ignore[method-assign]
        camera.read = read  # type: ignore[method-assign]
        return CylinderPerception(c, devices)

    service = TouchshapeService(cfg, perception, logs_dir=tmp_path)
    await service.start()
    service._publish = lambda name, body: None  # type: ignore[method-assign]
    try:
        positions = []
        for _ in range(APPROACH_FAULTS_IN_A_ROW):
            summary = await run(service)
            assert summary["state"] == "fault" and "DeviceTimeoutError" in summary["error"]
            assert "retreat failed" not in summary["error"]
            positions.append(tcp_position(service.devices))
        seen["failing"] = False
        valid = await run(service)
    finally:
        await service.stop()
    drift = np.linalg.norm(np.array(positions) - positions[0], axis=1)
    assert drift.max() <= TCP_TOLERANCE_M, drift
    # Lifted, not left on the approach line beside the object.
    assert positions[0][2] > 0.25
    # Every session captured from home (the first from where the service started: home too),
    # and all but the first had to go back there first.
    assert len(seen["capture_at"]) == APPROACH_FAULTS_IN_A_ROW + 1
    for position in seen["capture_at"]:
        assert np.linalg.norm(position - home) <= 0.001, position
    assert not np.allclose(positions[0], home, atol=0.01)
    assert valid["state"] == "done", valid["error"]
    assert valid["touches"] == 1 and valid["contacts"] == 1
