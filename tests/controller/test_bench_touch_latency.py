"""The latency function the exploration benchmark calls (no wall-clock assertions)."""

from __future__ import annotations

import json

import torch

from controller.benchmarks.touch_latency import touch_latency


def test_touch_latency_reports_select_and_refine_as_json() -> None:
    torch.manual_seed(0)
    weights = torch.randn(200, 16**3) * 0.05

    def decode(latent: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(latent @ weights - 0.5).reshape(16, 16, 16)

    report = touch_latency(16, decode, torch.randn(1, 200), iterations=2, repeats=1)
    json.dumps(report)
    assert report["resolution"] == 16 and report["refine_iterations"] == 2
    for step in ("select", "refine"):
        assert report[step]["wall_s"] > 0 and report[step]["cpu_s"] >= 0
    only_select = touch_latency(16, repeats=1)
    assert "refine" not in only_select and only_select["select"]["wall_s"] > 0
