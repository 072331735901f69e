"""The safety benchmark: tool-part clearances along motions (TCP lines and joint moves), and
short runs of full sim sessions: with the geometric stand-in perception (the controller's paths
are what is measured; one session made to fail each way), and one with the learned perception."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from controller.benchmarks.safety import (
    TOUCH_LABELS,
    SafetyObject,
    SafetySettings,
    SurfaceSamples,
    box_clearance_m,
    format_table,
    joint_move_poses,
    line_poses,
    motion_clearances,
    run_safety_benchmark,
    safety_objects,
    session_clearances,
    summarise_safety,
)
from controller.config import Config
from drivers.factory import Devices
from drivers.tool import ToolBox, ToolModel
from drivers.ur5.kinematics import forward_kinematics
from models.geometry import make_transform, rotation_about_axis, ur_pose_to_matrix
from tests.fakes.perception import CylinderPerception, make_cylinder_perception

CUBE = trimesh.creation.box((0.1, 0.1, 0.1))  # faces at +-50 mm
SPHERE = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
PARTS = [box.name for box in ToolModel(Config().gripper, Config().sensor).rigid_boxes(0.08)]
ROW_KEYS = (
    "object",
    "yaw_deg",
    "session",
    "state",
    "touches",
    "contacts",
    "error",
    "protective_stops",
    "rigid_contacts",
    "unexpected_forces",
    "stop_reason",
    "skipped_targets",
    "motions",
    "min_transit_clearance_mm",
    "min_transit_clearance_by_part_mm",
    "worst_transit",
    "min_approach_clearance_mm",
    "min_approach_clearance_by_part_mm",
)


def turned(yaw_deg: float, position: tuple[float, float, float]) -> np.ndarray:
    return make_transform(rotation_about_axis((0, 0, 1), math.radians(yaw_deg)), position)


@pytest.fixture(scope="module")
def cube() -> SurfaceSamples:
    return SurfaceSamples.of_mesh(CUBE)


@pytest.fixture(scope="module")
def sphere() -> SurfaceSamples:
    return SurfaceSamples.of_mesh(SPHERE)


# --- one box --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("yaw_deg", "expected_m"),
    [(0.0, 0.020), (30.0, 0.015), (0.0, 0.004), (0.0, 0.080)],
)
def test_a_box_facing_a_cube_is_at_its_gap(
    cube: SurfaceSamples, yaw_deg: float, expected_m: float
) -> None:
    half = np.array([0.01, 0.02, 0.03])
    yaw = math.radians(yaw_deg)
    reach_x = half[0] * math.cos(yaw) + half[1] * math.sin(yaw)  # the turned box's x extent
    pose = turned(yaw_deg, (0.05 + reach_x + expected_m, 0.0, 0.0))
    assert box_clearance_m(pose, half, cube) == pytest.approx(expected_m, abs=0.001)


def test_a_box_beside_a_sphere_is_at_its_gap(sphere: SurfaceSamples) -> None:
    half = np.array([0.01, 0.01, 0.01])
    pose = turned(0.0, (0.05 + 0.012 + 0.01, 0.0, 0.0))  # its near face 12 mm from the sphere
    assert box_clearance_m(pose, half, sphere) == pytest.approx(0.012, abs=0.001)
    corner = np.array([0.01, 0.01, 0.01])  # the box's corner toward the sphere's centre
    centre = (0.05 + 0.012) * corner / np.linalg.norm(corner) + corner
    assert box_clearance_m(turned(0.0, tuple(centre)), half, sphere) == pytest.approx(
        0.012, abs=0.001
    )


def test_a_box_into_the_surface_or_buried_is_not_clear(cube: SurfaceSamples) -> None:
    half = np.array([0.01, 0.01, 0.01])
    assert box_clearance_m(turned(0.0, (0.055, 0.0, 0.0)), half, cube) < 0.0  # 5 mm in
    # Wholly inside: no surface point in the box, found by its centre inside the solid.
    assert box_clearance_m(turned(20.0, (0.0, 0.0, 0.0)), half, cube) < -0.02


def test_far_clearances_are_lower_bounds_past_the_search(cube: SurfaceSamples) -> None:
    half = np.array([0.01, 0.01, 0.01])
    pose = turned(0.0, (0.05 + 0.01 + 0.2, 0.0, 0.0))  # 200 mm away
    assert 0.03 <= box_clearance_m(pose, half, cube, search_m=0.03) <= 0.2
    assert box_clearance_m(pose, half, cube, search_m=0.3) == pytest.approx(0.2, abs=0.001)


# --- motions --------------------------------------------------------------------------------------


def test_line_poses_are_at_most_two_mm_of_travel_or_turn_apart() -> None:
    start = turned(0.0, (0.0, 0.0, 0.0))
    poses = line_poses(start, turned(0.0, (0.1, 0.0, 0.0)))
    assert np.allclose(poses[0], start) and np.allclose(poses[-1][:3, 3], [0.1, 0, 0])
    assert np.max(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)) <= 0.002 + 1e-12
    turn = line_poses(start, turned(90.0, (0.0, 0.0, 0.0)))  # a pure turn: 0.17 m * pi / 2
    assert len(turn) - 1 >= math.ceil(0.17 * math.pi / 2 / 0.002)


def test_a_line_past_the_object_keeps_its_gap_and_one_through_it_does_not(
    sphere: SurfaceSamples,
) -> None:
    box = ToolBox("probe", make_transform(None, (0.0, 0.0, 0.0)), np.array([0.01, 0.01, 0.01]))
    past = motion_clearances(
        turned(0.0, (-0.2, 0.08, 0.0)), turned(0.0, (0.2, 0.08, 0.0)), [box], sphere
    )
    assert past["probe"] == pytest.approx(0.08 - 0.01 - 0.05, abs=0.001)
    through = motion_clearances(
        turned(0.0, (-0.2, 0.0, 0.0)), turned(0.0, (0.2, 0.0, 0.0)), [box], sphere
    )
    assert through["probe"] <= 0.0


def test_a_turning_tool_is_checked_between_its_end_poses() -> None:
    """A part 15 cm from the TCP sweeps through a small ball at 45 degrees while the TCP
    stays put: only poses between the ends find it."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.01)
    ball.apply_translation(0.15 * np.array([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0]))
    box = ToolBox("arm", make_transform(None, (0.15, 0.0, 0.0)), np.array([0.005, 0.005, 0.005]))
    samples = SurfaceSamples.of_mesh(ball)
    ends = [turned(0.0, (0, 0, 0)), turned(90.0, (0, 0, 0))]
    assert all(
        box_clearance_m(end @ box.pose_tcp_box, box.half_extents_m, samples) > 0.05 for end in ends
    )
    assert motion_clearances(*ends, [box], samples)["arm"] <= 0.0


@pytest.mark.parametrize("part", PARTS)
def test_every_rigid_part_is_measured(part: str) -> None:
    """A small ball at one part's centre, met on a short motion: that part (and no other)
    reports no clearance. A part left out of the computation would fail here."""
    config = Config()
    tool = ToolModel(config.gripper, config.sensor)
    boxes = {box.name: box for box in tool.rigid_boxes(0.08)}
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.001)
    ball.apply_translation(boxes[part].pose_tcp_box[:3, 3])
    motion = [turned(0.0, (0.0, -0.003, 0.0)), turned(0.0, (0.0, 0.003, 0.0))]
    clearances = motion_clearances(*motion, list(boxes.values()), SurfaceSamples.of_mesh(ball))
    assert set(clearances) == set(boxes)
    assert clearances[part] <= 0.0
    assert all(c > 0.0 for name, c in clearances.items() if name != part), clearances


def test_a_transit_whose_only_collision_is_the_gripper_body_is_reported() -> None:
    """A cube beside the gripper body (between it and the fingers' x, below them): the
    transit sweeps the body through it; the session's report names that motion and part."""
    config = Config()
    tool = ToolModel(config.gripper, config.sensor)
    cube = trimesh.creation.box((0.01, 0.01, 0.01))
    cube.apply_translation((0.065, 0.0, 0.036))  # inside the body's x, z; far below the fingers
    start, end = turned(0.0, (0.0, -0.1, 0.0)), turned(0.0, (0.0, 0.1, 0.0))
    motions = [
        {
            "label": "direct",
            "start_world_tcp": start.tolist(),
            "end_world_tcp": end.tolist(),
            "width_m": 0.08,
        },
    ]
    report = session_clearances(motions, tool, SurfaceSamples.of_mesh(cube), config.robot.arm)
    by_part = report["min_transit_clearance_by_part_mm"]
    assert by_part["gripper_body"] <= 0.0
    assert all(v > 0.0 for part, v in by_part.items() if part != "gripper_body"), by_part
    assert report["worst_transit"]["part"] == "gripper_body"
    assert report["worst_transit"]["motion"] == 0 and report["worst_transit"]["label"] == "direct"


def test_a_joint_move_is_followed_along_its_arc_not_the_chord() -> None:
    """The base turns 1.5 rad: the TCP swings on an arc. A ball on the arc's middle,
    off the straight line between the ends, is met by the joint move (and not by a line)."""
    config = Config()
    arm = config.robot.arm
    start = np.asarray(arm.home_joints_rad, dtype=float)
    end = start + np.array([1.5, 0.0, 0.0, 0.0, 0.0, 0.0])
    poses = joint_move_poses(start, end, arm)
    world_base = ur_pose_to_matrix(arm.pose_world_base)
    assert np.allclose(poses[-1], world_base @ forward_kinematics(end))
    assert np.max(np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)) <= 0.002
    tool = ToolModel(config.gripper, config.sensor)
    body = next(box for box in tool.rigid_boxes(0.08) if box.name == "gripper_body")
    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.005)
    ball.apply_translation((poses[len(poses) // 2] @ body.pose_tcp_box)[:3, 3])
    record = {
        "label": "home",
        "kind": "joints",
        "start_world_tcp": poses[0].tolist(),
        "end_world_tcp": poses[-1].tolist(),
        "width_m": 0.08,
    }
    samples = SurfaceSamples.of_mesh(ball)
    as_line = session_clearances([record], tool, samples, arm)
    assert as_line["min_transit_clearance_by_part_mm"]["gripper_body"] > 0.0
    record |= {"start_joints_rad": start.tolist(), "end_joints_rad": end.tolist()}
    as_joints = session_clearances([record], tool, samples, arm)
    assert as_joints["min_transit_clearance_by_part_mm"]["gripper_body"] <= 0.0


def test_the_approach_is_kept_apart_and_the_window_left_out_there() -> None:
    config = Config()
    tool = ToolModel(config.gripper, config.sensor)
    samples = SurfaceSamples.of_mesh(SPHERE)
    far = turned(0.0, (0.0, 0.0, 0.5)).tolist()
    motions = [
        {"label": label, "start_world_tcp": far, "end_world_tcp": far, "width_m": 0.08}
        for label in ("direct", *TOUCH_LABELS)
    ]
    report = session_clearances(motions, tool, samples, config.robot.arm)
    assert report["transit_motions"] == 1 and report["motions"] == 3
    assert "gelsight_window" not in report["min_approach_clearance_by_part_mm"]
    assert "gelsight_window" in report["min_transit_clearance_by_part_mm"]


# --- the benchmark --------------------------------------------------------------------------------


def test_objects_are_the_categories_or_all_of_them_and_files_are_scaled(tmp_path: Path) -> None:
    assert [o.name for o in safety_objects(["mug", "can"], None)] == ["mug", "can"]
    assert len(safety_objects(None, None)) == 14
    path = tmp_path / "block.stl"
    trimesh.creation.box((1.0, 2.0, 0.5)).export(path)
    (block,) = safety_objects(None, [path], fit_size_m=0.1)
    assert block.name == "block" and block.scale == pytest.approx(0.05)


def test_totals_count_states_stops_and_reasons() -> None:
    def row(state: str, stops: int | None, clearance: float | None, reasons: list[str]) -> dict:
        return {
            "state": state,
            "touches": 2,
            "contacts": 1,
            "protective_stops": stops,
            "stop_reason": "the touch budget is spent" if state == "done" else None,
            "skipped_targets": [{"reason": reason} for reason in reasons],
            "min_transit_clearance_mm": clearance,
            "min_transit_clearance_by_part_mm": {} if clearance is None else {"body": clearance},
        }

    rows = [
        row("done", 0, 12.5, ["part would be 8.9 mm above the table", "too near"]),
        row("fault", 1, -3.0, ["part would be -7.0 mm above the table"]),
        row("error", None, None, []),
    ]
    totals = summarise_safety(rows, SafetySettings(touches=2))
    assert totals["states"] == {"done": 1, "fault": 1, "error": 1}
    assert (totals["faults"], totals["errors"], totals["protective_stops"]) == (1, 1, 1)
    assert totals["min_transit_clearance_mm"] == -3.0
    assert totals["min_transit_clearance_by_part_mm"] == {"body": -3.0}
    assert (totals["touches"], totals["contacts"], totals["contact_fraction"]) == (6, 3, 0.5)
    assert totals["skipped_targets"] == 3
    assert totals["skipped_reasons"] == {"part would be # mm above the table": 2, "too near": 1}
    assert totals["stop_reasons"] == {"the touch budget is spent": 1, "none": 2}
    assert totals["sessions_run"] == rows


def test_a_short_run_reports_each_session_as_it_went(tmp_path: Path) -> None:
    config = Config()
    settings = SafetySettings(touches=2, yaws=1, seed=3)
    rows: list[dict] = []
    result = run_safety_benchmark(
        config,
        safety_objects(["can"], None),
        settings,
        perception_factory=make_cylinder_perception,
        logs_dir=tmp_path,
        progress=rows.append,
    )
    assert result["sessions"] == 1 and len(result["sessions_run"]) == 1
    (row,) = result["sessions_run"]
    assert rows == [row]
    assert set(ROW_KEYS) <= set(row), set(ROW_KEYS) - set(row)
    summary = json.loads((tmp_path / row["session"] / "summary.json").read_text())
    assert row["state"] == summary["state"] == "done", row["error"]
    assert (row["touches"], row["contacts"]) == (summary["touches"], summary["contacts"])
    assert (result["touches"], result["contacts"]) == (summary["touches"], summary["contacts"])
    assert row["touches"] >= 1 and row["protective_stops"] == 0
    assert row["rigid_contacts"] == [] and row["unexpected_forces"] == 0
    assert 0.0 <= row["yaw_deg"] < 360.0
    clearance = result["min_transit_clearance_mm"]
    assert clearance is not None and math.isfinite(clearance) and clearance > 0.0
    assert clearance == row["min_transit_clearance_mm"]
    assert set(row["min_transit_clearance_by_part_mm"]) == set(PARTS)
    assert result["config"] == result["config"] | {"touches": 2, "yaws": 1, "seed": 3}
    json.dumps(result)  # JSON as it is
    assert "can" in format_table(result)


def post_instead_of_the_bottle(config: Config, devices: Devices) -> CylinderPerception:
    """The stand-in perception; on the bottle's session the arm meets a 45 cm post instead,
    which the camera does not show (the estimate is the bottle's): the first transit over the
    estimate hits it."""
    perception = CylinderPerception(config, devices)
    world = devices.world
    if config.sim.object == "bottle" and world is not None:
        post = trimesh.creation.box((0.06, 0.06, 0.45))
        post.apply_translation((0.0, 0.0, 0.225))
        world.object_mesh_world = post
        world.scene_mesh_world = trimesh.util.concatenate([post, world.table_mesh_world])
    return perception


def test_failing_sessions_are_reported_and_the_next_runs(tmp_path: Path) -> None:
    """One session cannot start (no such mesh file), one faults on a protective stop: both
    are reported with their errors, the stop is counted and its transit shows no clearance,
    and the last session still runs."""
    missing = SafetyObject("missing", str(tmp_path / "missing.stl"))
    result = run_safety_benchmark(
        Config(),
        [missing, *safety_objects(["bottle", "can"], None)],
        SafetySettings(touches=1),
        perception_factory=post_instead_of_the_bottle,
        logs_dir=tmp_path,
    )
    error, fault, done = result["sessions_run"]
    assert error["state"] == "error" and "missing.stl" in error["error"]
    assert fault["state"] == "fault" and "protective stop" in fault["error"]
    assert fault["protective_stops"] == 1 and result["protective_stops"] == 1
    assert fault["rigid_contacts"] and result["rigid_contacts"] >= 1
    assert fault["min_transit_clearance_mm"] < 0.0
    assert fault["worst_transit"]["clearance_mm"] == fault["min_transit_clearance_mm"]
    assert done["state"] == "done" and done["protective_stops"] == 0
    assert result["states"] == {"error": 1, "fault": 1, "done": 1}
    assert (result["errors"], result["faults"], result["aborted"]) == (1, 1, 0)
    assert result["min_transit_clearance_mm"] == fault["min_transit_clearance_mm"]
    assert "protective stop" in format_table(result)


# ~16 s here: the learned perception (prior, GelSight calibration, warm-up) and one touch.
def test_a_session_with_the_learned_perception_is_measured(tmp_path: Path) -> None:
    from controller.perception.learned import make_perception

    result = run_safety_benchmark(
        Config(),
        safety_objects(["can"], None),
        SafetySettings(touches=1),
        perception_factory=make_perception,
        logs_dir=tmp_path,
    )
    (row,) = result["sessions_run"]
    summary = json.loads((tmp_path / row["session"] / "summary.json").read_text())
    assert (row["state"], row["touches"], row["contacts"]) == (
        summary["state"],
        summary["touches"],
        summary["contacts"],
    )
    assert set(ROW_KEYS) <= set(row)
    assert row["protective_stops"] == 0, row["protective_stop_parts"]
    clearance = row["min_transit_clearance_mm"]
    assert clearance is not None and math.isfinite(clearance) and clearance > 0.0


def test_runs_split_across_processes_merge_into_one_json(tmp_path: Path) -> None:
    """`bench safety --merge A B` sums the sessions of earlier runs and keeps the least
    clearance over all of them."""
    from controller.cli.main import main

    def run(name: str, clearance_mm: float, contacts: int) -> Path:
        row = {
            "object": name,
            "yaw_deg": 10.0,
            "state": "done",
            "error": None,
            "touches": 10,
            "contacts": contacts,
            "protective_stops": 0,
            "stop_reason": "the touch budget is spent",
            "skipped_targets": [{"reason": "gripper_body would come within 10 mm"}],
            "min_transit_clearance_mm": clearance_mm,
            "min_transit_clearance_by_part_mm": {"gripper_body": clearance_mm},
        }
        path = tmp_path / f"{name}.json"
        config = {"touches": 10, "yaws": 1, "seed": 0, "input": "rgb"}
        path.write_text(json.dumps({"config": config, "sessions_run": [row]}))
        return path

    out = tmp_path / "merged.json"
    assert (
        main(
            [
                "bench",
                "safety",
                "--merge",
                str(run("a", 30.0, 10)),
                str(run("b", 12.5, 8)),
                "--json",
                str(out),
            ]
        )
        == 0
    )
    merged = json.loads(out.read_text())
    assert merged["sessions"] == 2 and merged["touches"] == 20 and merged["contacts"] == 18
    assert merged["min_transit_clearance_mm"] == 12.5
    assert merged["skipped_targets"] == 2
