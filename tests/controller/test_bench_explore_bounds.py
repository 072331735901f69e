"""Bounds of the exploration benchmark: ideal touches, the latent fit, the summary and the CLI."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import trimesh

from controller.benchmarks import explore_bounds
from controller.benchmarks.explore_bounds import (
    BoundsSettings,
    fit_latent_to_volume,
    ideal_targets,
    ideal_touch,
    ideal_touch_curve,
    run_bounds,
    summarise_bounds,
)
from controller.cli.main import main
from controller.config import Config
from controller.perception.learned import load_calibration
from models.geometry import make_transform
from models.prior.evaluation import EvalObject
from models.prior.shape_prior import ShapePrior

RADIUS_M = 0.05
CENTRE_M = np.array([0.0, 0.0, 0.06])
PAD_M = (0.019, 0.014)


@pytest.fixture(scope="module")
def sphere() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(4, RADIUS_M).apply_translation(CENTRE_M)


@pytest.fixture(scope="module")
def grid():
    return Config().voxel_grid.grid((0.6, 0.0, 0.4))


def signed_distance_m(grid, ijk: np.ndarray) -> np.ndarray:
    """Distance of voxel centres from the sphere's surface (negative inside)."""
    centres = grid.voxel_to_world(ijk + 0.5)
    return np.linalg.norm(centres - CENTRE_M, axis=1) - RADIUS_M


def test_an_ideal_touch_empties_the_front_and_fills_the_surface(sphere, grid) -> None:
    normal = np.array([0.6, 0.0, 0.8])
    touch = ideal_touch(sphere, grid, CENTRE_M + RADIUS_M * normal, normal, PAD_M)
    voxel = grid.voxel_size_m
    # A 19 x 14 mm pad on a 4 mm grid: tens of surface voxels, and the sweep in front of them.
    assert len(touch.occupied) > 10 and len(touch.empty) > 5 * len(touch.occupied)
    assert signed_distance_m(grid, touch.empty_ijk()).min() > -0.5 * voxel
    occupied = signed_distance_m(grid, touch.occupied_ijk())
    assert occupied.max() < 0.5 * voxel and occupied.min() > -1.5 * voxel


def test_ideal_targets_lie_on_the_surface_off_the_bottom(sphere) -> None:
    points, normals = ideal_targets(sphere, 20, seed=3)
    assert points.shape == normals.shape == (20, 3)
    assert np.allclose(np.linalg.norm(points - CENTRE_M, axis=1), RADIUS_M, atol=1e-3)
    assert np.all(points[:, 2] > 0.01) and np.all(normals[:, 2] > -0.5)
    longer, _ = ideal_targets(sphere, 50, seed=3)
    assert np.array_equal(points, longer[:20])  # a shorter run touches a longer one's first


def test_the_ideal_oracle_keeps_the_best_candidate_each_touch(sphere, grid, monkeypatch) -> None:
    # A stand-in error: the more occupied voxels the touches so far proved, the lower.
    monkeypatch.setattr(
        explore_bounds, "_chamfer_mm", lambda run, constraints: 1000.0 / len(constraints.occupied)
    )
    run = SimpleNamespace(
        mesh_world=sphere, grid=grid, vision=None, vision_metrics={"chamfer_mm": 9.0}
    )

    def refine(estimate, constraints):
        return SimpleNamespace(probabilities=constraints)

    curve, made = ideal_touch_curve(run, refine, PAD_M, 2, 3, seed=0)
    points, normals = ideal_targets(sphere, 6, seed=0)
    touches = [ideal_touch(sphere, grid, p, n, PAD_M) for p, n in zip(points, normals, strict=True)]
    first = max(touches[:3], key=lambda t: len(t.occupied))
    second = max(touches[3:], key=lambda t: len(first.merged(t).occupied))
    assert curve == [9.0, 1000.0 / len(first.occupied), 1000.0 / len(first.merged(second).occupied)]
    assert [len(t.occupied) for t in made] == [len(first.occupied), len(second.occupied)]


def test_the_latent_fit_matches_the_volume_better() -> None:
    torch.manual_seed(0)
    weights = torch.randn(4**3, 8)

    def decode(latent: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(weights @ latent).reshape(4, 4, 4)

    truth = (decode(torch.randn(8)) > 0.5).float()
    start = torch.zeros(8)

    def bce(latent: torch.Tensor) -> float:
        return float(torch.nn.functional.binary_cross_entropy(decode(latent), truth))

    fitted = fit_latent_to_volume(decode, start, truth, steps=200, learning_rate=0.05)
    assert not fitted.requires_grad
    assert bce(fitted) < 0.5 * bce(start)


def test_summary_means_the_per_object_changes() -> None:
    rows = [
        {"vision_mm": 10.0, "floor_mm": 2.0, "latent_fit_mm": 6.0, "ideal_touches_mm": [10.0, 9.0]},
        {"vision_mm": 4.0, "floor_mm": 2.0, "latent_fit_mm": 4.0, "ideal_touches_mm": [4.0, 2.0]},
    ]
    summary = summarise_bounds(rows, (1,))
    assert summary["vision_mm"] == 7.0 and summary["latent_fit_mm"] == 5.0
    assert summary["latent_fit_change_pct"] == pytest.approx(-20.0)  # mean of -40 % and 0 %
    assert summary["floor_change_pct"] == pytest.approx(-65.0)
    assert summary["ideal_touches"]["1"] == {"chamfer_mm": 5.5, "change_pct": -30.0}


def test_bounds_json_on_a_small_object() -> None:
    config = Config()
    box = trimesh.creation.box((0.06, 0.05, 0.08), transform=make_transform(None, (0, 0, 0.04)))
    result = run_bounds(
        config,
        [EvalObject("small_box", "file", box)],
        BoundsSettings(touch_counts=(2,), fit_steps=3, oracle_candidates=2),
        prior=ShapePrior.untrained("cpu"),
        calibration=load_calibration(config),
    )
    json.dumps(result, allow_nan=False)
    (row,) = result["objects"]
    assert row["name"] == "small_box" and len(row["ideal_touches_mm"]) == 3
    assert 0.0 < row["floor_mm"] < 4.0  # the true voxels, within a voxel of the true surface
    assert row["ideal_voxels_per_touch"]["occupied"] > 0
    assert len(row["ideal_oracle_touches_mm"]) == 3
    assert set(result["summary"]["ideal_touches"]) == {"2"}
    assert set(result["summary"]["ideal_oracle_touches"]) == {"2"}


def test_the_bounds_command_runs_the_bounds_as_asked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What the command line says is what the bounds get: the held-out objects, the touch
    counts, the prior, the workers and the JSON (the measurement is replaced by a recorder)."""
    import controller.cli.bench as bench_cli
    import controller.perception.learned as learned
    import models.prior.evaluation as evaluation

    calls: dict = {}

    def run(config: Config, objects: list, settings: object, **kwargs: object) -> dict:
        calls.update(objects=objects, settings=settings, **kwargs)
        return {"summary": {"objects": len(objects)}}

    monkeypatch.setattr(explore_bounds, "run_bounds", run)
    monkeypatch.setattr(evaluation, "held_out_objects", lambda categories, n: [(categories, n)])
    monkeypatch.setattr(bench_cli, "_load_prior", lambda config, name: f"prior {name}")
    monkeypatch.setattr(learned, "load_calibration", lambda config: "calibration")
    monkeypatch.setattr(torch, "set_num_threads", lambda n: calls.update(threads=n))
    out = tmp_path / "b.json"
    argv = ["bench", "explore-bounds", "--touches", "10", "30", "--workers", "2"]
    assert main([*argv, "--json", str(out), "--prior", "box"]) == 0
    assert calls["settings"] == BoundsSettings(touch_counts=(10, 30), prior="box")
    assert len(calls["objects"]) == 1 and calls["objects"][0][1] == 1  # one per category
    assert calls["prior"] == "prior box" and calls["calibration"] == "calibration"
    assert calls["workers"] == 2 and calls["threads"] == 1
    assert json.loads(out.read_text())["summary"] == {"objects": 1}
