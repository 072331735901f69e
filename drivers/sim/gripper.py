"""Simulated WSG 50 gripper carrying the GelSight finger.

Opening pushes the gel pad (outward on the +x finger) toward whatever is in front of it. The gel
force comes from the tactile simulation's elastic model; the fingers stop ("blocked") when that
force reaches the commanded force limit, when the gel bottoms out on its rigid backing, or when
any rigid part of the tool runs into the object or the table (then the motor stalls at the force
limit). Motion runs at constant speed in simulated time and can be stopped or cancelled.

Planning where a move stops (tens to hundreds of milliseconds of ray casts and gel simulation)
and the gel force of ``state`` run in worker threads, from the TCP pose read before the hop;
the opening is changed on the event loop only (see ``SimWorld``).
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from drivers.base import (
    DeviceNotConnectedError,
    DeviceTimeoutError,
    Gripper,
    GripperState,
    MotionRejectedError,
)
from drivers.config import GripperConfig
from drivers.sim.world import SimWorld
from models.geometry import transform_points
from models.tactile.sim import GelSightSimulator

SWEEP_STEP_M = 0.0005
"""Finger travel between collision checks; a blocking contact is then refined by bisection."""
CONTACT_TOLERANCE_M = 1e-5
"""Bisection tolerance on the finger opening where the force limit is reached."""
UPDATE_PERIOD_S = 0.01
"""Simulated time between position updates while moving (the WSG streams at up to 100 Hz)."""
PRECHECK_GRID = (24, 18)
"""Rays per pad side used to find how far the pad is from the nearest surface."""


@dataclass(frozen=True)
class _Stop:
    width_m: float
    blocked: bool
    rigid: bool
    """Stopped by a rigid part (or the gel on its backing): the motor stalls at its limit."""


class SimWSG50(Gripper):
    """A WSG 50 with 0..stroke finger opening, speed and force limits, and force readback."""

    def __init__(self, world: SimWorld, config: GripperConfig, gel: GelSightSimulator) -> None:
        self.world = world
        self.config = config
        self.gel = gel
        self._connected = False
        self._referenced = False
        self._moving = False
        self._blocked = False
        self._stall_force_n: float | None = None  # set while stalled against a rigid contact
        self._stop_requested = asyncio.Event()

    # --- lifecycle ------------------------------------------------------------------------------

    async def connect(self) -> None:
        self._connected = True

    async def close(self) -> None:
        if self._connected:
            await self.stop()
        self._connected = False

    @property
    def is_connected(self) -> bool:
        return self._connected

    # --- commands -------------------------------------------------------------------------------

    async def home(self, *, timeout_s: float = 10.0, opening: bool = True) -> None:
        """Reference by opening fully, as the WSG 50 homes toward its outer end stop by default;
        ``opening=False`` homes toward the closed end (a setting on the real gripper)."""
        self._require_connected()
        self._referenced = True
        state = await self.move(
            self.config.stroke_m if opening else 0.0,
            speed_m_s=0.1,
            force_limit_n=self.config.max_force_n,
            timeout_s=timeout_s,
        )
        if state.blocked:
            self._referenced = False
            raise MotionRejectedError(
                f"homing blocked at {state.width_m * 1e3:.1f} mm: clear the fingers first"
            )

    async def move(
        self, width_m: float, *, speed_m_s: float, force_limit_n: float, timeout_s: float
    ) -> GripperState:
        self._require_connected()
        if not self._referenced:
            raise MotionRejectedError("gripper is not referenced: call home() first")
        if self._moving:
            raise MotionRejectedError("gripper is busy with another motion")
        if not (math.isfinite(width_m) and 0.0 <= width_m <= self.config.stroke_m):
            raise MotionRejectedError(
                f"width {width_m} m outside the stroke 0..{self.config.stroke_m} m"
            )
        if not 0.0 < speed_m_s <= self.config.max_speed_m_s:
            raise MotionRejectedError(f"speed {speed_m_s} m/s outside (0, max_speed_m_s]")
        if not 0.0 < force_limit_n <= self.config.max_force_n:
            raise MotionRejectedError(f"force limit {force_limit_n} N outside (0, max_force_n]")

        # Busy from here: planning awaits a worker thread, and a stop() meanwhile counts.
        self._stop_requested.clear()
        self._moving = True
        try:
            start_m = self.world.gripper_width_m
            stop = await self.world.compute(
                self._plan, self.world.pose_world_tcp(), start_m, width_m, force_limit_n
            )
            duration_s = abs(stop.width_m - start_m) / speed_m_s
            if duration_s > timeout_s:
                raise DeviceTimeoutError(
                    f"gripper move of {abs(stop.width_m - start_m) * 1e3:.1f} mm at"
                    f" {speed_m_s} m/s takes {duration_s:.2f} s, over the {timeout_s} s timeout"
                )
            self._blocked = False
            self._stall_force_n = None
            elapsed_s = 0.0
            while elapsed_s < duration_s:
                if self._stop_requested.is_set():
                    break
                step_s = min(UPDATE_PERIOD_S, duration_s - elapsed_s)
                await self.world.clock.advance(step_s)
                elapsed_s += step_s
                fraction = elapsed_s / duration_s
                self.world.gripper_width_m = start_m + fraction * (stop.width_m - start_m)
            else:
                self.world.gripper_width_m = stop.width_m
                self._blocked = stop.blocked
                self._stall_force_n = force_limit_n if stop.rigid else None
        finally:
            self._moving = False
        return await self.state()

    async def stop(self) -> None:
        self._stop_requested.set()

    async def state(self) -> GripperState:
        self._require_connected()
        # All read before the force's worker thread: the state is of one instant.
        width, pose_world_tcp = self.world.gripper_width_m, self.world.pose_world_tcp()
        moving, blocked, now_s = self._moving, self._blocked, self.world.clock.now_s
        force = self._stall_force_n
        if force is None:
            force = await self.world.compute(self._gel_force_n, pose_world_tcp, width)
        return GripperState(
            width_m=width, force_n=force, is_moving=moving, blocked=blocked, timestamp_s=now_s
        )

    # --- physics --------------------------------------------------------------------------------

    def _require_connected(self) -> None:
        if not self._connected:
            raise DeviceNotConnectedError("simulated gripper is not connected")

    def _gel_force_n(self, pose_world_tcp: NDArray[np.float64], width_m: float) -> float:
        # Polled often while the arm approaches: a few hundred rays say "nothing near" cheaply.
        if self._pad_gap_m(pose_world_tcp, width_m) > 0.0:
            return 0.0
        pose_world_pad = pose_world_tcp @ self.world.tool.pose_tcp_pad(width_m)
        indentation = self.gel.indentation_mm(self.world.scene_mesh_world, pose_world_pad)
        if self.gel.bottomed_out(indentation):
            return self.config.max_force_n  # pressed onto the rigid backing: the finger stalls
        return self.gel.contact_force_n(indentation)

    def _block_reason(
        self,
        pose_world_tcp: NDArray[np.float64],
        width_m: float,
        force_limit_n: float,
        *,
        gel: bool,
    ) -> str | None:
        """Why the fingers cannot be at this opening: "rigid" (a rigid tool part in the object
        or table, or the gel bottomed out on its backing), "force" (gel force at the limit), or
        None. ``gel=False`` skips the gel test where the pad cannot reach anything."""
        if self.world.tool_collision(pose_world_tcp, width_m) is not None:
            return "rigid"
        if not gel:
            return None
        pose_world_pad = pose_world_tcp @ self.world.tool.pose_tcp_pad(width_m)
        indentation = self.gel.indentation_mm(self.world.scene_mesh_world, pose_world_pad)
        if self.gel.bottomed_out(indentation):
            return "rigid"
        return "force" if self.gel.contact_force_n(indentation) >= force_limit_n else None

    def _plan(
        self,
        pose_world_tcp: NDArray[np.float64],
        start_m: float,
        target_m: float,
        force_limit_n: float,
    ) -> _Stop:
        """Where a move from start to target ends: sweep, then bisect the first blocking step.

        The world is static while the fingers move (the arm is not commanded meanwhile), so the
        stopping opening can be found before the motion is played out in simulated time.
        """
        gap_m = self._pad_gap_m(pose_world_tcp, start_m)
        steps = max(1, math.ceil(abs(target_m - start_m) / SWEEP_STEP_M))
        free_m = start_m
        for width_m in np.linspace(start_m, target_m, steps + 1)[1:]:
            # The pad advances half the change in opening; until it closes the gap to the
            # nearest surface only the rigid parts can collide (a cheap test).
            pad_reach = (width_m - start_m) / 2 >= gap_m - SWEEP_STEP_M
            reason = self._block_reason(pose_world_tcp, width_m, force_limit_n, gel=pad_reach)
            if reason is None:
                free_m = width_m
                continue
            blocked_m = width_m
            while abs(blocked_m - free_m) > CONTACT_TOLERANCE_M:
                middle_m = (free_m + blocked_m) / 2
                middle_reason = self._block_reason(
                    pose_world_tcp, middle_m, force_limit_n, gel=True
                )
                if middle_reason is None:
                    free_m = middle_m
                else:
                    blocked_m, reason = middle_m, middle_reason
            return _Stop(free_m, blocked=True, rigid=reason == "rigid")
        return _Stop(target_m, blocked=False, rigid=False)

    def _pad_gap_m(self, pose_world_tcp: NDArray[np.float64], width_m: float) -> float:
        """Distance from the undeformed gel to the nearest surface along the pad normal
        (0 if already touching, inf if nothing is in front)."""
        pose_world_pad = pose_world_tcp @ self.world.tool.pose_tcp_pad(width_m)
        spec = self.gel.spec
        backing_m = spec.gel_thickness_mm * 1e-3
        xs = np.linspace(-spec.width_mm / 2, spec.width_mm / 2, PRECHECK_GRID[0]) * 1e-3
        ys = np.linspace(-spec.height_mm / 2, spec.height_mm / 2, PRECHECK_GRID[1]) * 1e-3
        # Rays start on the rigid backing, so a surface already pressing into the gel is seen.
        grid = np.stack(np.meshgrid(xs, ys, [-backing_m], indexing="ij"), axis=-1).reshape(-1, 3)
        origins = transform_points(pose_world_pad, grid)
        normal = pose_world_pad[:3, 2]
        mesh = self.world.scene_mesh_world
        triangles, ray_ids, locations = mesh.ray.intersects_id(
            origins,
            np.broadcast_to(normal, origins.shape),
            multiple_hits=False,
            return_locations=True,
        )
        if len(ray_ids) == 0:
            return math.inf
        if np.any(mesh.face_normals[triangles] @ normal > 0):
            return 0.0  # a back face first: the backing itself is inside the object
        distances: NDArray[np.float64] = (locations - origins[ray_ids]) @ normal - backing_m
        # Coarse rays can pass between fine features: keep one sample spacing of margin.
        margin = max(xs[1] - xs[0], ys[1] - ys[0])
        return max(0.0, float(distances.min()) - margin)
