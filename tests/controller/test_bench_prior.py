"""The prior benchmark's latency of every committed prior and of the automatic choice."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from controller.benchmarks.prior import committed_prior_latency
from controller.cli.prior import evaluation_camera
from controller.config import Config
from models.prior.shape_prior import ShapePrior
from models.prior.training import save_weights


def test_every_prior_and_auto_are_timed_on_one_thread(tmp_path: Path) -> None:
    prior = ShapePrior.untrained("cpu")
    save_weights(prior.sketch_net, "sketch", "cpu", tmp_path / "sketch.pt")
    save_weights(prior.shape_net, "shape", "cpu", tmp_path / "shape.pt")
    entry = {"preset": "cpu", "sketch_weights": "sketch.pt", "shape_weights": "shape.pt"}
    priors = [
        {"name": "fixed", "grid_extent_m": 0.26, **entry},
        {"name": "fitted", "grid_extent_m": 0.26, "frame": "object", **entry},
    ]
    (tmp_path / "priors.json").write_text(json.dumps({"priors": priors}))
    threads = torch.get_num_threads()

    figures = committed_prior_latency(evaluation_camera(Config()), repeats=1, weights_dir=tmp_path)

    assert list(figures) == ["fixed", "fitted", "auto"]
    assert [figures[name]["frame"] for name in figures] == ["fixed", "object", "fixed+object"]
    for name, figure in figures.items():
        for mode in ("rgb_to_voxels", "rgbd_to_voxels"):
            assert figure[mode]["repeats"] == 1, name
            assert 0 < figure[mode]["min_ms"] <= figure[mode]["max_ms"], name
            assert figure[mode]["cpu_median_ms"] > 0, name
    assert torch.get_num_threads() == threads  # restored for the caller
