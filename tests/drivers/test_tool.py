"""The tool's geometry: where an object can first meet the sensor's finger."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.config import GripperConfig, SensorConfig
from drivers.tool import ToolModel


def test_the_leading_points_are_the_gel_then_the_housing_then_the_finger() -> None:
    """Three faces facing the pad's +z, front first: the gel (z = 0, the pad), the housing's
    front 10 mm behind it, the finger's front at the housing's back; a face keeps no point that
    a face ahead of it covers."""
    sensor = SensorConfig()
    points = ToolModel(GripperConfig(), sensor).leading_points_pad(0.002)
    depths = sorted({round(z, 6) for z in points[:, 2]}, reverse=True)
    assert depths == [0.0, -sensor.housing_recess_m, -sensor.housing_thickness_m]
    faces = [points[np.isclose(points[:, 2], z)] for z in depths]
    half_pad = np.array([sensor.pad_width_mm, sensor.pad_height_mm]) * 1e-3 / 2
    assert np.all(np.abs(faces[0][:, :2]) <= half_pad + 1e-9)
    for index, face in enumerate(faces[1:], start=1):
        for ahead in faces[:index]:
            low, high = ahead[:, :2].min(axis=0), ahead[:, :2].max(axis=0)
            covered = np.all((face[:, :2] > low + 1e-9) & (face[:, :2] < high - 1e-9), axis=1)
            assert not covered.any()
    # The housing reaches past the pad's ends: its front is there around the gel.
    assert np.ptp(faces[1][:, 0]) == pytest.approx(sensor.housing_length_m)
