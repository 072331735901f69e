"""One line per touch while a session runs, and the summary table after it: what
``touchshape explore`` and ``touchshape replay`` print (log records go to the session's
``session.log``)."""

from __future__ import annotations

import sys
import threading
from pathlib import Path
from typing import Any, TextIO


class TouchProgress:
    """Turns the service's publications (``state``, ``touch``, ``score``) into one line per
    touch: touch n/N, its end state, contact (the gripper's force) and the surface points its
    height map gave, the force and, when the bench knows the truth, the Chamfer distance after
    it. With scores, a touch's line waits for its score (they come from
    the background, in order of the estimates); ``finish`` prints what is still waiting."""

    def __init__(self, max_touches: int, *, scored: bool, out: TextIO | None = None) -> None:
        self.max_touches = max_touches
        self.scored = scored
        self.out = out or sys.stdout
        self._lock = threading.Lock()
        self._waiting: dict[int, tuple[str, bool]] = {}
        """Lines by touch (0 = vision) not printed yet, and whether each waits for a score."""
        self._scores: dict[int, float] = {}

    def __call__(self, name: str, body: dict[str, Any]) -> None:
        with self._lock:
            if name == "state":
                self._on_state(body)
            elif name == "touch":
                self._on_touch(body)
            elif name == "score":
                self._scores[int(body["touch"])] = float(body["chamfer_mm"])
                self._print_ready()

    def _on_state(self, body: dict[str, Any]) -> None:
        state = str(body["state"])
        if state == "select" and body.get("previous") == "reconstruct":
            width = len(f"touch {self.max_touches}/{self.max_touches}  {'touched':<8}")
            self._queue(0, f"{'vision':<{width}}", self.scored)
        elif state in ("fault", "aborted"):
            self._print(f"{state}: {body.get('detail', '')}")

    def _on_touch(self, body: dict[str, Any]) -> None:
        touch = int(body["touch"])
        width = len(str(self.max_touches))
        head = f"touch {touch:>{width}}/{self.max_touches}"
        if "error" in body:  # refused: no estimate of its own, so no score to wait for
            line = f"{head}  refused   contact {_yes(body.get('contact'))}  {body['error']}"
            self._queue(touch, line, False)
            return
        line = (
            f"{head}  {'touched':<8}  contact {_yes(body['contact'])} "
            f"{int(body['contact_points']):5d} points  force {float(body['force_n']):4.1f} N"
        )
        self._queue(touch, line, self.scored)

    def _queue(self, touch: int, line: str, wants_score: bool) -> None:
        self._waiting[touch] = (line, wants_score)
        self._print_ready()

    def _print_ready(self) -> None:
        """The waiting lines, in touch order, up to the first whose score has not come."""
        while self._waiting:
            touch = min(self._waiting)
            line, wants_score = self._waiting[touch]
            if wants_score and touch not in self._scores:
                return
            del self._waiting[touch]
            score = f"  Chamfer {self._scores[touch]:5.2f} mm" if wants_score else ""
            self._print(line + score)

    def finish(self) -> None:
        """Print the lines whose scores never came (a fault ended the session)."""
        with self._lock:
            for touch in sorted(self._waiting):
                self._print(self._waiting[touch][0])
            self._waiting.clear()

    def _print(self, line: str) -> None:
        print(line, file=self.out, flush=True)


def _yes(value: Any) -> str:
    return "yes" if value else "no "


def _times_row(summary: dict[str, Any]) -> tuple[str, str]:
    """The time the robot waited for the computer against the time it moved. On the simulated
    bench, over the touches (as ``bench service``'s ``compute_over_motion``): the robot's time
    is the simulation's clock, what a real robot would take, not the wall time the simulator
    computed for."""
    simulated = summary.get("per_touch_sim_s")
    if not simulated:
        return "compute / motion", f"{summary['compute_s']:.1f} s / {summary['motion_s']:.1f} s"
    compute_s, robot_s = sum(summary["per_touch_compute_s"]), sum(simulated)
    return (
        "compute / robot",
        f"{compute_s:.1f} s / {robot_s:.1f} s simulated over the touches "
        f"({compute_s / robot_s:.0%}; {robot_s / len(simulated):.1f} s a touch)",
    )


def print_summary(summary: dict[str, Any], out: TextIO | None = None) -> None:
    """The session's summary as a two-column table: result, touches, times, scores, files."""
    artifacts = summary.get("artifacts", {})
    rows = [
        ("session", summary["session"]),
        ("result", summary["state"] + (f" ({summary['error']})" if summary.get("error") else "")),
        ("touches", _touches_row(summary)),
    ]
    if "replay_of" in summary:
        rows.append(("replay of", summary["replay_of"]))
    else:
        rows.append(_times_row(summary))
    vision = summary.get("vision")
    if vision:
        rows.append(("vision", f"{vision['input']} input, prior {vision['prior']}"))
    for metric, values in summary.get("metrics", {}).items():
        if values:
            rows.append((metric, " -> ".join(f"{v:.2f}" for v in (values[0], values[-1]))))
    sizes = summary.get("object_size_cm")
    if sizes:
        rows.append(("size cm (x y z)", _sizes_text(sizes)))
    if "summary" in artifacts:
        rows.append(("folder", str(_parent(artifacts["summary"]))))
    for name in ("picture", "recording"):
        if name in artifacts:
            rows.append((name, artifacts[name]))
    if "recording" in artifacts:
        rows.append(("review", f"touchshape review {summary['session']}"))
    width = max(len(name) for name, _ in rows)
    for name, value in rows:
        print(f"{name:<{width}}  {value}", file=out or sys.stdout)


def _sizes_text(sizes: dict[str, Any]) -> str:
    """'vision -> final (true ...)' of ``object_size_cm``, each as 'x x y x z'."""

    def box(extent: list[float] | None) -> str:
        return "empty" if extent is None else " x ".join(f"{v:.1f}" for v in extent)

    text = f"{box(sizes.get('vision'))} -> {box(sizes.get('final'))}"
    return text + (f" (true {box(sizes['true'])})" if "true" in sizes else "")


def _parent(path: str) -> str:
    return str(Path(path).parent) + "/"


def _touches_row(summary: dict[str, Any]) -> str:
    """``10 (10 contacts, 4 without an imprint)``; older summaries lack the imprint count."""
    contacts = summary["contacts"]
    row = f"{summary['touches']} ({contacts} contact{'' if contacts == 1 else 's'}"
    without_imprint = summary.get("contacts_without_imprint", 0)
    return row + (f", {without_imprint} without an imprint)" if without_imprint else ")")
