"""Fault injection around real (simulated) devices: same interface, same code paths, plus a
fault on cue."""

from __future__ import annotations

from drivers.base import DeviceTimeoutError, Gripper, GripperState, RGBDCamera, RGBDFrame


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
