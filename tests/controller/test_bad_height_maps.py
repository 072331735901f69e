"""A height map that cannot be a measurement (NaN, all zero under contact, wrong size) is refused
with a clear error, and the session goes on without that touch."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from controller.config import Config
from controller.perception.protocol import TouchMeasurement, TouchOutcome
from controller.request import ExploreRequest
from controller.service import TouchshapeService
from drivers.factory import Devices
from models.tactile.reconstruction import HeightMapError, check_height_map
from tests.fakes.perception import CylinderPerception

SHAPE = (240, 320)


def test_a_measured_height_map_passes() -> None:
    height = np.random.default_rng(0).uniform(0.0, 0.01, SHAPE)
    check_height_map(height, SHAPE, contact=True)
    check_height_map(np.zeros(SHAPE), SHAPE, contact=False)  # a miss: nothing pressed


@pytest.mark.parametrize(
    ("height", "contact", "message"),
    [
        (np.full(SHAPE, np.nan), True, "NaN"),
        (np.where(np.eye(*SHAPE) > 0, np.inf, 0.1), False, "NaN/inf"),
        (np.zeros(SHAPE), True, "all zero"),
        (np.ones((120, 160)), True, r"\(120, 160\)"),
    ],
)
def test_a_bad_height_map_is_refused(height: np.ndarray, contact: bool, message: str) -> None:
    with pytest.raises(HeightMapError, match=message):
        check_height_map(height, SHAPE, contact=contact)


class BadSecondTouch(CylinderPerception):
    """The cylinder perception, whose second touch's height map holds NaN: interpreted through
    the same check the learned perception applies."""

    def __init__(self, config: Config, devices: Devices) -> None:
        super().__init__(config, devices)
        self.interpreted = 0

    def interpret(self, measurement: TouchMeasurement) -> TouchOutcome:
        self.interpreted += 1
        height = np.full(measurement.tactile.image_bgr.shape[:2], 0.05)
        if self.interpreted == 2:
            height[10, 10] = np.nan
        check_height_map(height, measurement.tactile.image_bgr.shape[:2], contact=True)
        return super().interpret(measurement)


async def test_the_session_goes_on_without_a_refused_touch(tmp_path: Path) -> None:
    config = Config()
    config = dataclasses.replace(config, sim=dataclasses.replace(config.sim, object="can"))
    made: list[BadSecondTouch] = []

    def perception(config: Config, devices: Devices) -> BadSecondTouch:
        made.append(BadSecondTouch(config, devices))
        return made[-1]

    service = TouchshapeService(config, perception, logs_dir=tmp_path)
    published: list[tuple[str, dict]] = []
    await service.start()
    service._publish = lambda name, body: published.append((name, body))  # type: ignore[method-assign]
    try:
        service.start_session(ExploreRequest(max_touches=2))
        summary = await service.wait_session()
    finally:
        await service.stop()
    assert summary is not None and summary["state"] == "done", summary
    assert summary["touches"] == 2
    touches = [body for name, body in published if name == "touch"]
    assert [t["touch"] for t in touches] == [1, 2]
    assert "NaN" in touches[1]["error"] and "error" not in touches[0]
    # One touch was refined; the refused one (the last) left the shape as it was.
    states = [body["state"] for name, body in published if name == "state"]
    assert states.count("refine") == 1
    assert states[-2:] == ["done", "idle"]
