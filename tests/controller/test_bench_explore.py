"""The exploration benchmark: simulated touches, the oracle, mesh files, the JSON and the CLI."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from controller.benchmarks.explore import (
    METHODS,
    ExploreSettings,
    TouchTrial,
    choose_oracle_trial,
    file_objects,
    run_explore_benchmark,
)
from controller.benchmarks.explore_summary import compare_methods, plot_curves, summarise
from controller.benchmarks.sim_touch import SimTouchBench
from controller.cli.main import main
from controller.config import Config
from controller.perception.learned import LearnedPerception, load_calibration
from controller.perception.protocol import TouchTarget
from controller.request import ExploreRequest
from models.geometry import make_transform
from models.prior.evaluation import EvalObject
from models.prior.shape_prior import ShapePrior

BOX_HALF_M = 0.04


@pytest.fixture(scope="module")
def config() -> Config:
    return Config()


@pytest.fixture(scope="module")
def calibration(config: Config):
    return load_calibration(config)


@pytest.fixture(scope="module")
def box_bench(config: Config):
    box = trimesh.creation.box(
        (2 * BOX_HALF_M,) * 3, transform=make_transform(None, (0, 0, BOX_HALF_M))
    )
    bench = SimTouchBench(config, box, seed=0)
    yield bench
    bench.close()


def perception_for(config: Config, calibration) -> LearnedPerception:
    return LearnedPerception(
        config,
        camera_position_world=config.cameras.rgbd.pose_world_camera()[:3, 3],
        calibration=calibration,
    )


def test_sweep_toward_a_box_face_makes_contact(box_bench, config) -> None:
    target = TouchTarget(np.array([BOX_HALF_M, 0.0, 0.04]), np.array([-1.0, 0.0, 0.0]))
    measurement = box_bench.touch(target, noise_seed=(0,))
    assert measurement is not None and measurement.contact
    assert measurement.force_n == pytest.approx(config.limits.contact_force_n, rel=0.05)
    # The pad started on the approach line before the face and stopped on it (gel pressed in).
    assert measurement.pad_start_world[0] > BOX_HALF_M + 0.02
    assert measurement.pose_world_pad[0, 3] == pytest.approx(BOX_HALF_M, abs=2e-3)


def test_contact_on_a_box_edge_gives_contact_points(box_bench, config, calibration) -> None:
    # A flat face filling the pad leaves no gradient for the GelSight to see; an edge does.
    edge = np.array([BOX_HALF_M, BOX_HALF_M, 0.04])
    target = TouchTarget(edge, np.array([-1.0, -1.0, 0.0]) / np.sqrt(2))
    measurement = box_bench.touch(target, noise_seed=(0,))
    assert measurement is not None and measurement.contact
    perception = perception_for(config, calibration)
    outcome = perception.interpret(measurement)
    points = outcome.contact_points_world
    assert len(points) > 0
    # On the box's surface, next to the vertical edge.
    box_points = np.abs(points - [0.0, 0.0, BOX_HALF_M])
    outside = np.linalg.norm(np.maximum(box_points - BOX_HALF_M, 0.0), axis=1)
    inside = np.maximum(BOX_HALF_M - box_points.max(axis=1), 0.0)
    assert np.percentile(outside + inside, 90) < 1e-3
    assert np.max(outside + inside) < 2e-3
    assert np.abs(points[:, :2] - edge[:2]).max() < 4e-3
    constraints = perception.constraints([outcome], perception.grid)
    assert len(constraints.occupied) > 0 and len(constraints.empty) > 0


def test_refinement_writes_the_measured_voxels_into_the_shape(
    box_bench, config, calibration
) -> None:
    """The pipeline refines the latent (anchored to the vision latent) and then writes what the
    touch measured into the refined shape: its empty voxels 0, its occupied ones 1."""
    from controller.perception.protocol import ShapeEstimate
    from models.prior.shape_prior import ShapePrior

    edge = np.array([BOX_HALF_M, BOX_HALF_M, 0.04])
    target = TouchTarget(edge, np.array([-1.0, -1.0, 0.0]) / np.sqrt(2))
    measurement = box_bench.touch(target, noise_seed=(0,))
    perception = perception_for(config, calibration)
    perception._priors["general"] = ShapePrior.untrained("cpu")
    outcome = perception.interpret(measurement)
    latent = torch.randn(200, generator=torch.Generator().manual_seed(0))
    shape = (perception.grid.resolution,) * 3
    vision = ShapeEstimate(
        perception.grid,
        np.full(shape, 0.5, np.float32),
        latent,
        vision_probabilities=np.full(shape, 0.5, np.float32),
        vision_latent=latent,
    )
    request = ExploreRequest(update="prior", prior="general")
    refined = perception.refine(vision, [outcome], request)
    flat = refined.probabilities.reshape(-1)
    constraints = perception.constraints([outcome], perception.grid)
    assert np.all(flat[constraints.empty] == 0.0)
    assert np.all(flat[constraints.occupied] == 1.0)
    assert not torch.equal(torch.as_tensor(refined.latent), latent)
    assert refined.vision_latent is latent


def test_sweep_through_free_space_is_a_miss_over_the_full_stroke(box_bench, config) -> None:
    target = TouchTarget(np.array([0.15, 0.15, 0.05]), np.array([-1.0, 0.0, 0.0]))
    measurement = box_bench.touch(target, noise_seed=(1,))
    assert measurement is not None and not measurement.contact
    travel = np.linalg.norm(measurement.pose_world_pad[:3, 3] - measurement.pad_start_world)
    assert travel == pytest.approx(config.gripper.stroke_m / 2 - 0.001, abs=1e-4)
    assert measurement.force_n == 0.0


def test_a_target_without_a_clear_start_is_refused(box_bench) -> None:
    # A target deep in the box: every start up to 45 mm out along the line is inside the box.
    inside = TouchTarget(np.array([-0.02, 0.0, 0.04]), np.array([-1.0, 0.0, 0.0]))
    assert not box_bench.allowed(inside)
    assert box_bench.touch(inside, noise_seed=(2,)) is None


def test_the_oracle_picks_the_candidate_with_the_lowest_error() -> None:
    targets = [TouchTarget(np.array([x, 0.0, 0.0]), np.array([-1.0, 0.0, 0.0])) for x in range(4)]
    errors = {0: 12.0, 1: None, 2: 7.5, 3: 9.0}  # None: the touch could not be made
    calls = []

    def trial(target: TouchTarget) -> TouchTrial | None:
        index = int(target.target_world[0])
        calls.append(index)
        if errors[index] is None:
            return None
        return TouchTrial(None, None, {"chamfer_mm": errors[index]}, 0.0)  # type: ignore[arg-type]

    chosen = choose_oracle_trial(targets, trial)
    assert chosen is not None and chosen.metrics["chamfer_mm"] == 7.5
    assert sorted(calls) == [0, 1, 2, 3]
    assert choose_oracle_trial([], trial) is None


def write_open_mesh_in_millimetres(path: Path) -> None:
    """A 300 mm tall, y-up open tube (no caps: not watertight), as a user's OBJ might be."""
    tube = trimesh.creation.cylinder(radius=40.0, height=300.0, sections=24)
    tube.apply_transform(make_transform(np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]]), (5, 7, 9)))
    keep = np.abs(tube.face_normals[:, 1]) < 0.9  # drop the caps
    trimesh.Trimesh(tube.vertices, tube.faces[keep]).export(path)


def test_any_mesh_file_becomes_an_upright_object_in_the_grid(tmp_path: Path) -> None:
    path = tmp_path / "tube.obj"
    write_open_mesh_in_millimetres(path)
    (obj,) = file_objects([path], up_axis="y")
    low, high = obj.mesh.bounds
    assert obj.name == "tube" and not obj.mesh.is_watertight
    assert low[2] == pytest.approx(0.0, abs=1e-9) and high[2] == pytest.approx(0.25)
    assert np.allclose((low[:2] + high[:2]) / 2, 0.0, atol=1e-9)
    (fitted,) = file_objects([path], up_axis="y", fit_size_m=0.12)
    assert max(fitted.mesh.extents) == pytest.approx(0.12)


def check_curves(result: dict, touches: int) -> None:
    for key in ("chamfer_mm", "fscore_5mm", "fscore_2mm", "iou"):
        assert len(result[key]) == touches + 1
    assert len(result["select_s"]) == len(result["refine_s"]) == result["touches_made"]


def run_on_small_box(config: Config, calibration, settings: ExploreSettings) -> dict:
    """The benchmark's JSON on a 6 x 5 x 8 cm box, with an untrained general prior."""
    box = trimesh.creation.box((0.06, 0.05, 0.08), transform=make_transform(None, (0, 0, 0.04)))
    return run_explore_benchmark(
        config,
        [EvalObject("small_box", "file", box)],
        settings,
        priors={"general": ShapePrior.untrained("cpu")},
        calibration=calibration,
        progress=False,
    )


def test_benchmark_json_on_a_small_object(config, calibration, tmp_path: Path) -> None:
    settings = ExploreSettings(
        touches=2,
        methods=("active-fused", "random-prior"),
        random_runs=2,
        timing_resolutions=(),
        input_mode="rgb",  # RGB-D: the fused methods start from the depth fused in
        prior="general",
    )
    result = run_on_small_box(config, calibration, settings)
    json.dumps(result, allow_nan=False)  # strict JSON: no NaN or inf
    (obj,) = result["objects"]
    assert obj["name"] == "small_box" and set(obj["methods"]) == set(settings.methods)
    active, random = obj["methods"]["active-fused"], obj["methods"]["random-prior"]
    check_curves(active, 2)
    assert active["chamfer_mm"][0] == random["chamfer_mm"][0]  # one vision estimate
    assert len(random["runs"]) == 2
    for run in random["runs"]:
        check_curves(run, 2)
    summary = result["summary"]
    assert summary["objects"] == 1 and summary["touches"] == 2
    assert len(summary["methods"]["active-fused"]["chamfer_mm"]) == 3
    assert "chamfer_change_pct" in summary["methods"]["random-prior"]
    # The fused surface passes through what the touches measured.
    if any(active["imprint"]):
        assert active["touch_fidelity_mm"][-1] < 0.5
    assert active["touch_fidelity_mm"][0] is None  # no contact before the first touch
    assert "active_fused_chamfer_change_pct" in summary["bar"]
    assert "active_prior_chamfer_change_pct" not in summary["bar"]
    assert result["timing"] == []
    plot_curves(result, tmp_path / "explore.png")
    assert (tmp_path / "explore.png").stat().st_size > 1000


@pytest.mark.parametrize("select_lag", [False, True])
def test_a_lagged_policy_reads_the_estimate_before_the_last_refinement(
    config, calibration, monkeypatch, select_lag: bool
) -> None:
    """As a session refining while the arm moves: the target after touch k is chosen from the
    estimate touch k was refined from, not from touch k's refinement."""
    # The estimates themselves, kept alive, compared by identity.
    read: list[object] = []
    refined_from: list[object] = []
    refined: list[object] = []
    select, refine = LearnedPerception.select, LearnedPerception.refine

    def recording_select(self, estimate, *args, **kwargs):
        read.append(estimate)
        return select(self, estimate, *args, **kwargs)

    def recording_refine(self, estimate, *args, **kwargs):
        result = refine(self, estimate, *args, **kwargs)
        refined_from.append(estimate)
        refined.append(result)
        return result

    monkeypatch.setattr(LearnedPerception, "select", recording_select)
    monkeypatch.setattr(LearnedPerception, "refine", recording_refine)
    settings = ExploreSettings(
        touches=3,
        methods=("active-fused",),
        timing_resolutions=(),
        input_mode="rgb",
        prior="general",
        select_lag=select_lag,
    )
    result = run_on_small_box(config, calibration, settings)
    assert result["select_lag"] is select_lag
    assert len(refined) == 3 and len(read) == 3
    assert read[0] is refined_from[0]  # the first target: from vision either way
    expected = refined_from[:2] if select_lag else refined[:2]
    assert all(a is b for a, b in zip(read[1:], expected, strict=True))


def method_result(chamfer: list[float]) -> dict:
    touches = len(chamfer) - 1
    return {
        "chamfer_mm": chamfer,
        **{key: [0.5] * (touches + 1) for key in ("fscore_5mm", "fscore_2mm", "iou")},
        "touch_fidelity_mm": [None] + [0.2] * touches,
        "select_s": [0.01] * touches,
        "refine_s": [0.2] * touches,
        "contact": [True, False, True][:touches],
        "imprint": [True, False, False][:touches],
        "stopped_by": ["gel", None, "gelsight_housing"][:touches],
        "touch_loss": [[2.0, 1.0]] * touches,
        "flipped": [4] * touches,
        "target": [[0.0, 0.0, 0.05, -1.0, 0.0, 0.0]] * touches,
        "touches_made": touches,
    }


def test_summary_averages_curves_and_checks_the_bar() -> None:
    objects = [
        {
            "methods": {
                "active-prior": method_result([10.0, 9.0, 8.0, 6.0]),
                "random-prior": method_result([10.0, 9.5, 9.0, 8.0]),
                "active-direct": method_result([10.0, 9.0, 8.0, 7.0]),
            }
        },
        {
            "methods": {
                "active-prior": method_result([20.0, 16.0, 12.0, 10.0]),
                "random-prior": method_result([20.0, 15.0, 13.0, 12.0]),
                "active-direct": method_result([20.0, 16.0, 12.0, 9.0]),
            }
        },
    ]
    summary = summarise(objects, ["active-prior", "random-prior", "active-direct"], 3)
    active = summary["methods"]["active-prior"]
    assert active["chamfer_mm"] == [15.0, 12.5, 10.0, 8.0]
    assert active["chamfer_change_pct"] == pytest.approx(-45.0)  # mean of -40 % and -50 %
    assert active["touches"]["imprint"] == 2 and active["touches"]["force_only"] == 2
    assert active["touches"]["force_only_stopped_by"] == {"gelsight_housing": 2}
    assert active["touches"]["miss"] == 2 and active["touches"]["flipped_voxels_mean"] == 4
    assert active["touches"]["touch_loss_after_over_before_median"] == 0.5
    assert active["touches"]["repeated_targets"] == 4  # the same target thrice per object
    assert summary["bar"] == {
        "active_prior_chamfer_change_pct": pytest.approx(-45.0),
        "active_prior_lowers_chamfer_30pct": True,
        "active_beats_random_from_3": True,  # 8.0 < 10.0 at 3 touches
        "active_beats_direct_at_end": False,  # 8.0 = 8.0
    }


def test_the_fused_bar_is_checked_per_object() -> None:
    objects = [
        {
            "methods": {
                "active-fused": method_result([10.0, 8.0, 7.0, 6.0]),
                "random-fused": method_result([10.0, 9.0, 8.0, 7.0]),
            }
        },
        {
            "methods": {
                "active-fused": method_result([4.0, 4.0, 4.1, 4.02]),  # +0.5 %: not worse than 1 %
                "random-fused": method_result([4.0, 4.1, 4.1, 4.1]),
            }
        },
    ]
    bar = summarise(objects, ["active-fused", "random-fused"], 3)["bar"]
    assert bar["active_fused_chamfer_change_pct"] == pytest.approx((-40.0 + 0.5) / 2)
    assert bar["active_fused_worst_object_change_pct"] == pytest.approx(0.5)
    assert bar["no_object_worse_than_1pct"] is True
    assert bar["active_fused_final_chamfer_mm"] == pytest.approx(5.01)
    assert bar["active_fused_lowers_chamfer_30pct_to_3_5mm"] is False  # -19.75 %, 5.01 mm
    assert bar["touch_fidelity_within_0_3mm"] is True
    assert bar["active_fused_beats_random_fused"] is True  # 5.01 vs 5.55: -9.7 %
    objects[1]["methods"]["active-fused"]["chamfer_mm"][-1] = 4.1  # +2.5 %
    assert summarise(objects, ["active-fused"], 3)["bar"]["no_object_worse_than_1pct"] is False


def test_settings_reject_unknown_methods() -> None:
    with pytest.raises(ValueError, match="unknown method"):
        ExploreSettings(methods=("active-prior", "greedy"))
    assert set(METHODS) == set(ExploreSettings().methods)


def test_the_issue_command_runs_the_benchmark_as_asked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """What the command line says is what the benchmark gets: objects, settings, prior, workers,
    the JSON and the plot (the benchmark itself is replaced by a recorder)."""
    import controller.benchmarks.explore as explore_module
    import controller.benchmarks.explore_summary as summary_module
    import controller.cli.bench as bench_cli
    import controller.perception.learned as learned

    calls: dict = {}

    def run(config: Config, objects: list, settings: object, **kwargs: object) -> dict:
        calls.update(objects=objects, settings=settings, **kwargs)
        return {"summary": {"objects": len(objects)}}

    monkeypatch.setattr(explore_module, "run_explore_benchmark", run)
    monkeypatch.setattr(
        explore_module,
        "file_objects",
        lambda paths, up_axis, fit_size_m: [(path.name, up_axis) for path in paths],
    )
    monkeypatch.setattr(bench_cli, "_load_priors", lambda config, name: f"prior {name}")
    monkeypatch.setattr(learned, "load_calibration", lambda config: "calibration")
    monkeypatch.setattr(summary_module, "plot_curves", lambda result, path: calls.update(plot=path))
    monkeypatch.setattr(torch, "set_num_threads", lambda n: calls.update(threads=n))
    out, plot = tmp_path / "out.json", tmp_path / "p.png"
    code = main(
        [
            *("bench", "explore", "--objects", "a.obj", "b.stl", "--up-axis", "y"),
            *("--touches", "10", "--methods", ",".join(METHODS), "--json", str(out)),
            *("--plot", str(plot), "--random-runs", "10", "--oracle-candidates", "4"),
            *("--prior", "box", "--input", "rgbd", "--workers", "2"),
        ]
    )
    assert code == 0
    assert calls["objects"] == [("a.obj", "y"), ("b.stl", "y")]
    assert calls["settings"] == ExploreSettings(
        touches=10,
        methods=tuple(METHODS),
        random_runs=10,
        oracle_candidates=4,
        input_mode="rgbd",
        prior="box",
    )
    assert calls["priors"] == "prior box" and calls["calibration"] == "calibration"
    assert calls["workers"] == 2 and calls["threads"] == 1
    assert calls["plot"] == plot
    assert json.loads(out.read_text())["summary"] == {"objects": 2}


@pytest.mark.slow
def test_a_mesh_file_runs_through_the_benchmark_deterministically(
    config, calibration, tmp_path: Path
) -> None:
    path = tmp_path / "tube.obj"
    write_open_mesh_in_millimetres(path)
    objects = file_objects([path], up_axis="y", fit_size_m=0.15)
    settings = ExploreSettings(
        touches=2,
        methods=("active-direct", "oracle-prior"),
        oracle_candidates=1,
        timing_resolutions=(),
        prior="general",
    )

    def run() -> dict:
        return run_explore_benchmark(
            config,
            objects,
            settings,
            priors={"general": ShapePrior.untrained("cpu")},
            calibration=calibration,
            progress=False,
        )

    first, second = run(), run()
    for method in settings.methods:
        check_curves(first["objects"][0]["methods"][method], 2)
        for key in ("chamfer_mm", "iou", "contact"):
            assert (
                first["objects"][0]["methods"][method][key]
                == second["objects"][0]["methods"][method][key]
            )


def test_where_the_gel_pressed_the_table_it_measured_no_object(
    box_bench, config, calibration, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Contact points at the table top (a random touch beside a flat object can press the gel
    onto the table) are the table's: dropped."""
    import controller.perception.learned as learned
    from models.geometry import invert_transform, transform_points
    from models.tactile.reconstruction import TactileContact

    target = TouchTarget(np.array([BOX_HALF_M, 0.0, 0.04]), np.array([-1.0, 0.0, 0.0]))
    measurement = box_bench.touch(target, noise_seed=(0,))
    assert measurement is not None and measurement.contact
    pad = measurement.pose_world_pad
    # Points on the face at heights 1 mm (the table's) and 3, 10 mm (the box's).
    world = np.array([[BOX_HALF_M, 0.0, z] for z in (0.001, 0.003, 0.010)])
    pad_mm = transform_points(invert_transform(pad), world) * 1e3
    contact = TactileContact(pad_mm, np.array([0.0, 0.0, -1.0]))
    monkeypatch.setattr(learned, "contact_geometry", lambda *args, **kwargs: contact)
    outcome = perception_for(config, calibration).interpret(measurement)
    assert np.allclose(outcome.contact_points_world[:, 2], [0.003, 0.010])


def _box_distance_m(points_world: np.ndarray) -> np.ndarray:
    """The box bench's signed distance (metres, positive outside)."""
    q = np.abs(points_world - [0.0, 0.0, BOX_HALF_M]) - BOX_HALF_M
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


@pytest.mark.parametrize(
    "height_m",
    [
        BOX_HALF_M,  # the face fills the pad: the gel pressed evenly, no slope to see
        2 * BOX_HALF_M + 0.012,  # the gel passes over the top; the housing meets the face
    ],
)
def test_a_stop_without_an_imprint_knows_where_the_tool_met_the_object(
    box_bench, config, calibration, height_m
) -> None:
    """Stopped by force without an imprint, the touch keeps the tool's leading points at the
    stop: the simulated bench's physics put the object against one of them (distance ~0) and
    inside none. With ``stop_constraints`` off it keeps none."""
    target = TouchTarget(np.array([BOX_HALF_M, 0.0, height_m]), np.array([-1.0, 0.0, 0.0]))
    measurement = box_bench.touch(target, noise_seed=(0,))
    outcome = perception_for(config, calibration).interpret(measurement)
    assert measurement.contact and len(outcome.contact_points_world) == 0  # force only
    distance = _box_distance_m(outcome.touch.stop_points_world)
    assert abs(distance.min()) < 0.001
    assert distance.min() > -0.001
    off = dataclasses.replace(
        config, models=dataclasses.replace(config.models, stop_constraints=False)
    )
    assert len(perception_for(off, calibration).interpret(measurement).touch.stop_points_world) == 0


@pytest.mark.parametrize(("tilt_deg", "imprint"), [(0.0, False), (10.0, True)])
def test_a_flat_face_filling_the_gel_leaves_an_imprint_only_when_met_at_a_tilt(
    box_bench, config, calibration, tilt_deg, imprint
) -> None:
    """A GelSight sees slopes: pressed square onto a face that fills it, the gel leaves no
    imprint (the touch is force only, stopped by the gel's own force); met 10 degrees off the
    face's normal it presses a wedge, and the reconstruction finds it on the face."""
    tilt = np.radians(tilt_deg)
    direction = np.array([-np.cos(tilt), 0.0, -np.sin(tilt)])
    target = TouchTarget(np.array([BOX_HALF_M, 0.0, 0.04]), direction)
    measurement = box_bench.touch(target, noise_seed=(0,))
    outcome = perception_for(config, calibration).interpret(measurement)
    assert measurement.contact and box_bench.stopped_by(measurement) == "gel"
    assert (len(outcome.contact_points_world) > 0) == imprint
    if imprint:
        assert np.allclose(outcome.contact_points_world[:, 0], BOX_HALF_M, atol=0.001)


@pytest.mark.parametrize(
    ("height_m", "stopped_by"),
    [
        (BOX_HALF_M, "gel"),  # the face fills the pad
        (2 * BOX_HALF_M + 0.012, "gelsight_housing"),  # the gel passes over the top
        (2 * BOX_HALF_M + 0.06, None),  # everything passes over: a miss
    ],
)
def test_the_bench_tells_what_stopped_the_fingers(box_bench, height_m, stopped_by) -> None:
    """Why a touch left no imprint, which the benchmark counts (``stopped_by``): the gel's own
    force, or the rigid part that meets the object just beyond where the fingers stopped."""
    target = TouchTarget(np.array([BOX_HALF_M, 0.0, height_m]), np.array([-1.0, 0.0, 0.0]))
    measurement = box_bench.touch(target, noise_seed=(0,))
    assert measurement is not None
    assert box_bench.stopped_by(measurement) == stopped_by


def test_a_stop_where_the_tool_reached_the_table_says_nothing_of_the_object(
    box_bench, config, calibration
) -> None:
    """The same stop without an imprint, moved down until a rigid part of the tool reaches the
    table: the table may have stopped the fingers, so the touch keeps its sweep alone."""
    target = TouchTarget(np.array([BOX_HALF_M, 0.0, BOX_HALF_M]), np.array([-1.0, 0.0, 0.0]))
    measurement = box_bench.touch(target, noise_seed=(0,))
    perception = perception_for(config, calibration)
    assert len(perception.interpret(measurement).touch.stop_points_world)
    tool = perception.tool
    width_m = measurement.gripper_width_m
    pose_world_tcp = measurement.pose_world_pad @ np.linalg.inv(tool.pose_tcp_pad(width_m))
    lowest_m = min(box.lowest_world_z_m(pose_world_tcp) for box in tool.rigid_boxes(width_m))
    lowered = measurement.pose_world_pad.copy()
    lowered[2, 3] -= lowest_m + 0.001  # the lowest part 1 mm into the table
    at_table = dataclasses.replace(measurement, pose_world_pad=lowered)
    assert len(perception.interpret(at_table).touch.stop_points_world) == 0


@pytest.mark.parametrize("update", ["global", "fused"])
def test_a_contact_without_an_imprint_never_moves_the_surface_inward(
    box_bench, config, calibration, update
) -> None:
    """A flat face filling the pad stops the fingers by force but leaves no imprint: only the
    sweep up to the stop is known free. The refined surface may retreat to the stop, never
    past it: points beyond the stop that the estimate held inside stay inside."""
    target = TouchTarget(np.array([BOX_HALF_M, 0.0, 0.04]), np.array([-1.0, 0.0, 0.0]))
    measurement = box_bench.touch(target, noise_seed=(0,))
    perception = perception_for(config, calibration)
    outcome = perception.interpret(measurement)
    assert measurement.contact and len(outcome.contact_points_world) == 0  # force only
    request = ExploreRequest(update=update, prior="general", input="rgbd")
    vision = perception.reconstruct(box_bench.frame(), request)
    refined = perception.refine(vision, [outcome], request)
    stop = measurement.pose_world_pad[:3, 3]
    beyond = stop + np.outer(np.linspace(0.001, 0.008, 8), target.direction_world)
    before, after = vision.fused.sdf(beyond), refined.fused.sdf(beyond)
    assert np.all(after <= np.maximum(before, 0.0) + 5e-4)


def explore_json(seed: int, finals: dict[str, dict[str, float]]) -> dict:
    """A `bench explore` JSON of one seed: per object, each method's final Chamfer (from 10)."""
    objects = [
        {
            "name": name,
            "input": "rgb",
            "prior": "general",
            "methods": {m: method_result([10.0, 10.0, final]) for m, final in methods.items()},
        }
        for name, methods in finals.items()
    ]
    return {"seed": seed, "objects": objects}


def test_methods_are_compared_per_object_and_seed_across_files() -> None:
    """Pairs are (seed, object) wherever both methods ran; a file may hold one method only."""
    active_0 = explore_json(0, {"cup": {"active-global": 6.0}, "box": {"active-global": 9.0}})
    random_0 = explore_json(0, {"cup": {"random-global": 8.0}, "box": {"random-global": 9.0}})
    both_1 = explore_json(
        1,
        {
            "cup": {"active-global": 7.0, "random-global": 7.0},
            "box": {"active-global": 12.0, "random-global": 10.0},
            "toy": {"active-global": 3.0},  # no random run: no pair
        },
    )
    comparison = compare_methods([active_0, random_0, both_1], "active-global", "random-global")
    assert comparison["pairs"] == 4 and comparison["objects"] == 2
    means = comparison["final_chamfer_mm_mean"]
    assert means == {"active-global": pytest.approx(8.5), "random-global": pytest.approx(8.5)}
    assert comparison["vs_baseline_pct"] == pytest.approx(0.0)
    assert comparison["vs_baseline_pct_per_seed"]["0"] == pytest.approx(100 * (15 / 17 - 1))
    assert comparison["vs_baseline_pct_per_seed"]["1"] == pytest.approx(100 * (19 / 17 - 1))
    geometric = np.exp(np.mean(np.log([6 / 8, 9 / 9, 7 / 7, 12 / 10])))
    assert comparison["per_pair_geometric_mean_pct"] == pytest.approx(100 * (geometric - 1))
    assert comparison["method_lower"] == 1
    low, high = comparison["per_pair_geometric_mean_pct_ci95"]
    assert low <= comparison["per_pair_geometric_mean_pct"] <= high


def test_a_clear_difference_has_an_interval_without_zero() -> None:
    """Active lower on every object of every seed: the bootstrap over objects excludes 0."""
    finals = {f"object{i}": {"active-global": 8.0 + i, "random-global": 10.0 + i} for i in range(8)}
    results = [explore_json(seed, finals) for seed in range(3)]
    comparison = compare_methods(results, "active-global", "random-global")
    assert comparison["pairs"] == 24 and comparison["method_lower"] == 24
    assert comparison["vs_baseline_pct_ci95"][1] < 0.0
    assert comparison["per_pair_geometric_mean_pct_ci95"][1] < 0.0


def test_a_run_given_twice_is_refused(tmp_path: Path, capsys) -> None:
    """The same seed and object twice would count one run as two draws: refused, clearly, as a
    file that is not a benchmark's JSON is."""
    result = explore_json(0, {"cup": {"active-global": 6.0, "random-global": 8.0}})
    with pytest.raises(ValueError, match="appears twice"):
        compare_methods([result, result], "active-global", "random-global")
    with pytest.raises(ValueError, match="no object ran both"):
        compare_methods([result], "active-global", "random-prior")
    good, corrupt = tmp_path / "good.json", tmp_path / "corrupt.json"
    good.write_text(json.dumps(result))
    corrupt.write_text('{"seed": 0, "objects": [')
    with pytest.raises(SystemExit, match="cannot read"):
        main(["bench", "compare", str(good), str(corrupt)])
    assert main(["bench", "compare", str(good), "--json", str(tmp_path / "out.json")]) == 0
    written = json.loads((tmp_path / "out.json").read_text())
    assert written["pairs"] == 1 and written["pairs_table"][0]["object"] == "cup"
    assert '"pairs_table"' not in capsys.readouterr().out


def test_the_global_bar_is_issue_27s() -> None:
    """Per-object drop, the worst object, active against random at N, the imprint share."""
    objects = [
        {
            "methods": {
                "active-global": method_result([10.0, 8.0, 7.0, 6.0]),  # -40 %
                "random-global": method_result([10.0, 9.0, 8.0, 7.0]),
            }
        },
        {
            "methods": {
                "active-global": method_result([4.0, 4.0, 4.1, 4.02]),  # +0.5 %
                "random-global": method_result([4.0, 4.1, 4.1, 4.1]),
            }
        },
    ]
    bar = summarise(objects, ["active-global", "random-global"], 3)["bar"]
    assert bar["active_global_chamfer_change_pct"] == pytest.approx((-40.0 + 0.5) / 2)
    assert bar["active_global_lowers_chamfer_25pct"] is False  # -19.75 %
    assert bar["active_global_no_object_worse_than_1pct"] is True
    assert bar["active_global_vs_random_global_pct"] == pytest.approx(100 * (5.01 / 5.55 - 1))
    assert bar["active_global_beats_random_global_5pct"] is True
    assert bar["active_global_imprint_share"] == pytest.approx(0.5)  # 1 imprint, 1 force only
    assert bar["active_global_imprints_90pct"] is False
    assert bar["active_global_fidelity_within_0_3mm"] is True
