"""The latency function the exploration benchmark calls (no wall-clock assertions)."""

from __future__ import annotations

import json

import pytest
import torch

from controller.benchmarks import touch_latency as latency
from controller.benchmarks.touch_latency import touch_latency


def test_touch_latency_reports_select_and_refine_as_json(monkeypatch: pytest.MonkeyPatch) -> None:
    """The figures time the real work: every timed repeat (and the warm-up) selects a target
    and runs all the refinement's iterations, on the constraints of a simulated touch."""
    torch.manual_seed(0)
    weights = torch.randn(200, 16**3) * 0.05
    calls = {"decode": 0, "select": 0}

    def decode(latent: torch.Tensor) -> torch.Tensor:
        calls["decode"] += 1
        return torch.sigmoid(latent @ weights - 0.5).reshape(16, 16, 16)

    select_touch = latency.select_touch

    def counted_select(*args: object, **kwargs: object) -> object:
        calls["select"] += 1
        return select_touch(*args, **kwargs)

    monkeypatch.setattr(latency, "select_touch", counted_select)
    iterations, repeats = 2, 3
    report = touch_latency(16, decode, torch.randn(1, 200), iterations=iterations, repeats=repeats)
    json.dumps(report)
    assert report["resolution"] == 16 and report["refine_iterations"] == iterations
    assert set(report["select"]) == set(report["refine"]) == {"wall_s", "cpu_s"}
    # Warm-up + repeats timed selections, and one more for the touch's target.
    assert calls["select"] == 1 + repeats + 1
    # The volume once, then every Adam step of the warm-up and of each repeat.
    assert calls["decode"] >= 1 + (1 + repeats) * iterations
    constraints = report["constraint_voxels"]
    assert constraints["empty"] > 0 and constraints["occupied"] > 0
    calls["select"] = 0
    only_select = touch_latency(16, repeats=1)
    assert "refine" not in only_select and "constraint_voxels" not in only_select
    assert calls["select"] == 1 + 1 + 1
