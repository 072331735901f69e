"""Build the four devices from their configs; simulated ones share one SimWorld."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.base import Arm, DeviceConnectionError, Gripper, RGBDCamera, TactileSensor
from drivers.config import ArmConfig, CameraConfig, GripperConfig, SensorConfig, SimConfig
from drivers.sim.world import SimWorld


@dataclass
class Devices:
    camera: RGBDCamera
    tactile: TactileSensor
    arm: Arm
    gripper: Gripper
    world: SimWorld | None
    """The simulated world when any device is simulated (ground truth for tests and benches)."""

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
) -> Devices:
    """Devices for a config; nothing is connected yet."""
    # Imported here so a real-robot install never loads the simulation's heavy pieces.
    from drivers.sim.arm import SimUR5
    from drivers.sim.camera import SimKinect
    from drivers.sim.gelsight import SimGelSight, gel_pad_spec
    from drivers.sim.gripper import SimWSG50
    from models.tactile_sim import GelSightSimulator

    kinds = {"arm": arm.type, "gripper": gripper.type, "sensor": sensor.type, "camera": camera.type}
    real = {name: kind for name, kind in kinds.items() if kind != "sim"}
    if real:
        # TODO(#7): real UR5 (ur-rtde), WSG 50, GelSight camera and Kinect v2 backends.
        raise DeviceConnectionError(
            "real device backends are not available yet (issue #7): "
            + ", ".join(f"{name}.type = {kind!r}" for name, kind in real.items())
        )
    world = SimWorld.from_config(sim, arm, gripper, sensor)
    gel = GelSightSimulator(gel_pad_spec(sensor))
    return Devices(
        camera=SimKinect(world, camera, rng),
        tactile=SimGelSight(world, gel, rng),
        arm=SimUR5(world, arm),
        gripper=SimWSG50(world, gripper, gel),
        world=world,
    )
