"""The event loop stays responsive: ``status`` polled over real Zenoh through a whole session on
the simulated bench, with the in-process loop-lag monitor in the service. The devices simulate
their physics (collision checks, finger planning, gel forces and images, depth noise) and the
session records and publishes images and shapes: all of it off the loop."""

from __future__ import annotations

import asyncio
import dataclasses
import time
from pathlib import Path

from controller.benchmarks.service import status_during_session
from controller.config import Config
from controller.loop_monitor import LoopLagMonitor, percentile
from tests.fakes.perception import make_cylinder_perception

MAX_LOOP_CPU_LAG_S = 0.05
"""The loop's own work in one tick. A step that blocks the loop shows here in full (planning a
finger move took 80-500 ms on the loop, a GelSight reference 340 ms); waiting for a core on a
loaded machine does not."""
MAX_LAG_P99_S = 0.05
"""Wall-clock lag, 99th percentile, with a margin for a loaded 2-core machine (the benchmark's
bar is 25 ms)."""


async def test_monitor_sees_a_blocking_step_and_its_cpu_time() -> None:
    async with LoopLagMonitor(interval_s=0.002) as monitor:
        await asyncio.sleep(0.02)
        busy_until = time.thread_time() + 0.08
        while time.thread_time() < busy_until:  # the loop's own work: 80 ms of CPU time
            pass
        await asyncio.sleep(0.02)
        time.sleep(0.08)  # noqa: ASYNC251 - blocked without computing: lag, no CPU time
        await asyncio.sleep(0.02)
    assert max(monitor.lags_s) >= 0.075
    assert 0.07 <= max(monitor.cpu_lags_s) < 0.1
    slept = [
        cpu for lag, cpu in zip(monitor.lags_s, monitor.cpu_lags_s, strict=True) if lag >= 0.075
    ]
    assert min(slept) < 0.03  # the tick that waited out time.sleep saw no computing
    summary = monitor.summary()
    assert summary["over_20ms"] >= 2 and summary["max_ms"] >= 75
    assert summary["ticks"] == len(monitor.lags_s) > 10


def test_percentile_is_the_nearest_rank() -> None:
    values = [float(v) for v in range(1, 101)]
    assert percentile(values, 50) == 50.0
    assert percentile(values, 99) == 99.0
    assert percentile(values, 100) == 100.0
    assert percentile([3.0], 99) == 3.0
    assert percentile([], 99) == 0.0


async def test_status_polled_through_a_session_never_waits_for_a_blocked_loop(
    tmp_path: Path,
) -> None:
    config = Config()
    config = dataclasses.replace(config, sim=dataclasses.replace(config.sim, object="can"))
    result = await status_during_session(
        config, make_cylinder_perception, tmp_path, hz=50, touches=2
    )
    print(result)
    assert result["session"] == {"state": "done", "touches": 2, "error": None}
    assert result["polls"] >= 20 and result["unanswered"] == 0
    lag = result["loop_lag"]
    assert lag["ticks"] >= 100
    assert lag["cpu_lag_max_ms"] < MAX_LOOP_CPU_LAG_S * 1e3, lag
    assert lag["p99_ms"] < MAX_LAG_P99_S * 1e3, lag
