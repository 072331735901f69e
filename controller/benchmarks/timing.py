"""The benchmarks' one timer, and the description of the machine their figures come from."""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable
from typing import Any, ParamSpec, TypeVar

P = ParamSpec("P")
R = TypeVar("R")


class Stopwatch:
    """Wall-clock and CPU seconds of every call made through it, in call order.

    The CPU clock is this process's CPU time over all threads (``time.process_time``) unless
    another is given (``time.thread_time`` for code that runs on one thread). On a shared
    machine the wall clock includes the time spent waiting for a core, the CPU time does not.
    """

    def __init__(self, cpu_clock: Callable[[], float] = time.process_time) -> None:
        self.cpu_clock = cpu_clock
        self.wall_s: list[float] = []
        self.cpu_s: list[float] = []

    def __call__(self, function: Callable[P, R], *args: P.args, **kwargs: P.kwargs) -> R:
        """``function(*args, **kwargs)``, timed."""
        wall_start, cpu_start = time.perf_counter(), self.cpu_clock()
        try:
            return function(*args, **kwargs)
        finally:
            self.wall_s.append(time.perf_counter() - wall_start)
            self.cpu_s.append(self.cpu_clock() - cpu_start)

    def milliseconds(self) -> dict[str, float]:
        """Median, fastest and slowest wall-clock time of the calls, ms."""
        samples = [seconds * 1e3 for seconds in self.wall_s]
        return {
            "median_ms": round(statistics.median(samples), 3),
            "min_ms": round(min(samples), 3),
            "max_ms": round(max(samples), 3),
        }

    def medians(self) -> dict[str, float]:
        """Median wall-clock and CPU time of the calls, seconds."""
        return {"wall_s": statistics.median(self.wall_s), "cpu_s": statistics.median(self.cpu_s)}


def repeated(
    function: Callable[[], object],
    repeats: int,
    cpu_clock: Callable[[], float] = time.process_time,
) -> Stopwatch:
    """``repeats`` timed calls of ``function`` after one untimed warm-up call (caches, the
    allocator, lazy initialisation)."""
    function()
    stopwatch = Stopwatch(cpu_clock)
    for _ in range(repeats):
        stopwatch(function)
    return stopwatch


def machine(**extra: Any) -> dict[str, Any]:
    """The machine a benchmark ran on: its CPU count and processor, and ``extra`` entries."""
    return {
        "cpu_count": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
        **extra,
    }
