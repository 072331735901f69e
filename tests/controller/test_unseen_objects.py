"""Exploration stays collision-safe whatever the vision estimate gets wrong: transits keep their
clearance from where the object may be (measured), not from the estimate, on the sim bench with
real sessions, measured against the true mesh."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import trimesh

from controller.benchmarks.safety import (
    SafetyObject,
    SessionRun,
    read_motions,
    run_session,
    session_row,
)
from controller.config import Config
from controller.perception.learned import make_perception
from controller.perception.protocol import ShapeEstimate, TouchTarget
from controller.request import ExploreRequest
from drivers.factory import Devices
from tests.fakes.perception import CylinderPerception

MIN_TRANSIT_CLEARANCE_MM = 5.0


class HalfSizePerception(CylinderPerception):
    """A prior that sees the object at half its true size (a cylinder half as wide and half as
    tall): its surface, and its targets, lie far inside the true object."""

    def reconstruct(self, frame, request) -> ShapeEstimate:  # type: ignore[no-untyped-def]
        centres = self.grid.voxel_centres_world()
        radius = 0.5 * np.max(np.linalg.norm(self.mesh.vertices[:, :2], axis=1))
        height = 0.5 * self.mesh.bounds[1, 2]
        inside = (np.linalg.norm(centres[..., :2], axis=-1) <= radius) & (centres[..., 2] <= height)
        return ShapeEstimate(self.grid, np.where(inside, 0.9, 0.02).astype(np.float32))

    def select(self, estimate, request, outcomes, allowed, feasible=None, robot_seconds=None):  # type: ignore[no-untyped-def]
        """Side touches just below the estimate's top, around its axis (the gripper body, a
        finger's length above the pad, must pass above the true object)."""
        occupied = estimate.occupied_points_world()
        radius = np.max(np.linalg.norm(occupied[:, :2], axis=1))
        height = occupied[:, 2].max() - 0.005
        for yaw_deg in range(0, 360, 45):
            yaw = np.radians(yaw_deg + 45 * len(outcomes))
            outward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
            target = TouchTarget(radius * outward + [0.0, 0.0, height], -outward)
            if allowed(target):
                return target
        return None


def config_with(object_spec: str) -> Config:
    base = Config()
    return dataclasses.replace(base, sim=dataclasses.replace(base.sim, object=object_spec))


async def explore(config: Config, factory, tmp_path: Path, touches: int) -> tuple[SessionRun, dict]:  # type: ignore[no-untyped-def]
    run = await run_session(config, ExploreRequest(max_touches=touches), factory, tmp_path, 0)
    assert run.error is None, run.error
    row = session_row(SafetyObject("object", config.sim.object), 0.0, run, config, tmp_path)
    return run, row


async def test_a_prior_half_the_true_size_cannot_make_a_transit_hit_the_object(
    tmp_path: Path,
) -> None:
    """A 20 x 20 x 10 cm box seen at half its size: a detour planned over the estimate would
    cross the box's top, an approach start beside the estimate would lie in its corner. Every
    transit keeps its clearance from the true box, and the approaches, aimed inside it, meet
    it on their force-checked way."""
    box = trimesh.creation.box((0.2, 0.2, 0.1))
    path = tmp_path / "box.obj"
    box.export(path)

    def perception(config: Config, devices: Devices) -> HalfSizePerception:
        return HalfSizePerception(config, devices)

    config = config_with(str(path))
    run, row = await explore(config, perception, tmp_path, touches=3)
    assert run.summary is not None
    assert run.summary["state"] == "done", run.summary["error"]
    assert row["protective_stops"] == 0
    assert row["touches"] == 3 and row["contacts"] == 3
    assert read_motions(tmp_path / run.summary["session"] / "motions.jsonl")
    assert row["min_transit_clearance_mm"] >= MIN_TRANSIT_CLEARANCE_MM, row["worst_transit"]


@pytest.mark.timeout(600)  # the learned perception and six touches: a minute on a quiet machine
async def test_six_touches_on_a_4_cm_object_do_not_fault(tmp_path: Path) -> None:
    """A lemon-sized ellipsoid (4 x 3 x 3 cm), the learned prior and the default settings: the
    session spends its budget without a fault or a protective stop, and the touches meet it."""
    lemon = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    lemon.apply_scale((0.02, 0.015, 0.015))
    path = tmp_path / "lemon.obj"
    lemon.export(path)
    config = config_with(str(path))
    run, row = await explore(config, make_perception, tmp_path, touches=6)
    assert run.summary is not None
    assert run.summary["state"] == "done", run.summary["error"]
    assert row["protective_stops"] == 0
    assert row["touches"] == 6
    assert row["contacts"] >= 0.8 * row["touches"]
    assert row["min_transit_clearance_mm"] >= MIN_TRANSIT_CLEARANCE_MM, row["worst_transit"]
