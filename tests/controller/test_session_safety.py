"""Sessions whose shape estimate is wrong, on the simulated bench: the planner keeps its margin
from where the object may be, the approach stops on the first light force, and a fault retreats
the way the arm came (sessions on the sim bench complete without protective stops)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from controller.config import Config
from controller.perception.protocol import ShapeEstimate
from controller.request import ExploreRequest
from controller.service import TouchshapeService
from drivers.factory import Devices
from models.geometry import make_transform
from tests.fakes.perception import CylinderPerception


def replace_object(devices: Devices, mesh: trimesh.Trimesh) -> None:
    """The simulated object the arm and the gel meet (the camera keeps the original)."""
    world = devices.world
    assert world is not None
    world.object_mesh_world = mesh
    world.scene_mesh_world = trimesh.util.concatenate([mesh, world.table_mesh_world])


def config(object_name: str = "can") -> Config:
    base = Config()
    return dataclasses.replace(base, sim=dataclasses.replace(base.sim, object=object_name))


class TooSmallPerception(CylinderPerception):
    """Sees a cylinder 15 mm narrower than the object (a vision estimate too small there): every
    approach meets the object well before the estimate's surface."""

    def reconstruct(self, frame, request) -> ShapeEstimate:  # type: ignore[no-untyped-def]
        self.reconstruct_calls += 1
        centres = self.grid.voxel_centres_world()
        radius = np.max(np.linalg.norm(self.mesh.vertices[:, :2], axis=1)) - 0.015
        height = self.mesh.bounds[1, 2]
        inside = (np.linalg.norm(centres[..., :2], axis=-1) <= radius) & (centres[..., 2] <= height)
        return ShapeEstimate(self.grid, np.where(inside, 0.9, 0.02).astype(np.float32))


async def run(service: TouchshapeService, touches: int) -> dict:
    service._publish = lambda name, body: None  # type: ignore[method-assign]
    service.start_session(ExploreRequest(max_touches=touches))
    summary = await service.wait_session()
    assert summary is not None
    return summary


async def test_estimate_too_small_the_pad_meets_tilted_faces_early(tmp_path: Path) -> None:
    """A box turned 40 degrees about the vertical, seen as a thinner cylinder: the pad meets
    faces tilted up to ~45 degrees to it (and their edges) long before the estimate said. The
    approach stops at the first light force (the rigid window behind the gel never reaches the
    box), the fingers make each touch, and the session completes."""

    def perception(cfg: Config, devices: Devices) -> TooSmallPerception:
        box = trimesh.creation.box((0.07, 0.07, 0.1))
        box.apply_transform(make_transform(None, (0.0, 0.0, 0.05)))
        box.apply_transform(trimesh.transformations.rotation_matrix(np.radians(40), (0, 0, 1)))
        replace_object(devices, box)
        return TooSmallPerception(cfg, devices)

    service = TouchshapeService(config(), perception, logs_dir=tmp_path)
    await service.start()
    try:
        summary = await run(service, touches=3)
        arm = await service.devices.arm.state()  # type: ignore[union-attr]
    finally:
        await service.stop()
    assert summary["state"] == "done", summary["error"]
    assert summary["touches"] == 3 and summary["contacts"] == 3
    assert not arm.protective_stopped


async def test_a_fault_on_the_approach_retreats_to_its_start_and_up(tmp_path: Path) -> None:
    """A bar the camera did not see, just below the gel's window on the first approach:
    the housing hits it (the gel feels nothing). The arm goes back to where the approach began
    (not to the last millimetre step, which is still beside the bar) and up above the object."""
    seen: dict = {}

    def perception(cfg: Config, devices: Devices) -> CylinderPerception:
        seen["devices"] = devices
        return CylinderPerception(cfg, devices)

    service = TouchshapeService(config(), perception, logs_dir=tmp_path)
    await service.start()
    try:
        world = seen["devices"].world
        mesh = world.object_mesh_world
        radius = np.max(np.linalg.norm(mesh.vertices[:, :2], axis=1)) + 0.01
        pad_z = mesh.bounds[1, 2] * 0.6  # CylinderPerception's first target: -y side, 0.6 h
        bar = trimesh.creation.box((0.06, 0.012, 0.006))
        bar.apply_translation((0.0, -radius - 0.011, pad_z - 0.014))
        replace_object(seen["devices"], trimesh.util.concatenate([mesh, bar]))
        summary = await run(service, touches=2)
        arm_state = await service.devices.arm.state()  # type: ignore[union-attr]
        pose = world.pose_world_tcp()
    finally:
        await service.stop()
    assert summary["state"] == "fault" and "gelsight_housing hit" in summary["error"]
    assert "retreat failed" not in summary["error"]
    assert not arm_state.protective_stopped
    # Back at the approach start (the first approach in motions.jsonl: the pad 60 mm before
    # the target, the flange 73 mm behind the pad), then lifted above the object.
    motions = (tmp_path / summary["session"] / "motions.jsonl").read_text().splitlines()
    approach = next(json.loads(line) for line in motions if '"approach"' in line)
    start = np.asarray(approach["start_world_tcp"])
    assert start[1, 3] < -radius - 0.05 - 0.07
    np.testing.assert_allclose(pose[:2, 3], start[:2, 3], atol=0.001)
    assert pose[2, 3] > mesh.bounds[1, 2] + 0.05


@pytest.mark.slow  # ~30 s: the learned prior, GelSight reconstruction and refinement
async def test_learned_session_on_the_mug_completes_without_a_fault(tmp_path: Path) -> None:
    from controller.perception.learned import make_perception

    service = TouchshapeService(config("mug"), make_perception, logs_dir=tmp_path)
    await service.start()
    try:
        summary = await run(service, touches=5)
    finally:
        await service.stop()
    assert summary["state"] == "done", summary["error"]
    assert summary["touches"] >= 3
