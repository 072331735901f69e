"""Simulated Kinect v2: the bench scene ray-cast by the project's one renderer."""

from __future__ import annotations

import numpy as np

from drivers.base import (
    DeviceNotConnectedError,
    RGBDCamera,
    RGBDFrame,
    depth_m_from_mm,
    depth_mm_from_m,
)
from drivers.config import CameraConfig
from drivers.sim.world import SimWorld
from models.camera import CameraIntrinsics
from models.render import RenderOutput, apply_kinect_depth_noise, render


class SimKinect(RGBDCamera):
    """Colour + registered metric depth of the bench, with ground-truth normals and silhouette.

    The scene is static (the arm is not drawn: it waits outside the view while capturing), so
    the noise-free frame is rendered once per connection and each ``read`` adds fresh depth
    noise, as consecutive frames of a real camera differ only by noise.
    """

    def __init__(self, world: SimWorld, config: CameraConfig, rng: np.random.Generator) -> None:
        self.world = world
        self.config = config
        self.rng = rng
        self.intrinsics = CameraIntrinsics.kinect_v2_colour(config.colour_scale)
        self.pose_world_camera = config.pose_world_camera()
        self._clean: RenderOutput | None = None

    async def connect(self) -> None:
        # Rendering takes tens of milliseconds: keep it off the event loop.
        self._clean = await self.world.compute(
            render,
            self.world.scene,
            self.intrinsics,
            self.pose_world_camera,
            background=self.config.background,
            rng=np.random.default_rng(self.world.sim_config.seed),
            transparent_objects=self.config.transparent_object,
        )

    async def close(self) -> None:
        self._clean = None

    @property
    def is_connected(self) -> bool:
        return self._clean is not None

    async def read(self, *, timeout_s: float = 2.0) -> RGBDFrame:
        if self._clean is None:
            raise DeviceNotConnectedError("simulated camera is not connected")
        # The depth noise takes tens of milliseconds: a worker thread's, not the loop's.
        return await self.world.compute(self._frame, self._clean, self.world.clock.now_s)

    def _frame(self, clean: RenderOutput, timestamp_s: float) -> RGBDFrame:
        depth = clean.depth_m
        if self.config.depth_noise:
            depth = apply_kinect_depth_noise(
                depth, clean.normals_camera, self.rng, intrinsics=self.intrinsics
            )
        return RGBDFrame(
            colour_rgb=clean.colour_rgb.copy(),
            # Whole millimetres, as the Kinect delivers them and the session files store them.
            depth_m=depth_m_from_mm(depth_mm_from_m(depth)),
            intrinsics=self.intrinsics,
            pose_world_camera=self.pose_world_camera.copy(),
            timestamp_s=timestamp_s,
            normals_camera=clean.normals_camera,
            silhouette=clean.silhouette,
        )
