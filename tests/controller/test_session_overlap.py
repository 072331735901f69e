"""The refinement overlaps the arm's motion to the next target (``motion.refine_while_moving``),
and the approach is checked again against the refined estimate before the pad goes in."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pytest

from controller.config import Config
from controller.motion.planner import MotionPlanner
from controller.motion.safety import Obstacles, SafetyViolation
from controller.perception.protocol import ShapeEstimate, TouchOutcome
from controller.request import ExploreRequest
from controller.service import TouchshapeService
from drivers.factory import Devices
from tests.fakes.perception import CylinderPerception

MOTION_WAIT_S = 2.0


def config(refine_while_moving: bool = True) -> Config:
    base = Config()
    return dataclasses.replace(
        base,
        sim=dataclasses.replace(base.sim, object="can"),
        motion=dataclasses.replace(base.motion, refine_while_moving=refine_while_moving),
    )


async def explore(cfg: Config, perception: type[CylinderPerception], tmp_path: Path) -> dict:
    made: list[CylinderPerception] = []

    def make(c: Config, devices: Devices) -> CylinderPerception:
        made.append(perception(c, devices))
        return made[-1]

    service = TouchshapeService(cfg, make, logs_dir=tmp_path)
    await service.start()
    service._publish = lambda name, body: None  # type: ignore[method-assign]
    try:
        service.start_session(ExploreRequest(max_touches=2))
        summary = await service.wait_session()
    finally:
        await service.stop()
    assert summary is not None
    return {"summary": summary, "perception": made[-1]}


class WatchingRefine(CylinderPerception):
    """Its refinement (in its worker thread) waits up to MOTION_WAIT_S for the arm to move and
    records whether it did."""

    def __init__(self, config: Config, devices: Devices) -> None:
        super().__init__(config, devices)
        self.world = devices.world
        self.arm_moved_during_refine: list[bool] = []

    def refine(
        self, estimate: ShapeEstimate, outcomes: list[TouchOutcome], request: ExploreRequest
    ) -> ShapeEstimate:
        assert self.world is not None
        start = self.world.pose_world_tcp()
        deadline = time.monotonic() + MOTION_WAIT_S
        moved = False
        while not moved and time.monotonic() < deadline:
            time.sleep(0.01)
            moved = not np.allclose(self.world.pose_world_tcp(), start, atol=1e-6)
        self.arm_moved_during_refine.append(moved)
        return super().refine(estimate, outcomes, request)


@pytest.mark.parametrize("overlap", [True, False])
async def test_the_arm_moves_to_the_next_target_while_the_shape_is_refined(
    tmp_path: Path, overlap: bool
) -> None:
    result = await explore(config(refine_while_moving=overlap), WatchingRefine, tmp_path)
    summary = result["summary"]
    assert summary["state"] == "done" and summary["touches"] == 2, summary["error"]
    moved = result["perception"].arm_moved_during_refine
    # The last refinement has no next target to move to: the session waits for it.
    assert moved == ([True, False] if overlap else [False, False])
    # The refined shape is the session's: scored after the vision estimate and each touch.
    assert len(summary["metrics"]["chamfer_mm"]) == 3


class MarkedRefine(CylinderPerception):
    """Its refined estimate has a marker voxel in the grid's corner."""

    def refine(
        self, estimate: ShapeEstimate, outcomes: list[TouchOutcome], request: ExploreRequest
    ) -> ShapeEstimate:
        refined = super().refine(estimate, outcomes, request)
        probabilities = refined.probabilities.copy()
        probabilities[0, 0, -1] = 1.0
        return ShapeEstimate(refined.grid, probabilities)


async def test_the_approach_is_checked_against_the_refined_estimate(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The planner refuses every touch once the obstacles hold the refined estimate's marker:
    the second target, chosen and reached while the first touch was being refined, is dropped
    at its approach start before the pad goes in."""
    check_touch = MotionPlanner.check_touch

    def refusing(
        self: MotionPlanner,
        target_world: np.ndarray,
        direction_world: np.ndarray,
        joints: np.ndarray,
        obstacles: Obstacles,
        **kwargs: object,
    ) -> float:
        if marked(obstacles):
            raise SafetyViolation("refused by the test: the refined estimate is in the way")
        return check_touch(self, target_world, direction_world, joints, obstacles, **kwargs)

    def marked(obstacles: Obstacles) -> bool:
        return bool(np.any(np.all(np.isclose(obstacles.occupied_points_world, marker[0]), axis=1)))

    marker: list[np.ndarray] = [np.full(3, np.nan)]
    monkeypatch.setattr(MotionPlanner, "check_touch", refusing)

    class Marked(MarkedRefine):
        def __init__(self, config: Config, devices: Devices) -> None:
            super().__init__(config, devices)
            marker[0] = self.grid.voxel_centres_world()[0, 0, -1]

    result = await explore(config(), Marked, tmp_path)
    summary = result["summary"]
    assert summary["state"] == "done" and summary["touches"] == 1, summary
    refused = [s for s in summary["skipped_targets"] if "refused by the test" in s["reason"]]
    assert refused and refused[0]["stage"] == "approach" and refused[0]["touch"] == 2
