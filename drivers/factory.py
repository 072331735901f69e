"""Build the four devices from their configs; simulated ones share one SimWorld, which exists
only when some device is simulated (a real robot's session has no ground truth to score)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from drivers.base import Arm, Gripper, RGBDCamera, TactileSensor
from drivers.config import ArmConfig, CameraConfig, GripperConfig, SensorConfig, SimConfig

if TYPE_CHECKING:
    from drivers.sim.world import SimWorld
    from models.tactile.sim import GelSightSimulator


@dataclass
class Devices:
    camera: RGBDCamera
    tactile: TactileSensor
    arm: Arm
    gripper: Gripper
    world: SimWorld | None
    """The simulated world when any device is simulated (ground truth for tests and benches);
    None when every device is real."""

    @property
    def all(self) -> tuple[RGBDCamera, TactileSensor, Arm, Gripper]:
        return (self.camera, self.tactile, self.arm, self.gripper)

    async def connect(self) -> None:
        """Connect every device; on failure close the ones already open, then re-raise."""
        opened = []
        try:
            for device in self.all:
                await device.connect()
                opened.append(device)
        except BaseException:
            for device in reversed(opened):
                await device.close()
            raise

    async def close(self) -> None:
        for device in reversed(self.all):
            await device.close()


def make_devices(
    *,
    arm: ArmConfig,
    gripper: GripperConfig,
    sensor: SensorConfig,
    camera: CameraConfig,
    sim: SimConfig,
    rng: np.random.Generator,
    max_object_extent_m: float | None = None,
) -> Devices:
    """Devices for a config; nothing is connected yet. The sim world (and the simulated gel,
    when the gripper or the GelSight is simulated) is built only for simulated devices; its
    object is refused (ShapeError) when larger than ``max_object_extent_m`` on a side."""
    world, gel = None, None
    if "sim" in (arm.type, gripper.type, sensor.type, camera.type):
        # Imported here so a real-robot install never loads the simulation's heavy pieces.
        from drivers.sim.world import SimWorld

        world = SimWorld.from_config(
            sim, arm, gripper, sensor, max_object_extent_m=max_object_extent_m
        )
    if "sim" in (gripper.type, sensor.type):
        from drivers.sim.gelsight import gel_pad_spec
        from models.tactile.sim import GelSightSimulator

        gel = GelSightSimulator(gel_pad_spec(sensor))
    return Devices(
        camera=_make_camera(camera, world, rng),
        tactile=_make_tactile(sensor, world, gel, rng),
        arm=_make_arm(arm, world),
        gripper=_make_gripper(gripper, world, gel),
        world=world,
    )


def _simulated(world: SimWorld | None) -> SimWorld:
    if world is None:
        raise ValueError("a simulated device needs the sim world")
    return world


def _make_arm(config: ArmConfig, world: SimWorld | None) -> Arm:
    if config.type == "ur_rtde":
        from drivers.ur5.rtde_arm import URRtdeArm

        return URRtdeArm(config)
    from drivers.sim.arm import SimUR5

    return SimUR5(_simulated(world), config)


# Real backends import their vendor SDK when built, so a missing optional extra only matters
# for the device that needs it.


def _make_gripper(
    config: GripperConfig, world: SimWorld | None, gel: GelSightSimulator | None
) -> Gripper:
    if config.type in ("wsg50_serial", "wsg50_tcp"):
        from drivers.wsg50.gripper import WSG50Gripper

        return WSG50Gripper(config)
    from drivers.sim.gripper import SimWSG50

    assert gel is not None
    return SimWSG50(_simulated(world), config, gel)


def _make_tactile(
    config: SensorConfig,
    world: SimWorld | None,
    gel: GelSightSimulator | None,
    rng: np.random.Generator,
) -> TactileSensor:
    if config.type == "opencv":
        from drivers.gelsight_camera import GelSightCamera

        return GelSightCamera(config)
    from drivers.sim.gelsight import SimGelSight

    assert gel is not None
    return SimGelSight(_simulated(world), gel, rng)


def _make_camera(
    config: CameraConfig, world: SimWorld | None, rng: np.random.Generator
) -> RGBDCamera:
    if config.type == "kinect_v2":
        from drivers.rgbd.kinect_v2 import KinectV2Camera

        return KinectV2Camera(config)
    if config.type == "realsense":
        from drivers.rgbd.realsense import RealSenseCamera

        return RealSenseCamera(config)
    from drivers.sim.camera import SimKinect

    return SimKinect(_simulated(world), config, rng)
