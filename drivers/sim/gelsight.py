"""Simulated GelSight: the pad's indentation at its current pose, imaged by the real optics
(in worker threads: a frame takes tens of milliseconds)."""

from __future__ import annotations

import numpy as np

from drivers.base import DeviceNotConnectedError, TactileFrame, TactileSensor
from drivers.config import SensorConfig
from drivers.sim.world import SimWorld
from models.tactile.sim import GelPadSpec, GelSightSimulator


def gel_pad_spec(config: SensorConfig) -> GelPadSpec:
    """The tactile simulation's pad description from the sensor config."""
    return GelPadSpec(
        width_mm=config.pad_width_mm,
        height_mm=config.pad_height_mm,
        image_width_px=config.image_width_px,
        image_height_px=config.image_height_px,
        gel_thickness_mm=config.gel_thickness_mm,
        max_indentation_mm=config.max_indentation_mm,
        youngs_modulus_mpa=config.youngs_modulus_mpa,
        noise_sigma=config.image_noise_sigma,
    )


class SimGelSight(TactileSensor):
    """Raw BGR frames of the simulated pad wherever the arm and gripper have put it."""

    def __init__(
        self, world: SimWorld, simulator: GelSightSimulator, rng: np.random.Generator
    ) -> None:
        self.world = world
        self.simulator = simulator
        self.rng = rng
        self._connected = False

    async def connect(self) -> None:
        self._connected = True

    async def close(self) -> None:
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    async def read(self, *, timeout_s: float = 1.0) -> TactileFrame:
        self._require_connected()
        pose_world_pad, now_s = self.world.pose_world_pad(), self.world.clock.now_s
        image = await self.world.compute(self._image, pose_world_pad)
        return TactileFrame(image_bgr=image, timestamp_s=now_s)

    async def reference(self, *, timeout_s: float = 5.0) -> TactileFrame:
        """The no-contact frame as a real sensor's reference: the mean of 10 noisy frames."""
        self._require_connected()
        now_s = self.world.clock.now_s
        # Ten renders take a few hundred milliseconds: a worker thread's, not the loop's.
        image = await self.world.compute(self._reference_image)
        return TactileFrame(image_bgr=image, timestamp_s=now_s)

    def _reference_image(self) -> np.ndarray:
        no_contact = np.zeros(self.simulator.spec.shape, dtype=np.float32)
        frames = [self.simulator.render_bgr(no_contact, self.rng) for _ in range(10)]
        return np.mean(frames, axis=0).round().astype(np.uint8)

    def _image(self, pose_world_pad: np.ndarray) -> np.ndarray:
        indentation = self.simulator.indentation_mm(self.world.scene_mesh_world, pose_world_pad)
        return self.simulator.render_bgr(indentation, self.rng)

    def _require_connected(self) -> None:
        if not self._connected:
            raise DeviceNotConnectedError("simulated GelSight is not connected")
