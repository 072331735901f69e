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
from controller.benchmarks.explore import ExploreSettings, ObjectRun
from controller.benchmarks.explore_bounds import (
    BoundsSettings,
    curve_start,
    fit_latent_to_volume,
    ideal_targets,
    ideal_touch,
    ideal_touch_curve,
    refiner,
    run_bounds,
    summarise_bounds,
)
from controller.cli.main import main
from controller.config import Config
from controller.perception.learned import load_calibration
from models.geometry import make_transform
from models.metrics import distance_to_mesh
from models.prior.evaluation import EvalObject
from models.prior.shape_prior import ShapePrior
from models.touch.constraints import constraints_from_touches, touch_constraints

RADIUS_M = 0.05
CENTRE_M = np.array([0.0, 0.0, 0.06])
PAD_M = (0.019, 0.014)


@pytest.fixture(scope="module")
def sphere() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(4, RADIUS_M).apply_translation(CENTRE_M)


@pytest.fixture(scope="module")
def grid():
    return Config().voxel_grid.grid((0.6, 0.0, 0.4))


@pytest.fixture(scope="module")
def calibration():
    return load_calibration(Config())


def small_box() -> EvalObject:
    box = trimesh.creation.box((0.06, 0.05, 0.08), transform=make_transform(None, (0, 0, 0.04)))
    return EvalObject("small_box", "file", box)


def signed_distance_m(grid, ijk: np.ndarray) -> np.ndarray:
    """Distance of voxel centres from the sphere's surface (negative inside)."""
    centres = grid.voxel_to_world(ijk + 0.5)
    return np.linalg.norm(centres - CENTRE_M, axis=1) - RADIUS_M


def test_an_ideal_touch_empties_the_front_and_fills_the_surface(sphere, grid) -> None:
    normal = np.array([0.6, 0.0, 0.8])
    result = ideal_touch(sphere, CENTRE_M + RADIUS_M * normal, normal, PAD_M)
    # World-frame rays: the hits end on the true surface, every ray starts in front of it.
    contacts = result.contact_points_world
    assert len(contacts) > 100  # a 19 x 14 mm pad, 1 mm apart: within 20 mm, all on a sphere
    assert np.allclose(np.linalg.norm(contacts - CENTRE_M, axis=1), RADIUS_M, atol=2e-4)
    assert np.all(np.linalg.norm(result.ray_starts_world - CENTRE_M, axis=1) > RADIUS_M)
    touch = touch_constraints(result, grid)
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


def test_the_ideal_oracle_keeps_the_best_candidate_each_touch(sphere, grid) -> None:
    # A stand-in refinement and error: the more occupied voxels the touches so far proved, the
    # lower. The curve refines with every touch so far and scores through run.metrics.
    def error(estimate: SimpleNamespace) -> dict:
        return {
            "chamfer_mm": 1000.0 / len(constraints_from_touches(estimate.touches, grid).occupied)
        }

    run = SimpleNamespace(mesh_world=sphere, grid=grid, metrics=error)

    def refine(estimate, touches):
        return SimpleNamespace(touches=list(touches))

    curve, made, estimate = ideal_touch_curve(run, refine, (None, 9.0), PAD_M, 2, 3, seed=0)
    points, normals = ideal_targets(sphere, 6, seed=0)
    touches = [ideal_touch(sphere, p, n, PAD_M) for p, n in zip(points, normals, strict=True)]
    first = max(touches[:3], key=lambda t: len(constraints_from_touches([t], grid).occupied))
    second = max(
        touches[3:], key=lambda t: len(constraints_from_touches([first, t], grid).occupied)
    )
    best = [constraints_from_touches(made[: n + 1], grid) for n in range(2)]
    assert curve == [9.0, 1000.0 / len(best[0].occupied), 1000.0 / len(best[1].occupied)]
    assert [t.contact_points_world.tolist() for t in made] == [
        t.contact_points_world.tolist() for t in (first, second)
    ]
    assert estimate.touches == made  # the same objects


def test_the_refiners_pass_all_touches_to_the_pipeline(sphere, grid) -> None:
    """Fused and global: the touches themselves, with their update's request; prior: their
    merged constraints."""
    calls: list = []
    perception = SimpleNamespace(
        refine_fused=lambda estimate, touches, request: calls.append((touches, request)),
        refine_with=lambda estimate, constraints, request: calls.append((constraints, request)),
    )
    run = SimpleNamespace(grid=grid, request=lambda policy, update: (policy, update))
    points, normals = ideal_targets(sphere, 2, seed=1)
    touches = [ideal_touch(sphere, p, n, PAD_M) for p, n in zip(points, normals, strict=True)]
    refiner(run, perception, "global")("vision", touches)
    refiner(run, perception, "fused")("vision", touches)
    refiner(run, perception, "prior")("vision", touches)
    (global_touches, global_request), (fused_touches, fused_request), prior_call = calls
    constraints, prior_request = prior_call
    assert global_touches == touches and fused_touches == touches  # the same objects
    assert global_request == ("active", "global") and fused_request == ("active", "fused")
    expected = touch_constraints(touches[0], grid).merged(touch_constraints(touches[1], grid))
    assert np.array_equal(constraints.occupied, expected.occupied)
    assert np.array_equal(constraints.empty, expected.empty)
    assert prior_request == ("active", "prior")
    with pytest.raises(ValueError):
        refiner(run, perception, "direct")


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
    rows[0]["ideal_touches_fused_mm"] = [10.0, 5.0]
    rows[1]["ideal_touches_fused_mm"] = [4.0, 1.0]
    rows[1]["ideal_oracle_touches_fused_mm"] = [4.0, 3.0]
    rows[0]["ideal_touches_global_mm"] = [8.0, 6.0]  # from its own start (the session's)
    summary = summarise_bounds(rows, (1,))
    assert summary["vision_mm"] == 7.0 and summary["latent_fit_mm"] == 5.0
    assert summary["latent_fit_change_pct"] == pytest.approx(-20.0)  # mean of -40 % and 0 %
    assert summary["floor_change_pct"] == pytest.approx(-65.0)
    assert summary["ideal_touches"]["1"] == {"chamfer_mm": 5.5, "change_pct": -30.0}
    assert summary["ideal_touches_fused"]["1"] == {"chamfer_mm": 3.0, "change_pct": -62.5}
    assert summary["ideal_oracle_touches_fused"]["1"] == {"chamfer_mm": 3.0, "change_pct": -25.0}
    assert summary["ideal_touches_global"]["1"] == {"chamfer_mm": 6.0, "change_pct": -25.0}
    assert "ideal_oracle_touches" not in summary  # no row has that curve


def test_bounds_json_on_a_small_object(calibration) -> None:
    config = Config()
    result = run_bounds(
        config,
        [small_box()],
        BoundsSettings(touch_counts=(1,), fit_steps=3, oracle_candidates=2, prior="general"),
        priors={"general": ShapePrior.untrained("cpu")},
        calibration=calibration,
    )
    json.dumps(result, allow_nan=False)
    (row,) = result["objects"]
    assert row["name"] == "small_box" and 0.0 < row["floor_mm"] < 4.0  # within a voxel
    # The bench's camera gives depth: the fused and global curves start from the session's
    # start (the depth fused in), the prior update's from the prior's voxels.
    assert result["input"] == "auto" and row["start_mm"] != row["vision_mm"]
    starts = {"": "vision_mm", "_fused": "start_mm", "_global": "start_mm"}
    for update, start in starts.items():
        for key in (f"ideal_touches{update}", f"ideal_oracle_touches{update}"):
            assert len(row[f"{key}_mm"]) == 2 and row[f"{key}_mm"][0] == row[start]
            assert set(result["summary"][key]) == {"1"}
    assert row["ideal_voxels_per_touch"]["occupied"] > 0
    assert result["updates"] == ["global", "fused", "prior"]
    fusion = result["refinement"]["fusion"]
    assert fusion["support_m"] == config.models.fusion_support_m
    assert fusion["prior_std_m"] == config.models.fusion_prior_std_m


@pytest.mark.slow  # 30 s; the fused field's contacts are tested in tests/models/test_fused_shape.py
def test_ideal_touches_bend_the_fused_surface_through_their_contacts(calibration) -> None:
    """The fused curve: its estimate is the fused shape, whose surface passes through what the
    ideal touches measured (their contact points), and it lowers the error from vision."""
    config = Config()
    priors = {"general": ShapePrior.untrained("cpu")}
    run = ObjectRun(
        config, calibration, priors, small_box(), ExploreSettings(touches=2, prior="general")
    )
    try:
        perception = run.perception(0)
        refine = refiner(run, perception, "fused")
        start = curve_start(run, "fused")
        curve = ideal_touch_curve(run, refine, start, perception.pad_size_m, 2, 1, run.metric_seed)
        assert len(curve.chamfer_mm) == 3 and len(curve.touches) == 2
        assert curve.chamfer_mm[-1] < curve.chamfer_mm[0]
        assert curve.estimate.fused is not None
        contacts = np.concatenate([touch.contact_points_world for touch in curve.touches])
        assert len(contacts) > 100
        distance_m = distance_to_mesh(contacts, curve.estimate.surface_mesh())
        assert np.median(distance_m) < 0.5e-3
    finally:
        run.close()


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
    monkeypatch.setattr(bench_cli, "_load_priors", lambda config, name: f"prior {name}")
    monkeypatch.setattr(learned, "load_calibration", lambda config: "calibration")
    monkeypatch.setattr(torch, "set_num_threads", lambda n: calls.update(threads=n))
    out = tmp_path / "b.json"
    argv = ["bench", "explore-bounds", "--touches", "10", "30", "--workers", "2"]
    assert main([*argv, "--json", str(out), "--prior", "box"]) == 0
    assert calls["settings"] == BoundsSettings(touch_counts=(10, 30), prior="box")
    assert len(calls["objects"]) == 1 and calls["objects"][0][1] == 1  # one per category
    assert calls["priors"] == "prior box" and calls["calibration"] == "calibration"
    assert calls["workers"] == 2 and calls["threads"] == 1
    assert json.loads(out.read_text())["summary"] == {"objects": 1}
    assert main([*argv, "--prior", "box", "--updates", "prior", "--input", "rgb"]) == 0
    assert calls["settings"] == BoundsSettings(
        (10, 30), prior="box", updates=("prior",), input_mode="rgb"
    )
    with pytest.raises(SystemExit):
        main([*argv, "--updates", "direct"])


def test_bounds_settings_refuse_unknown_or_repeated_updates() -> None:
    for updates in ((), ("direct",), ("fused", "fused")):
        with pytest.raises(ValueError):
            BoundsSettings(updates=updates)
