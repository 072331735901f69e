"""Touches on the simulated bench without arm motion, for the exploration benchmark.

The tool is placed so that the pad faces the target a little before it with the fingers nearly
closed; the fingers then open with the contact force limit, so the pad sweeps along the line
through the target and stops on contact or misses. Starts that are not clear back off along the
line; a target without a clear start is refused (docs/explore.md, "Simulated touch").
"""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine, Sequence
from typing import Any, TypeVar

import numpy as np
import trimesh
from numpy.typing import NDArray

from controller.config import Config
from controller.motion.poses import pad_pose_facing, tcp_pose_for_pad
from controller.perception.protocol import TouchMeasurement, TouchTarget
from drivers.base import RGBDFrame, TactileFrame
from drivers.sim.camera import SimKinect
from drivers.sim.gelsight import SimGelSight, gel_pad_spec
from drivers.sim.gripper import SimWSG50
from drivers.sim.world import SimWorld
from models.geometry import invert_transform, make_transform
from models.tactile.sim import GelSightSimulator

FloatArray = NDArray[np.float64]
T = TypeVar("T")

TOUCH_START_WIDTH_M = 0.002
"""Finger opening at the start of a sweep: nearly closed, so the pad travels most of the
stroke."""
START_STANDOFF_M = 0.025
"""Pad distance before the target where a sweep starts: clear of the surface, with most of the
travel left for past the target."""
START_BACKOFF_STEP_M = 0.005
"""How much further back the next start is tried when one is not clear."""
START_FREE_TRAVEL_M = 0.003
"""The pad must travel this far from the start before anything can stop it: the free rays of
a contact are pulled back (``free_pad_points``) and must stay in front of the start."""
MAX_START_STANDOFF_M = 0.045
"""The farthest start: from there the pad still sweeps past the target."""
STOP_PROBE_M = 0.0001
"""How much wider than where they stopped the fingers are tried to tell what stopped them."""
FREE_AIR_POSE_WORLD_TCP = make_transform(None, (0.0, 0.0, 0.5))
"""Where the gripper is homed and the GelSight reference taken: fingers up, far above the
object."""


class SimTouchBench:
    """The simulated bench with one object: its camera frame, and touches made by placing the
    tool directly and opening the fingers (module docstring). The simulated devices are driven
    through a private event loop, so the benchmark stays synchronous; call :meth:`close`."""

    def __init__(self, config: Config, object_mesh_world: trimesh.Trimesh, seed: int) -> None:
        self.config = config
        self.world = SimWorld(
            object_mesh_world,
            sim=config.sim,
            arm=config.robot.arm,
            gripper=config.gripper,
            sensor=config.sensor,
        )
        self._gel = GelSightSimulator(gel_pad_spec(config.sensor))
        self.gripper = SimWSG50(self.world, config.gripper, self._gel)
        self.gelsight = SimGelSight(self.world, self._gel, np.random.default_rng((seed, 1)))
        self.camera = SimKinect(self.world, config.cameras.rgbd, np.random.default_rng((seed, 2)))
        self._loop = asyncio.new_event_loop()
        self.reference = self._run(self._connect())

    def _run(self, coroutine: Coroutine[Any, Any, T]) -> T:
        return self._loop.run_until_complete(coroutine)

    async def _connect(self) -> TactileFrame:
        for device in (self.camera, self.gelsight, self.gripper):
            await device.connect()
        self._place_tool(FREE_AIR_POSE_WORLD_TCP, TOUCH_START_WIDTH_M)
        await self.gripper.home()
        return await self.gelsight.reference()

    def close(self) -> None:
        self._loop.close()

    def frame(self) -> RGBDFrame:
        """One bench Kinect frame (colour, noisy depth)."""
        return self._run(self.camera.read())

    def _place_tool(self, pose_world_tcp: FloatArray, width_m: float) -> None:
        world = self.world
        world.pose_base_flange = invert_transform(world.pose_world_base) @ pose_world_tcp
        world.gripper_width_m = width_m

    def approach_start(self, target: TouchTarget) -> FloatArray | None:
        """Pad pose (world, 4x4) where the sweep toward ``target`` starts, or None when no
        start within ``MAX_START_STANDOFF_M`` is clear."""
        for roll in dict.fromkeys((target.roll_rad, 0.0)):  # the target's roll, else none
            standoff = START_STANDOFF_M
            while standoff <= MAX_START_STANDOFF_M + 1e-9:
                pose_world_pad = pad_pose_facing(
                    target.target_world, -np.asarray(target.direction_world), standoff, roll
                )
                if self._clear(pose_world_pad):
                    return pose_world_pad
                standoff += START_BACKOFF_STEP_M
        return None

    def allowed(self, target: TouchTarget) -> bool:
        """The policy's feasibility callback: the bench can start a sweep toward ``target``."""
        return self.approach_start(target) is not None

    def _clear(self, pose_world_pad: FloatArray) -> bool:
        """No rigid tool part in the object or the table and the gel untouched, with the pad
        here and ``START_FREE_TRAVEL_M`` further on, and its centre outside a closed object."""
        world = self.world
        pose_world_tcp = tcp_pose_for_pad(pose_world_pad, world.tool, TOUCH_START_WIDTH_M)
        for width in (TOUCH_START_WIDTH_M, TOUCH_START_WIDTH_M + 2 * START_FREE_TRAVEL_M):
            if world.tool_collision(pose_world_tcp, width) is not None:
                return False
        mesh = world.object_mesh_world
        if mesh.is_watertight and mesh.contains(pose_world_pad[None, :3, 3])[0]:
            return False
        advanced = pose_world_pad.copy()
        advanced[:3, 3] += START_FREE_TRAVEL_M * pose_world_pad[:3, 2]
        indentation = self._gel.indentation_mm(world.scene_mesh_world, advanced)
        return not np.any(indentation > 0)

    def touch(self, target: TouchTarget, noise_seed: Sequence[int]) -> TouchMeasurement | None:
        """Sweep the pad through ``target`` along its direction; None if no start is clear.
        ``noise_seed`` seeds this touch's GelSight image noise."""
        start = self.approach_start(target)
        if start is None:
            return None
        self.gelsight.rng = np.random.default_rng(list(noise_seed))
        return self._run(self._sweep(target, start))

    def stopped_by(self, measurement: TouchMeasurement) -> str | None:
        """What stopped the fingers of ``measurement`` (the bench's touch just made): the
        rigid tool part that meets the object just beyond where they stopped
        (``"gelsight_window"``: the rigid window behind the gel, met through the gel pressed
        to its full depth or at its sides), ``"table"`` for any part meeting the table,
        ``"gel"`` for the gel's own force; None without a contact. Why a touch left no
        imprint, which a robot cannot tell (docs/explore.md)."""
        if not measurement.contact or measurement.gripper_width_m is None:
            return None
        world, width_m = self.world, measurement.gripper_width_m
        pose_world_tcp = tcp_pose_for_pad(measurement.pose_world_pad, world.tool, width_m)
        collision = world.tool_collision(pose_world_tcp, width_m + STOP_PROBE_M)
        if collision is None:
            return "gel"
        return "table" if collision.obstacle == "table" else collision.part

    async def _sweep(
        self, target: TouchTarget, pose_world_pad_start: FloatArray
    ) -> TouchMeasurement:
        config = self.config
        width = TOUCH_START_WIDTH_M
        self._place_tool(tcp_pose_for_pad(pose_world_pad_start, self.world.tool, width), width)
        speed = config.motion.finger_speed_m_s
        state = await self.gripper.move(
            config.gripper.stroke_m,
            speed_m_s=speed,
            force_limit_n=config.limits.contact_force_n,
            timeout_s=2.0 * config.gripper.stroke_m / speed + 1.0,
        )
        tactile = await self.gelsight.read()
        return TouchMeasurement(
            target=target,
            contact=state.blocked,
            tactile=tactile,
            reference=self.reference,
            pose_world_pad=self.world.pose_world_pad(),
            pad_start_world=pose_world_pad_start[:3, 3].copy(),
            force_n=state.force_n,
            gripper_width_m=state.width_m,
        )
