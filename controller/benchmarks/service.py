"""`touchshape bench service`: the service's own figures, measured through real Zenoh sessions.

- trigger-to-capture latency: a remote client's explore query until it receives the session's
  ``capture`` state publication (loopback);
- compute vs motion per touch at real-time factor 1: the session's wall time not spent
  awaiting the devices (perception, planning, recording, publishing: ``SessionTimes``) against
  the simulated time the devices took (arm and finger motions, camera and GelSight reads);
- memory growth: resident set size after each of N sessions in one service process (after a
  garbage collection, and after returning freed heap pages to the system: what stays is what
  the process holds);
- status latency during a session: a client in another process polls ``status`` at a fixed
  rate over Zenoh while one session runs; the reply times, and the event loop's lag from the
  in-process monitor (``controller.loop_monitor``).
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import dataclasses
import gc
import json
import os
import socket
import statistics
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from controller.benchmarks.status_poller import StatusPoller
from controller.benchmarks.timing import machine
from controller.config import Config, MessagingConfig
from controller.loop_monitor import LoopLagMonitor, percentile
from controller.messaging import zenoh_config
from controller.request import ExploreRequest
from controller.service import PerceptionFactory, TouchshapeService


def _release_free_memory() -> None:
    """Collect garbage and hand the C heap's free pages back to the system (glibc), so that
    the resident size shows what is held, not what the allocator keeps for reuse."""
    gc.collect()
    with contextlib.suppress(OSError, AttributeError):  # not glibc: free pages stay counted
        ctypes.CDLL("libc.so.6").malloc_trim(0)


def _rss_mb() -> float:
    """Current resident set size of this process (Linux /proc), MB."""
    with open("/proc/self/statm") as statm:
        pages = int(statm.read().split()[1])
    return pages * (4096 / 2**20)


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


async def _trigger_to_capture(
    config: Config, factory: PerceptionFactory, logs_dir: Path, trials: int
) -> list[float]:
    port = _free_port()
    served = dataclasses.replace(
        config, messaging=MessagingConfig(listen=(f"tcp/127.0.0.1:{port}",))
    )
    service = TouchshapeService(served, factory, logs_dir=logs_dir)
    stop, ready = asyncio.Event(), asyncio.Event()
    task = asyncio.create_task(service.serve(stop, ready))
    await asyncio.wait_for(ready.wait(), 120)
    client = await asyncio.to_thread(
        zenoh.open, zenoh_config(MessagingConfig(listen=(), connect=(f"tcp/127.0.0.1:{port}",)))
    )
    captured = threading.Event()
    captured_at: list[float] = []

    def on_state(sample: zenoh.Sample) -> None:
        if json.loads(sample.payload.to_string())["state"] == "capture":
            captured_at.append(time.perf_counter())
            captured.set()

    subscriber = client.declare_subscriber(f"touchshape/{config.robot.id}/state", on_state)
    latencies = []
    try:
        await asyncio.sleep(0.5)
        for _ in range(trials):
            captured.clear()
            sent = time.perf_counter()
            await asyncio.to_thread(
                lambda: list(
                    client.get(
                        f"touchshape/{config.robot.id}/explore",
                        payload=json.dumps({"max_touches": 1}),
                        timeout=5.0,
                    )
                )
            )
            await asyncio.to_thread(captured.wait, 10.0)
            latencies.append((captured_at[-1] - sent) * 1e3)
            await service.abort_session()
    finally:
        subscriber.undeclare()
        await asyncio.to_thread(client.close)
        stop.set()
        await task
    return latencies


async def status_during_session(
    config: Config, factory: PerceptionFactory, logs_dir: Path, *, hz: float, touches: int
) -> dict[str, Any]:
    """Serve on a loopback port, poll ``status`` at ``hz`` over Zenoh from another process
    while one explore request (sent from this one) runs, and measure the loop's lag in the
    service meanwhile."""
    port = _free_port()
    served = dataclasses.replace(
        config, messaging=MessagingConfig(listen=(f"tcp/127.0.0.1:{port}",))
    )
    service = TouchshapeService(served, factory, logs_dir=logs_dir)
    stop, ready = asyncio.Event(), asyncio.Event()
    task = asyncio.create_task(service.serve(stop, ready))
    await asyncio.wait_for(ready.wait(), 120)
    endpoint = f"tcp/127.0.0.1:{port}"
    prefix = f"touchshape/{config.robot.id}"
    client = await asyncio.to_thread(
        zenoh.open, zenoh_config(MessagingConfig(listen=(), connect=(endpoint,)))
    )
    poller = StatusPoller(endpoint, f"{prefix}/status", hz)
    load_before = os.getloadavg()
    try:
        await asyncio.to_thread(poller.start)
        async with LoopLagMonitor() as monitor:
            try:
                body = json.dumps({"max_touches": touches})
                await asyncio.to_thread(
                    lambda: list(client.get(f"{prefix}/explore", payload=body, timeout=5.0))
                )
                summary = await service.wait_session()
            finally:
                round_trips = await asyncio.to_thread(poller.stop)
    finally:
        await asyncio.to_thread(client.close)
        stop.set()
        await task
    if summary is None:
        raise RuntimeError("the explore request was not accepted: no session ran")
    replies = [ms for ms in round_trips if ms is not None]
    return {
        "hz": hz,
        "polls": len(round_trips),
        "unanswered": len(round_trips) - len(replies),
        "reply_ms": {
            "p50": round(percentile(replies, 50), 2),
            "p99": round(percentile(replies, 99), 2),
            "max": round(max(replies, default=0.0), 2),
            "over_100ms": sum(ms > 100.0 for ms in replies),
        },
        "loop_lag": monitor.summary(),
        "session": {key: summary[key] for key in ("state", "touches", "error")},
        "machine": machine(
            load_average_before=[round(load, 2) for load in load_before],
            load_average_after=[round(load, 2) for load in os.getloadavg()],
        ),
    }


async def _sessions(
    config: Config, factory: PerceptionFactory, logs_dir: Path, count: int, touches: int
) -> list[dict[str, Any]]:
    service = TouchshapeService(config, factory, logs_dir=logs_dir)
    await service.start()
    rows = []
    try:
        for _ in range(count):
            service.start_session(ExploreRequest(max_touches=touches))
            summary = await service.wait_session()
            assert summary is not None
            untrimmed = _rss_mb()
            _release_free_memory()
            rows.append(
                {**summary, "rss_mb": round(_rss_mb(), 1), "rss_untrimmed_mb": round(untrimmed, 1)}
            )
    finally:
        await service.stop()
    return rows


def _real_time_figures(summary: dict[str, Any]) -> dict[str, Any]:
    compute = summary["per_touch_compute_s"]
    simulated = summary.get("per_touch_sim_s") or summary["per_touch_motion_s"]
    ratios = [c / max(m, 1e-9) for c, m in zip(compute, simulated, strict=True)]
    return {
        "touches": summary["touches"],
        "state": summary["state"],
        "error": summary["error"],
        "compute_s": summary["compute_s"],
        "motion_s": summary["motion_s"],
        "per_touch_compute_s": compute,
        "per_touch_motion_s": summary["per_touch_motion_s"],
        "per_touch_sim_motion_s": simulated,
        "compute_over_motion": round(sum(compute) / max(sum(simulated), 1e-9), 3),
        "compute_over_motion_worst_touch": round(max(ratios), 3) if ratios else None,
    }


def benchmark_service(
    config: Config,
    factory: PerceptionFactory,
    logs_dir: Path,
    *,
    trials: int = 5,
    sessions: int = 20,
    touches: int = 3,
    status_hz: float = 50.0,
) -> dict[str, Any]:
    """All four figures (status latency unless ``status_hz`` is 0); sessions run on the
    simulated bench (rtf 1 for the timing session; the config's, 0 by default, for the status
    and memory sessions, so they finish in minutes)."""
    latencies = asyncio.run(_trigger_to_capture(config, factory, logs_dir, trials))
    status = None
    if status_hz > 0:
        status = asyncio.run(
            status_during_session(config, factory, logs_dir, hz=status_hz, touches=touches)
        )
    real_time = dataclasses.replace(
        config, sim=dataclasses.replace(config.sim, real_time_factor=1.0)
    )
    timed = asyncio.run(_sessions(real_time, factory, logs_dir, 1, touches))[0]
    series = asyncio.run(_sessions(config, factory, logs_dir, sessions, touches))
    rss = [row["rss_mb"] for row in series]
    return {
        "benchmark": "service",
        "trigger_to_capture_ms": {
            "median": round(statistics.median(latencies), 2),
            "max": round(max(latencies), 2),
            "trials": trials,
        },
        **({"status_during_session": status} if status is not None else {}),
        "real_time_session": _real_time_figures(timed),
        "memory": {
            "sessions": sessions,
            "touches_per_session": touches,
            "rss_mb_after_each": rss,
            "rss_untrimmed_mb_after_each": [row["rss_untrimmed_mb"] for row in series],
            "growth_mb_second_to_last": round(rss[-1] - rss[1], 1) if len(rss) > 1 else 0.0,
        },
    }
