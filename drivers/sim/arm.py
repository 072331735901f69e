"""Simulated UR5: analytic kinematics, trapezoidal motion profiles and tool collisions, all
stepped in simulated time at the RTDE control rate.

Frames: poses named ``pose_base_*`` are in the robot base frame (ur_analytic_ik's UR5 base,
flange = tool0); the TCP is ``flange @ config.tcp_offset``. Contacts are checked on the tool
model attached to the flange (``SimWorld.tool_contact``) before each step is committed: a rigid
part pressed into the object or the table makes an elastic force, which ``state()`` reports as
the TCP force (``tcp_wrench_base``, as a UR's ``getActualTCPForce``), so the controller can feel
an unexpected contact and stop.

Behaviour of a running move:
- ``stop()`` from another task: the move returns normally at its next control step without
  reaching the target; ``state()`` shows the pose reached. The arm stops at once (no ramp down).
- Cancelling the awaiting task: the arm stops where it is and ``CancelledError`` propagates.
- ``close()``: the arm stops and the move raises ``DeviceNotConnectedError``.
- A contact whose force exceeds the sim config's ``protective_stop_force_n``: the arm stays at
  the last pose before it, enters protective stop and the move raises ``ProtectiveStopError``.
- Joint limits or a singularity (a joint would have to exceed ``max_joint_speed_rad_s``): the
  arm stays at the last valid pose, ``MotionRejectedError``.
- Simulated time past ``timeout_s``: the arm stops where it is, ``DeviceTimeoutError``.

Each step's forward kinematics and collision check (milliseconds, more near the object) run in
a worker thread on the joints and finger opening read before the hop; the step is committed to
the world on the event loop after it, so a cancelled move commits nothing more.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation, Slerp

from drivers.base import (
    Arm,
    ArmState,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    MotionRejectedError,
    ProtectiveStopError,
)
from drivers.config import ArmConfig
from drivers.sim.world import Collision, SimWorld
from drivers.ur5.kinematics import forward_kinematics, inverse_kinematics
from models.geometry import invert_transform, matrix_to_ur_pose, ur_pose_to_matrix

JOINT_LIMIT_RAD = 2.0 * np.pi
"""Every UR5 joint turns within +-2 pi."""
MAX_TOOL_SPEED_M_S = 1.0
MAX_TOOL_ACCELERATION_M_S2 = 5.0
MAX_TOOL_ROTATION_SPEED_RAD_S = 1.0
"""moveL bounds the tool's rotation by these, whatever the requested linear speed."""
MAX_TOOL_ROTATION_ACCELERATION_RAD_S2 = 5.0
MAX_JOINT_ACCELERATION_RAD_S2 = 40.0
PROTECTIVE_STOP_HOLD_S = 5.0
"""A UR refuses to unlock a protective stop earlier than this after it happened."""

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class _Trapezoid:
    """Trapezoidal profile of a path parameter s from 0 to 1 (triangular when the path is too
    short to reach the cruise speed). Speeds in 1/s, acceleration in 1/s^2."""

    acceleration: float
    peak_speed: float
    ramp_s: float
    duration_s: float

    @classmethod
    def fastest(
        cls, distances: ArrayLike, speed_limits: ArrayLike, acceleration_limits: ArrayLike
    ) -> _Trapezoid:
        """Fastest profile where each ``distances[i] * s`` keeps within its speed and
        acceleration limits (same units as the distance, per second and per second^2)."""
        distances = np.abs(np.asarray(distances, dtype=float))
        moving = distances > 0.0
        if not np.any(moving):
            return cls(0.0, 0.0, 0.0, 0.0)
        speed_limits = np.broadcast_to(speed_limits, distances.shape)[moving]
        acceleration_limits = np.broadcast_to(acceleration_limits, distances.shape)[moving]
        speed = float(np.min(speed_limits / distances[moving]))
        acceleration = float(np.min(acceleration_limits / distances[moving]))
        ramp_s = min(speed / acceleration, math.sqrt(1.0 / acceleration))
        peak_speed = acceleration * ramp_s
        cruise_s = (1.0 - acceleration * ramp_s**2) / peak_speed
        return cls(acceleration, peak_speed, ramp_s, 2.0 * ramp_s + cruise_s)

    def position(self, time_s: float) -> float:
        """Path parameter s at ``time_s`` after the start, clamped to [0, 1]."""
        t = min(max(time_s, 0.0), self.duration_s)
        if t < self.ramp_s:
            return 0.5 * self.acceleration * t**2
        if t < self.duration_s - self.ramp_s:
            return 0.5 * self.acceleration * self.ramp_s**2 + self.peak_speed * (t - self.ramp_s)
        return 1.0 - 0.5 * self.acceleration * (self.duration_s - t) ** 2


class SimUR5(Arm):
    """A UR5 moving the shared ``SimWorld``'s joints; see the module docstring for behaviour."""

    def __init__(self, world: SimWorld, config: ArmConfig) -> None:
        self._world = world
        self._config = config
        self._pose_flange_tcp = ur_pose_to_matrix(config.tcp_offset)
        self._pose_tcp_flange = invert_transform(self._pose_flange_tcp)
        self._connected = False
        self._moving = False
        self._stop_requested = False
        self._protective_stop_at_s: float | None = None
        self._contact_force_world_n = np.zeros(3)
        """The force the tool's rigid parts meet at the pose held (world frame)."""
        self._in_contact = False
        self.rigid_contacts: list[Collision] = []
        """Every rigid-part contact a move pressed on into (its first step), oldest first."""
        self.protective_stops: list[Collision] = []
        """Every collision that put the arm in protective stop, oldest first: a session that
        recovers from one leaves no other trace of it (the safety benchmark counts them)."""

    @property
    def is_connected(self) -> bool:
        return self._connected

    async def connect(self) -> None:
        """Read the flange pose from the world's joints (forward kinematics)."""
        self._world.pose_base_flange = forward_kinematics(self._world.joints_rad)
        self._connected = True

    async def close(self) -> None:
        """Disconnect; a running move stops at its next step and raises DeviceNotConnectedError."""
        self._connected = False

    async def stop(self) -> None:
        """End a running move at its next control step; a no-op when idle or disconnected."""
        self._stop_requested = True

    async def state(self) -> ArmState:
        self._require_connected()
        return ArmState(
            pose_base_tcp=matrix_to_ur_pose(self._world.pose_base_flange @ self._pose_flange_tcp),
            joints_rad=self._world.joints_rad.copy(),
            is_moving=self._moving,
            protective_stopped=self._protective_stop_at_s is not None,
            timestamp_s=self._world.clock.now_s,
            tcp_wrench_base=self.tcp_wrench_base(),
        )

    def tcp_wrench_base(self) -> FloatArray:
        """Force (N) and torque (N m) at the TCP, base frame: the rigid parts' contact force (the
        simulation computes no torque)."""
        rotation_world_base = self._world.pose_world_base[:3, :3]
        return np.concatenate([rotation_world_base.T @ self._contact_force_world_n, np.zeros(3)])

    async def recover_protective_stop(self, *, timeout_s: float = 30.0) -> None:
        """Wait (simulated time) until PROTECTIVE_STOP_HOLD_S after the stop, then unlock."""
        self._require_connected()
        if self._protective_stop_at_s is None:
            return
        hold_left_s = self._protective_stop_at_s + PROTECTIVE_STOP_HOLD_S - self._world.clock.now_s
        if hold_left_s > 0.0:
            await self._world.clock.advance(min(hold_left_s, timeout_s))
            if hold_left_s > timeout_s:
                raise DeviceTimeoutError(
                    f"protective stop can be unlocked only {PROTECTIVE_STOP_HOLD_S} s after it"
                    f" happened; {hold_left_s:.2f} s were left, timeout {timeout_s} s"
                )
        self._protective_stop_at_s = None

    async def move_linear(
        self,
        pose_base_tcp: NDArray[np.float64],
        *,
        speed_m_s: float,
        acceleration_m_s2: float,
        timeout_s: float,
    ) -> None:
        """Straight TCP line to a UR pose in the base frame; orientation slerped along it."""
        self._check_can_move()
        target = np.asarray(pose_base_tcp, dtype=float)
        if target.shape != (6,) or not np.all(np.isfinite(target)):
            raise MotionRejectedError(f"pose_base_tcp must be 6 finite values, got {target}")
        _check_limit("speed_m_s", speed_m_s, MAX_TOOL_SPEED_M_S)
        _check_limit("acceleration_m_s2", acceleration_m_s2, MAX_TOOL_ACCELERATION_M_S2)
        target_tcp = ur_pose_to_matrix(target)
        if inverse_kinematics(target_tcp @ self._pose_tcp_flange, self._world.joints_rad) is None:
            raise MotionRejectedError(f"pose {target} is unreachable")

        start_tcp = self._world.pose_base_flange @ self._pose_flange_tcp
        start_position, offset = start_tcp[:3, 3], target_tcp[:3, 3] - start_tcp[:3, 3]
        rotations = Rotation.from_matrix(np.stack([start_tcp[:3, :3], target_tcp[:3, :3]]))
        slerp = Slerp([0.0, 1.0], rotations)
        angle_rad = (rotations[0].inv() * rotations[1]).magnitude()
        profile = _Trapezoid.fastest(
            [np.linalg.norm(offset), angle_rad],
            [speed_m_s, MAX_TOOL_ROTATION_SPEED_RAD_S],
            [acceleration_m_s2, MAX_TOOL_ROTATION_ACCELERATION_RAD_S2],
        )

        def joints_at(time_s: float) -> FloatArray:
            s = profile.position(time_s)
            pose_tcp = np.eye(4)
            pose_tcp[:3, :3] = slerp(s).as_matrix()
            pose_tcp[:3, 3] = start_position + s * offset
            joints = inverse_kinematics(pose_tcp @ self._pose_tcp_flange, self._world.joints_rad)
            if joints is None:
                raise MotionRejectedError(f"no IK solution on the line at s={s:.4f} (singular)")
            return joints

        await self._run(joints_at, profile.duration_s, timeout_s)

    async def move_joints(
        self,
        joints_rad: NDArray[np.float64],
        *,
        speed_rad_s: float,
        acceleration_rad_s2: float,
        timeout_s: float,
    ) -> None:
        """Synchronised joint move: all joints start and arrive together (linear in joints)."""
        self._check_can_move()
        target = np.asarray(joints_rad, dtype=float)
        if target.shape != (6,) or not np.all(np.isfinite(target)):
            raise MotionRejectedError(f"joints_rad must be 6 finite values, got {target}")
        if np.any(np.abs(target) > JOINT_LIMIT_RAD):
            raise MotionRejectedError(f"joints_rad exceed the joint limits +-2 pi: {target}")
        _check_limit("speed_rad_s", speed_rad_s, self._config.max_joint_speed_rad_s)
        _check_limit("acceleration_rad_s2", acceleration_rad_s2, MAX_JOINT_ACCELERATION_RAD_S2)
        start = self._world.joints_rad.copy()
        profile = _Trapezoid.fastest(target - start, speed_rad_s, acceleration_rad_s2)
        await self._run(
            lambda time_s: start + profile.position(time_s) * (target - start),
            profile.duration_s,
            timeout_s,
        )

    async def follow(
        self, joints_at: Callable[[float], FloatArray], duration_s: float, *, timeout_s: float
    ) -> None:
        """Follow a joint trajectory: ``joints_at(t)`` gives the joints (rad) t seconds after
        the start, for ``duration_s``. Same checks, stop and cancellation as a move (the UR
        controller emulator runs speedL through this)."""
        self._check_can_move()
        await self._run(joints_at, duration_s, timeout_s)

    # --- stepping -------------------------------------------------------------------------------

    async def _run(
        self, joints_at: Callable[[float], FloatArray], duration_s: float, timeout_s: float
    ) -> None:
        """Step a move at the control rate in simulated time; ``joints_at(t)`` gives the joints
        commanded t seconds after the start. The last step may overshoot the duration (held)."""
        if not timeout_s > 0.0:
            raise MotionRejectedError(f"timeout_s must be positive, got {timeout_s}")
        period_s = 1.0 / self._config.control_frequency_hz
        self._moving = True
        self._stop_requested = False
        try:
            for step in range(1, math.ceil(duration_s / period_s - 1e-9) + 1):
                if self._stop_requested:
                    break
                if step * period_s > timeout_s:
                    raise DeviceTimeoutError(
                        f"move needs {duration_s:.3f} s, timeout_s is {timeout_s} s"
                    )
                await self._world.clock.advance(period_s)
                if not self._connected:
                    raise DeviceNotConnectedError("arm closed during a move")
                joints = joints_at(step * period_s)
                self._check_joint_step(joints, period_s)
                pose_base_flange, contact = await self._world.compute(
                    self._flange_and_contact, joints, self._world.gripper_width_m
                )
                if not self._connected:
                    raise DeviceNotConnectedError("arm closed during a move")
                force_world_n = np.zeros(3) if contact is None else np.array(contact.force_world_n)
                limit_n = self._world.sim_config.protective_stop_force_n
                if contact is not None and np.linalg.norm(force_world_n) > limit_n:
                    self._protective_stop_at_s = self._world.clock.now_s
                    self.protective_stops.append(contact)
                    raise ProtectiveStopError(
                        f"protective stop: {contact.part} hit the {contact.obstacle}"
                        f" ({np.linalg.norm(force_world_n):.0f} N over {limit_n:.0f} N)"
                    )
                if contact is not None and not self._in_contact:
                    self.rigid_contacts.append(contact)
                self._in_contact = contact is not None
                self._contact_force_world_n = force_world_n
                self._world.joints_rad = joints
                self._world.pose_base_flange = pose_base_flange
        finally:
            self._moving = False

    def _check_joint_step(self, joints: FloatArray, period_s: float) -> None:
        """A joint that would have to turn faster than its limit means a singularity on the
        path, or, when it is off by a full turn, that it would pass its +-2 pi limit (IK stays
        within it)."""
        max_step_rad = self._config.max_joint_speed_rad_s * period_s * (1.0 + 1e-9)
        step_rad = joints - self._world.joints_rad
        if np.any(np.abs(step_rad) > max_step_rad):
            joint = int(np.argmax(np.abs(step_rad)))
            wrapped_rad = (step_rad + np.pi) % (2.0 * np.pi) - np.pi
            if np.all(np.abs(wrapped_rad) <= max_step_rad):
                raise MotionRejectedError(f"joint {joint} would pass its limit +-2 pi")
            raise MotionRejectedError(
                f"joint {joint} would exceed {self._config.max_joint_speed_rad_s} rad/s"
                " (singularity on the path)"
            )

    def _flange_and_contact(
        self, joints: FloatArray, width_m: float
    ) -> tuple[FloatArray, Collision | None]:
        """The flange pose at ``joints`` and what the tool would press on there (run in a
        worker thread: reads only the world's fixed geometry)."""
        pose_base_flange = forward_kinematics(joints)
        pose_world_tcp = self._world.pose_world_base @ pose_base_flange
        return pose_base_flange, self._world.tool_contact(pose_world_tcp, width_m)

    # --- checks ---------------------------------------------------------------------------------

    def _require_connected(self) -> None:
        if not self._connected:
            raise DeviceNotConnectedError("SimUR5 is not connected")

    def _check_can_move(self) -> None:
        self._require_connected()
        if self._moving:
            raise MotionRejectedError("busy: the arm is already moving")
        if self._protective_stop_at_s is not None:
            raise ProtectiveStopError("in protective stop: call recover_protective_stop() first")


def _check_limit(name: str, value: float, maximum: float) -> None:
    if not 0.0 < value <= maximum:  # also False for NaN
        raise MotionRejectedError(f"{name} must be in (0, {maximum}], got {value}")
