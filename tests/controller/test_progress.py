"""The explore progress: one line per touch, in touch order, each with its score when the bench
scores estimates (scores come from the background, maybe late or out of order)."""

from __future__ import annotations

import io
from types import SimpleNamespace

import numpy as np

from controller.cli.progress import TouchProgress, print_summary
from controller.perception.protocol import contact_counts


def _touch(number: int, points: int = 100) -> dict:
    return {"touch": number, "contact": True, "contact_points": points, "force_n": 5.0}


def test_lines_wait_for_their_scores_and_keep_touch_order() -> None:
    out = io.StringIO()
    progress = TouchProgress(3, scored=True, out=out)
    progress("state", {"state": "select", "previous": "reconstruct"})
    progress("touch", _touch(1))
    progress("score", {"touch": 1, "chamfer_mm": 5.5})  # before vision's: waits for it
    assert out.getvalue() == ""
    progress("score", {"touch": 0, "chamfer_mm": 6.0})
    progress("touch", {"touch": 2, "contact": False, "error": "refused: no height map"})
    progress("touch", _touch(3, points=0))
    progress("state", {"state": "fault", "detail": "arm: protective stop"})
    progress.finish()  # touch 3's score never came
    lines = out.getvalue().splitlines()
    assert [line.split()[0] for line in lines] == ["vision", "touch", "touch", "fault:", "touch"]
    assert lines[0].endswith("Chamfer  6.00 mm")
    assert lines[1].startswith("touch 1/3") and lines[1].endswith("Chamfer  5.50 mm")
    assert "100 points" in lines[1] and "force  5.0 N" in lines[1]
    assert lines[2].startswith("touch 2/3  refused") and "Chamfer" not in lines[2]
    assert lines[3] == "fault: arm: protective stop"
    assert lines[4].startswith("touch 3/3") and "    0 points" in lines[4]


def test_without_scores_a_touch_prints_at_once() -> None:
    out = io.StringIO()
    progress = TouchProgress(10, scored=False, out=out)
    progress("state", {"state": "select", "previous": "reconstruct"})
    progress("touch", _touch(1))
    assert out.getvalue().splitlines()[1].startswith("touch  1/10  touched   contact yes")


def test_the_summary_shows_the_object_size_vision_final_and_true() -> None:
    summary = {
        "session": "s",
        "state": "done",
        "touches": 2,
        "contacts": 1,
        "compute_s": 1.0,
        "motion_s": 9.0,
        "object_size_cm": {"vision": [7.9, 11.0, 9.4], "final": None, "true": [8.0, 11.6, 9.5]},
    }
    out = io.StringIO()
    print_summary(summary, out)
    (row,) = [line for line in out.getvalue().splitlines() if line.startswith("size cm (x y z)")]
    assert row.split(maxsplit=5)[-1] == "7.9 x 11.0 x 9.4 -> empty (true 8.0 x 11.6 x 9.5)"


def _outcome(contact: bool, points: int) -> SimpleNamespace:
    return SimpleNamespace(
        measurement=SimpleNamespace(contact=contact), contact_points_world=np.zeros((points, 3))
    )


def test_contacts_that_left_no_imprint_are_counted_and_shown() -> None:
    outcomes = [_outcome(True, 300), _outcome(True, 0), _outcome(False, 0), _outcome(True, 0)]
    counts = contact_counts(outcomes)
    assert counts == {"contacts": 3, "contacts_without_imprint": 2}
    summary = {"session": "s", "state": "done", "touches": 4, **counts}
    summary |= {"compute_s": 1.0, "motion_s": 9.0}
    out = io.StringIO()
    print_summary(summary, out)
    (row,) = [line for line in out.getvalue().splitlines() if line.startswith("touches")]
    assert row.split(maxsplit=1)[1] == "4 (3 contacts, 2 without an imprint)"
    summary |= contact_counts(outcomes[:1])  # every contact with an imprint: nothing to add
    out = io.StringIO()
    print_summary(summary, out)
    (row,) = [line for line in out.getvalue().splitlines() if line.startswith("touches")]
    assert row.split(maxsplit=1)[1] == "4 (1 contact)"


def test_on_the_simulated_bench_compute_is_shown_against_the_robots_simulated_time() -> None:
    """The simulator computes its motions faster than real time: the robot's time is the
    simulation's clock, summed over the touches as the compute is."""
    summary = {"session": "s", "state": "done", "touches": 2, "contacts": 2}
    summary |= {"compute_s": 5.0, "motion_s": 3.0, "per_touch_compute_s": [1.0, 2.0]}
    out = io.StringIO()
    print_summary(summary | {"per_touch_sim_s": [10.0, 20.0]}, out)
    (row,) = [line for line in out.getvalue().splitlines() if line.startswith("compute")]
    assert row == (
        "compute / robot  3.0 s / 30.0 s simulated over the touches (10%; 15.0 s a touch)"
    )
    out = io.StringIO()
    print_summary(summary, out)  # real devices: their wall time is the robot's
    (row,) = [line for line in out.getvalue().splitlines() if line.startswith("compute")]
    assert row == "compute / motion  5.0 s / 3.0 s"
