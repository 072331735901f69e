"""Device interfaces shared by the simulated and the real drivers.

Every device is async: ``connect()``, idempotent ``close()``, ``is_connected``; every device that
moves has ``stop()``; every motion takes a keyword-only ``timeout_s``. Errors are typed so the
controller can tell a rejected command from a fault. Blocking SDK calls never run on the event
loop (real backends use threads or processes).
"""

from __future__ import annotations

import abc
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from models.camera import CameraIntrinsics


class DeviceError(Exception):
    """Base class of every driver error."""


class DeviceNotConnectedError(DeviceError):
    """A command was sent to a device that is not connected (or was closed)."""


class DeviceConnectionError(DeviceError):
    """The device could not be reached or the link dropped."""


class DeviceTimeoutError(DeviceError):
    """The device did not answer or finish in time."""


class MotionRejectedError(DeviceError):
    """A motion command was refused before moving: unreachable, out of limits, bad argument."""


class ProtectiveStopError(DeviceError):
    """The arm stopped itself (collision or safety limit) during a motion; recovery is needed."""


@dataclass(frozen=True)
class RGBDFrame:
    """One registered colour + depth frame.

    ``depth_m`` is z-depth along the colour camera's optical axis, 0.0 where the sensor gave no
    return. ``normals_camera`` and ``silhouette`` are ground truth that only a simulation has.
    """

    colour_rgb: NDArray[np.uint8]
    depth_m: NDArray[np.float32]
    intrinsics: CameraIntrinsics
    pose_world_camera: NDArray[np.float64]
    timestamp_s: float
    normals_camera: NDArray[np.float32] | None = None
    silhouette: NDArray[np.bool_] | None = None


def depth_mm_from_m(depth_m: NDArray[np.floating]) -> NDArray[np.uint16]:
    """Depth in whole millimetres (0 = no return), as RGB-D sensors deliver it and the session
    files store it (16-bit PNG)."""
    return np.clip(np.round(np.asarray(depth_m, dtype=np.float64) * 1000.0), 0, 65535).astype(
        np.uint16
    )


def depth_m_from_mm(depth_mm: NDArray[np.integer]) -> NDArray[np.float32]:
    """Metres from whole millimetres: the one conversion every camera driver and the session
    reader use, so a recorded frame reads back bit-exact."""
    return np.asarray(depth_mm).astype(np.float32) * np.float32(1e-3)


@dataclass(frozen=True)
class TactileFrame:
    """One raw GelSight image (BGR, as OpenCV and the real sensor give it)."""

    image_bgr: NDArray[np.uint8]
    timestamp_s: float


@dataclass(frozen=True)
class ArmState:
    """Arm readback: TCP pose in the robot base frame as a UR pose ``[x, y, z, rx, ry, rz]``."""

    pose_base_tcp: NDArray[np.float64]
    joints_rad: NDArray[np.float64]
    is_moving: bool
    protective_stopped: bool
    timestamp_s: float
    tcp_wrench_base: NDArray[np.float64] = field(default_factory=lambda: np.zeros(6))
    """Force (N) and torque (N m) at the TCP in the base frame, as the UR reports it
    (``getActualTCPForce``): what the tool meets. On a CB3 it is estimated from the joint
    currents, with an offset that drifts: compare it with a reading taken just before."""


@dataclass(frozen=True)
class GripperState:
    """Gripper readback. ``width_m`` is the opening between the fingers' inner faces."""

    width_m: float
    force_n: float
    is_moving: bool
    blocked: bool
    timestamp_s: float


class Device(abc.ABC):
    """Lifecycle shared by all devices."""

    @abc.abstractmethod
    async def connect(self) -> None:
        """Open the device; release anything partly opened if this fails."""

    @abc.abstractmethod
    async def close(self) -> None:
        """Release the device. Safe to call twice or after a failed connect."""

    @property
    @abc.abstractmethod
    def is_connected(self) -> bool: ...


class RGBDCamera(Device):
    @abc.abstractmethod
    async def read(self, *, timeout_s: float = 2.0) -> RGBDFrame:
        """The newest frame."""


class TactileSensor(Device):
    @abc.abstractmethod
    async def read(self, *, timeout_s: float = 1.0) -> TactileFrame:
        """The newest tactile image."""

    @abc.abstractmethod
    async def reference(self, *, timeout_s: float = 5.0) -> TactileFrame:
        """A no-contact reference image (what reconstruction subtracts)."""


class Arm(Device):
    @abc.abstractmethod
    async def move_linear(
        self,
        pose_base_tcp: NDArray[np.float64],
        *,
        speed_m_s: float,
        acceleration_m_s2: float,
        timeout_s: float,
    ) -> None:
        """Straight-line TCP motion to a UR pose in the base frame (moveL).

        Raises MotionRejectedError before moving, ProtectiveStopError if stopped on the way.
        Cancelling the awaiting task stops the arm.
        """

    @abc.abstractmethod
    async def move_joints(
        self,
        joints_rad: NDArray[np.float64],
        *,
        speed_rad_s: float,
        acceleration_rad_s2: float,
        timeout_s: float,
    ) -> None:
        """Joint-space motion (moveJ); same errors and cancellation as move_linear."""

    @abc.abstractmethod
    async def stop(self) -> None:
        """Decelerate to a stop now. Always allowed, also when not moving."""

    @abc.abstractmethod
    async def state(self) -> ArmState: ...

    @abc.abstractmethod
    async def recover_protective_stop(self, *, timeout_s: float = 30.0) -> None:
        """Unlock a protective stop so that motion can resume."""


class Gripper(Device):
    @abc.abstractmethod
    async def home(self, *, timeout_s: float = 10.0) -> None:
        """Reference the fingers (required once after power-up on a WSG 50)."""

    @abc.abstractmethod
    async def move(
        self, width_m: float, *, speed_m_s: float, force_limit_n: float, timeout_s: float
    ) -> GripperState:
        """Move the fingers to ``width_m``; stop early when the force reaches ``force_limit_n``.

        Returns the final state: ``blocked`` is True when the fingers stopped on force before
        reaching the width (for a touch: contact). Cancelling stops the fingers.
        """

    @abc.abstractmethod
    async def stop(self) -> None:
        """Stop the fingers now."""

    @abc.abstractmethod
    async def state(self) -> GripperState: ...
