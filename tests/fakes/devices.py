"""Fault injection around real (simulated) devices: same interface, same code paths, plus a
fault on cue."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.base import DeviceTimeoutError, Gripper, GripperState, RGBDCamera, RGBDFrame
from drivers.factory import Devices
from models.geometry import ur_pose_to_matrix


@dataclass(frozen=True)
class ArmMove:
    """One ``move_linear`` the sim arm was given: where the TCP was when it began, where it
    was sent, where it was when the call ended, and the error that ended it (world frame)."""

    start_world: np.ndarray
    target_world: np.ndarray
    end_world: np.ndarray
    speed_m_s: float
    error: str | None


def record_arm_moves(devices: Devices) -> list[ArmMove]:
    """The path the simulated arm takes: every ``move_linear`` from now on, appended as it
    ends (the list is filled in place)."""
    world, arm = devices.world, devices.arm
    assert world is not None
    moves: list[ArmMove] = []
    inner = arm.move_linear

    async def move_linear(
        pose_base_tcp: np.ndarray, *, speed_m_s: float, acceleration_m_s2: float, timeout_s: float
    ) -> None:
        start = world.pose_world_tcp()
        target = world.pose_world_base @ ur_pose_to_matrix(pose_base_tcp)
        error = None
        try:
            await inner(
                pose_base_tcp,
                speed_m_s=speed_m_s,
                acceleration_m_s2=acceleration_m_s2,
                timeout_s=timeout_s,
            )
        except BaseException as exc:
            error = f"{type(exc).__name__}: {exc}"
            raise
        finally:
            moves.append(ArmMove(start, target, world.pose_world_tcp(), speed_m_s, error))

    arm.move_linear = move_linear  # type: ignore[method-assign]
    return moves


class TimingOutGripper(Gripper):
    """Delegates to a gripper but times out on the touch (the slow, force-limited opening)."""

    def __init__(self, inner: Gripper, touch_force_n: float) -> None:
        self.inner = inner
        self.touch_force_n = touch_force_n

    async def connect(self) -> None:
        await self.inner.connect()

    async def close(self) -> None:
        await self.inner.close()

    @property
    def is_connected(self) -> bool:
        return self.inner.is_connected

    async def home(self, *, timeout_s: float = 10.0) -> None:
        await self.inner.home(timeout_s=timeout_s)

    async def move(
        self, width_m: float, *, speed_m_s: float, force_limit_n: float, timeout_s: float
    ) -> GripperState:
        if force_limit_n == self.touch_force_n:
            raise DeviceTimeoutError("WSG 50 did not answer within the timeout")
        return await self.inner.move(
            width_m, speed_m_s=speed_m_s, force_limit_n=force_limit_n, timeout_s=timeout_s
        )

    async def stop(self) -> None:
        await self.inner.stop()

    async def state(self) -> GripperState:
        return await self.inner.state()


class StaleCamera(RGBDCamera):
    """A camera whose frames stopped arriving: reads fail as the real reader's max-age does."""

    def __init__(self, inner: RGBDCamera) -> None:
        self.inner = inner

    async def connect(self) -> None:
        await self.inner.connect()

    async def close(self) -> None:
        await self.inner.close()

    @property
    def is_connected(self) -> bool:
        return self.inner.is_connected

    async def read(self, *, timeout_s: float = 2.0) -> RGBDFrame:
        raise DeviceTimeoutError("newest colour frame is 5.2 s old (max age 0.5 s)")


def approach_start_world(moves: list[ArmMove], approach_speed_m_s: float) -> np.ndarray:
    """Where the first approach began: the start of the first move at the approach speed (the
    approach's small steps; transits run faster)."""
    slow = [m for m in moves if m.speed_m_s <= approach_speed_m_s]
    assert slow, "the arm never approached"
    return slow[0].start_world[:3, 3]


def assert_went_back_to(moves: list[ArmMove], final_world: np.ndarray, start: np.ndarray) -> None:
    """The path after an interrupted motion: a completed move back to where the motion started,
    and the arm ends there or straight above it (a lift only goes up)."""
    back = [m for m in moves if np.allclose(m.target_world[:3, 3], start, atol=1e-6)]
    assert back and back[-1].error is None, f"no move back to {np.round(start, 3)}"
    final = final_world[:3, 3]
    assert np.linalg.norm(final[:2] - start[:2]) < 0.001, (final, start)
    assert final[2] >= start[2] - 0.001, (final, start)
