"""The tool's geometry: where an object can first meet a finger as the fingers open."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.config import GripperConfig, SensorConfig
from drivers.tool import ToolModel


def test_the_leading_points_are_the_gel_housing_and_finger_then_the_other_finger() -> None:
    """Moving along the pad's +z, front first: the gel (z = 0, the pad), the housing's front
    10 mm behind it, the finger's front at the housing's back, a face keeping no point a face
    ahead of it covers. Moving along -z: the other finger's outer face, the opening and both
    fingers' thickness and the housing behind the gel."""
    gripper, sensor = GripperConfig(), SensorConfig()
    width_m = 0.03
    points, directions = ToolModel(gripper, sensor).leading_points_pad(width_m, 0.002)
    assert points.shape == directions.shape
    forward = directions[:, 2] > 0
    assert np.all(np.abs(directions[:, 2]) == 1.0)
    depths = sorted({round(z, 6) for z in points[forward, 2]}, reverse=True)
    assert depths == [0.0, -sensor.housing_recess_m, -sensor.housing_thickness_m]
    faces = [points[forward & np.isclose(points[:, 2], z)] for z in depths]
    half_pad = np.array([sensor.pad_width_mm, sensor.pad_height_mm]) * 1e-3 / 2
    assert np.all(np.abs(faces[0][:, :2]) <= half_pad + 1e-9)
    for index, face in enumerate(faces[1:], start=1):
        for ahead in faces[:index]:
            low, high = ahead[:, :2].min(axis=0), ahead[:, :2].max(axis=0)
            covered = np.all((face[:, :2] > low + 1e-9) & (face[:, :2] < high - 1e-9), axis=1)
            assert not covered.any()
    # The housing reaches past the pad's ends: its front is there around the gel.
    assert np.ptp(faces[1][:, 0]) == pytest.approx(sensor.housing_length_m)
    other = points[~forward]
    behind_m = width_m + 2 * gripper.finger_size_m[0] + sensor.housing_thickness_m
    np.testing.assert_allclose(other[:, 2], -behind_m)
    assert np.ptp(other[:, 0]) == pytest.approx(gripper.finger_size_m[2])
