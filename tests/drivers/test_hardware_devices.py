"""Bring-up of the real gripper, GelSight and RGB-D camera; skipped unless --run-hardware.

On the robot: TOUCHSHAPE_HARDWARE_CONFIG=my_robot.toml pytest --run-hardware -k real_.
The gripper test homes the fingers and moves them 5 mm and back: keep them clear.
"""

from __future__ import annotations

import os

import pytest

from controller.cli.check import check_camera, check_gripper, check_tactile
from controller.config import Config, load_config


def hardware_config() -> Config:
    path = os.environ.get("TOUCHSHAPE_HARDWARE_CONFIG")
    if not path:
        pytest.skip("set TOUCHSHAPE_HARDWARE_CONFIG to the robot's config file")
    return load_config(path)


@pytest.mark.hardware
async def test_real_wsg50_bring_up() -> None:
    config = hardware_config().gripper
    lines: list[str] = []
    assert await check_gripper(config, motion_m=0.005, home=True, report=lines.append), lines


@pytest.mark.hardware
async def test_real_gelsight_bring_up() -> None:
    lines: list[str] = []
    assert await check_tactile(hardware_config().sensor, report=lines.append), lines


@pytest.mark.hardware
async def test_real_rgbd_camera_bring_up() -> None:
    lines: list[str] = []
    assert await check_camera(hardware_config().cameras.rgbd, report=lines.append), lines
