"""An in-process event-loop lag monitor: how long the loop was kept from running ready work.

A ticker task sleeps ``interval_s`` and records how late it woke (the lag): a step that holds
the loop for 300 ms shows as one ~300 ms lag. Zenoh replies, abort requests and force readings
wait for the loop as long as that, so its lag bounds their extra latency.

A lag has two parts: the loop's own work (a blocking step: what code can fix) and waiting for a
core or for the GIL (a busy machine, other threads). Each tick also records the loop thread's
CPU time over the tick, which counts only the first: on a loaded machine a 5 ms step can wake
the ticker 50 ms late, but it still shows as ~5 ms of CPU time.
"""

from __future__ import annotations

import asyncio
import math
import time
from typing import Any


class LoopLagMonitor:
    """Measures the running loop's lag from ``start()`` to ``stop()`` (or as ``async with``)."""

    def __init__(self, interval_s: float = 0.005) -> None:
        self.interval_s = interval_s
        self.lags_s: list[float] = []
        """How late each tick woke (wall clock)."""
        self.cpu_lags_s: list[float] = []
        """The part of each lag the loop thread spent computing: its CPU time over the tick
        less the interval (at least 0; at most the lag, as CPU time cannot exceed wall time)."""
        self._task: asyncio.Task[None] | None = None

    async def __aenter__(self) -> LoopLagMonitor:
        self.start()
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.stop()

    def start(self) -> None:
        """Start ticking on the running loop (call from a coroutine)."""
        if self._task is None:
            self._task = asyncio.create_task(self._tick(), name="loop-lag-monitor")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
            self._task = None

    async def _tick(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            started, cpu_started = loop.time(), time.thread_time()  # this is the loop's thread
            await asyncio.sleep(self.interval_s)
            self.lags_s.append(max(0.0, loop.time() - started - self.interval_s))
            self.cpu_lags_s.append(max(0.0, time.thread_time() - cpu_started - self.interval_s))

    def summary(self) -> dict[str, Any]:
        """Tick count; p50 / p99 / max lag and how many ticks were over 20 ms late; the
        largest part of a lag that was the loop's own work. Milliseconds."""
        return {
            "interval_ms": self.interval_s * 1e3,
            "ticks": len(self.lags_s),
            "p50_ms": round(percentile(self.lags_s, 50) * 1e3, 2),
            "p99_ms": round(percentile(self.lags_s, 99) * 1e3, 2),
            "max_ms": round(max(self.lags_s, default=0.0) * 1e3, 2),
            "over_20ms": sum(lag > 0.020 for lag in self.lags_s),
            "cpu_lag_max_ms": round(max(self.cpu_lags_s, default=0.0) * 1e3, 2),
        }


def percentile(values: list[float], percent: float) -> float:
    """The value at or below which ``percent`` % of ``values`` lie (nearest rank; 0 if none)."""
    if not values:
        return 0.0
    ordered = sorted(values)
    return ordered[max(1, math.ceil(percent / 100 * len(ordered))) - 1]
