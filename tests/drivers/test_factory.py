"""The device factory: the simulated world exists only when some device is simulated, so a real
robot's sessions have no simulated object to be scored against."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from drivers.config import ArmConfig, CameraConfig, GripperConfig, SensorConfig, SimConfig
from drivers.factory import make_devices
from drivers.gelsight_camera import GelSightCamera
from drivers.rgbd.realsense import RealSenseCamera
from drivers.sim.arm import SimUR5
from drivers.ur5.rtde_arm import URRtdeArm
from drivers.wsg50.gripper import WSG50Gripper

REPO = Path(__file__).resolve().parents[2]
REAL = {
    "arm": ArmConfig(type="ur_rtde", host="127.0.0.2"),
    "gripper": GripperConfig(type="wsg50_tcp", host="127.0.0.1", tcp_port=1000),
    "sensor": SensorConfig(type="opencv", device="0"),
    "camera": CameraConfig(type="realsense"),
}
"""The real backends, pointed at the addresses the emulators serve (not connected here)."""


def test_real_devices_get_no_sim_world(rng: np.random.Generator) -> None:
    devices = make_devices(**REAL, sim=SimConfig(), rng=rng)
    assert devices.world is None
    assert isinstance(devices.arm, URRtdeArm) and isinstance(devices.gripper, WSG50Gripper)
    assert isinstance(devices.tactile, GelSightCamera)
    assert isinstance(devices.camera, RealSenseCamera)
    assert not any(device.is_connected for device in devices.all)


def test_real_devices_load_nothing_of_the_simulation() -> None:
    """Building the real devices imports no simulation module (no world, no gel optics)."""
    code = (
        "import sys, numpy as np\n"
        "from drivers.config import *\n"
        "from drivers.factory import make_devices\n"
        "make_devices(arm=ArmConfig(type='ur_rtde'), gripper=GripperConfig(type='wsg50_tcp'),\n"
        "    sensor=SensorConfig(type='opencv'), camera=CameraConfig(type='realsense'),\n"
        "    sim=SimConfig(), rng=np.random.default_rng(0))\n"
        "print(' '.join(m for m in sys.modules if m.startswith(('drivers.sim', 'models.tactile'))))"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True
    )
    assert result.stdout.split() == []


def test_one_simulated_device_brings_the_world_it_shares(rng: np.random.Generator) -> None:
    """A real arm with the simulated gripper, GelSight and camera: they share one world."""
    devices = make_devices(
        arm=REAL["arm"],
        gripper=GripperConfig(),
        sensor=SensorConfig(),
        camera=CameraConfig(),
        sim=SimConfig(object="can"),
        rng=rng,
    )
    assert devices.world is not None
    assert isinstance(devices.arm, URRtdeArm)
    sim_only = make_devices(
        arm=ArmConfig(), **{k: v for k, v in REAL.items() if k != "arm"}, sim=SimConfig(), rng=rng
    )
    assert sim_only.world is not None and isinstance(sim_only.arm, SimUR5)
    assert sim_only.arm._world is sim_only.world
