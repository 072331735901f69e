"""Where a session's wall-clock time goes: device motion versus the computer's own work."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass
class SessionTimes:
    """Where a session's wall-clock time goes. ``motion_s`` is the time spent awaiting the
    devices (arm and finger motions, camera and GelSight reads, state queries); ``compute_s``
    is all the rest of the session's own path: perception, planning, recording, publishing -
    the time the robot waits for the computer. Work taken off that path (the simulation's
    ground-truth scores) is not in it. Per touch: from the end of one refinement (or of the
    reconstruction) to the end of the next refinement. On the simulated bench ``sim_clock``
    reads the simulation's clock: ``per_touch_sim_s`` is the simulated time the devices took
    (at real-time factor 1, what a real robot would take; ``motion_s`` also holds the
    simulator's own computing)."""

    sim_clock: Callable[[], float] | None = None
    compute_s: float = 0.0
    motion_s: float = 0.0
    per_touch_compute_s: list[float] = field(default_factory=list)
    per_touch_motion_s: list[float] = field(default_factory=list)
    per_touch_sim_s: list[float] = field(default_factory=list)
    _marks: list[tuple[float, float, float]] = field(default_factory=list)

    def start(self) -> None:
        self._marks = [(time.perf_counter(), self.motion_s, self._sim_now())]

    def mark(self, *, touch: bool = True) -> None:
        """Close a stretch of the session's accounting (a touch's when ``touch``) and open the
        next one."""
        now, sim_now = time.perf_counter(), self._sim_now()
        started, motion_before, sim_before = self._marks[-1]
        motion = self.motion_s - motion_before
        compute = now - started - motion
        self.compute_s += compute
        if touch:
            self.per_touch_compute_s.append(round(compute, 3))
            self.per_touch_motion_s.append(round(motion, 3))
            if self.sim_clock is not None:
                self.per_touch_sim_s.append(round(sim_now - sim_before, 3))
        self._marks.append((now, self.motion_s, sim_now))

    def summary(self) -> dict[str, float | list[float]]:
        """The figures a session's summary reports (``per_touch_sim_s`` on the bench only)."""
        figures: dict[str, float | list[float]] = {
            "compute_s": round(self.compute_s, 3),
            "motion_s": round(self.motion_s, 3),
            "per_touch_compute_s": self.per_touch_compute_s,
            "per_touch_motion_s": self.per_touch_motion_s,
        }
        if self.sim_clock is not None:
            figures["per_touch_sim_s"] = self.per_touch_sim_s
        return figures

    def _sim_now(self) -> float:
        return self.sim_clock() if self.sim_clock is not None else 0.0
