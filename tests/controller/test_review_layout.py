"""The review layout, read back from the layout file a recorder writes: the views a reviewer
relies on exist, each shows entities the recording holds (one plot per metric quantity, the
3D views framed on the object frame), and the recording has the one ``touch`` timeline."""

from __future__ import annotations

import subprocess
from collections import defaultdict
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import pytest
import trimesh
from rerun.chunk import RrdReader

from controller.recording import (
    CAMERA_IMAGE_PLANE_M,
    PATCH_ARROW_M,
    SessionRecorder,
    rerun_binary,
    std_colours,
)
from controller.recording_layout import BLUEPRINT_FILE, STD_COLORMAP
from drivers.base import RGBDFrame
from models.camera import CameraIntrinsics
from models.geometry import VoxelGrid

CURRENT = "current estimate (std 0-4 mm)"
VIEWS = {
    "world": "3D",
    "vision estimate": "3D",
    CURRENT: "3D",
    "kinect": "2D",
    "GelSight image": "2D",
    "GelSight height (mm)": "2D",
    "Chamfer distance (mm)": "TimeSeries",
    "F-score @2 mm / @5 mm (0-1)": "TimeSeries",
    "voxels flipped (count)": "TimeSeries",
    "log": "TextLog",
    "legend": "TextDocument",
}
GRID = VoxelGrid(
    resolution=16,
    extent_m=0.2,
    origin_world=(0.5, -0.1, 0.0),
    axes_world=((0.0, -1.0, 0.0), (1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
)


def rows(path: Path, store: Any = None) -> dict[str, list[tuple[list[str], dict[str, Any]]]]:
    """Entity path -> [(timelines, {component column: value})] of every row of a store."""
    reader = RrdReader(path)
    found: dict[str, list[tuple[list[str], dict[str, Any]]]] = defaultdict(list)
    for chunk in reader.stream(store=store(reader) if store else None):
        batch = chunk.to_record_batch()
        columns = {n: batch.column(n).to_pylist() for n in batch.schema.names if ":" in n}
        for row in range(batch.num_rows):
            values = {name: column[row] for name, column in columns.items()}
            found[chunk.entity_path.strip("/")].append((list(chunk.timeline_names), values))
    return found


def views(blueprint: Path) -> dict[str, dict[str, Any]]:
    """View name -> its class, origin, contents query and eye controls, from the layout file."""
    by_id: dict[str, dict[str, Any]] = defaultdict(dict)
    for path, entries in rows(blueprint, lambda reader: reader.blueprints()[0]).items():
        parts = path.split("/")
        if parts[0] != "view":
            continue
        for _, values in entries:
            by_id[parts[1]].update({k: v for k, v in values.items() if v is not None})
    return {
        view["ViewBlueprint:display_name"][0]: {
            "class": view["ViewBlueprint:class_identifier"][0],
            "origin": view["ViewBlueprint:space_origin"][0],
            "contents": view.get("ViewContents:query", ["$origin/**"]),
            "look_target": view.get("EyeControls3D:look_target"),
        }
        for view in by_id.values()
    }


def shown(view: dict[str, Any], entity: str) -> bool:
    """Whether ``entity`` matches the view's contents query (``+``/``-`` rules, last one wins
    among equally specific rules is not needed here: a ``-`` rule always wins)."""
    included = excluded = False
    for rule in view["contents"]:
        exclude = rule.startswith("- ")
        pattern = rule.removeprefix("- ").removeprefix("+ ").replace("$origin", view["origin"])
        pattern = pattern.strip("/")
        match = (
            entity == pattern.removesuffix("/**") or entity.startswith(pattern[:-2])
            if pattern.endswith("/**")
            else entity == pattern
        )
        excluded |= exclude and match
        included |= not exclude and match
    return included and not excluded


def rgbd_frame() -> RGBDFrame:
    k = CameraIntrinsics(width=64, height=48, fx=60.0, fy=60.0, cx=32.0, cy=24.0)
    pose = np.eye(4)
    pose[:3, 3] = (1.2, -0.1, 0.5)
    rng = np.random.default_rng(0)
    return RGBDFrame(
        colour_rgb=rng.integers(0, 255, (48, 64, 3), dtype=np.uint8),
        depth_m=np.full((48, 64), 0.7, np.float32),
        intrinsics=k,
        pose_world_camera=pose,
        timestamp_s=0.0,
    )


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> SessionRecorder:
    """A small session recorded with real Rerun: setup, camera, one touch, scores, meshes."""
    logs = tmp_path_factory.mktemp("logs")
    recorder = SessionRecorder(logs, "layout")
    recorder.log_state("capture", "idle")
    object_mesh = trimesh.creation.box((0.06, 0.06, 0.1))
    object_mesh.apply_translation((0.5, -0.1, 0.05))
    recorder.log_setup(np.eye(4), GRID, object_mesh)
    recorder.log_camera(rgbd_frame())
    estimate = trimesh.creation.icosphere(subdivisions=2, radius=0.04)
    estimate.apply_translation((0.5, -0.1, 0.05))
    recorder.log_estimate_mesh("vision", estimate)
    recorder.log_estimate_mesh("current", estimate)
    for name, value in (("chamfer_mm", 6.0), ("fscore_2mm", 0.3), ("fscore_5mm", 0.8)):
        recorder.log_metric(name, value, touch=0)
    recorder.set_touch(1)
    recorder.log_tactile(np.zeros((24, 32, 3), np.uint8), np.zeros((24, 32), np.float32))
    patch = np.array([[0.46, -0.1 + 0.001 * i, 0.05] for i in range(10)])
    recorder.log_contact_patch(patch, np.tile((-1.0, 0.0, 0.0), (10, 1)))
    recorder.log_touch(
        {
            "touch": 1,
            "target_world": [0.46, -0.1, 0.05],
            "direction_world": [1.0, 0.0, 0.0],
            "contact_point_world": [0.46, -0.1, 0.05],
        },
        np.array([[[0.4, -0.1, 0.05], [0.46, -0.1, 0.05]]]),
    )
    std_m = np.linspace(0.0, 0.004, len(estimate.vertices))
    recorder.log_estimate_mesh("current", estimate, std_m)
    recorder.log_metric("voxels_flipped", 120.0)
    recorder.log_metric("chamfer_mm", 5.5)
    recorder.close()
    return recorder


def test_the_layout_has_the_named_views(session: SessionRecorder) -> None:
    layout = views(session.blueprint_path)
    assert {name: view["class"] for name, view in layout.items()} == VIEWS
    assert session.blueprint_path.name == BLUEPRINT_FILE


def test_each_view_shows_what_the_recording_holds(session: SessionRecorder) -> None:
    layout = views(session.blueprint_path)
    entities = set(rows(session.rrd_path))

    def shown_in(name: str) -> set[str]:
        return {entity for entity in entities if shown(layout[name], entity)}

    # One plot per quantity, every recorded score in exactly one.
    plots = [name for name, kind in VIEWS.items() if kind == "TimeSeries"]
    assert {name: shown_in(name) for name in plots} == {
        "Chamfer distance (mm)": {"metrics/chamfer_mm"},
        "F-score @2 mm / @5 mm (0-1)": {"metrics/fscore/2mm", "metrics/fscore/5mm"},
        "voxels flipped (count)": {"metrics/voxels_flipped"},
    }
    assert {e for e in entities if e.startswith("metrics/")} == set().union(
        *(shown_in(name) for name in plots)
    )
    assert shown_in("vision estimate") == {"world/estimate/vision", "world/ground_truth"}
    current = shown_in(CURRENT)
    assert {"world/estimate/current", "world/ground_truth", "world/touch/contact"} <= current
    assert {"world/contacts/001/points", "world/contacts/001/normals"} <= current
    assert "world/estimate/vision" not in current
    world = shown_in("world")
    assert {"world/kinect", "world/kinect/rgb", "world/voxel_grid", "world/touch/rays"} <= world
    assert not any(entity.startswith("world/estimate") for entity in world)
    assert shown_in("kinect") == {"world/kinect/rgb"}
    assert shown_in("GelSight image") == {"gelsight/image"}
    assert shown_in("GelSight height (mm)") == {"gelsight/height_mm"}
    assert shown_in("log") == {"log"} and shown_in("legend") == {"legend"}


def test_the_3d_views_look_at_the_object_frame(session: SessionRecorder) -> None:
    """The layout file is the same for every configuration: the 3D views look from
    ``world/object``, which the recording places at the grid's object point."""
    layout = views(session.blueprint_path)
    for name in ("world", "vision estimate", CURRENT):
        assert layout[name]["origin"] == "world/object"
        (target,) = layout[name]["look_target"]  # at the object, or beside it towards the camera
        assert np.linalg.norm(target) < 0.25 and 0.0 < target[2] < 0.2
    ((timelines, frame),) = rows(session.rrd_path)["world/object"]
    assert timelines == []  # static
    (translation,) = frame["Transform3D:translation"]
    assert translation == pytest.approx(GRID.origin_world)
    (matrix,) = frame["Transform3D:mat3x3"]
    columns = np.asarray(matrix).reshape(3, 3, order="F")  # Rerun's matrices: column-major
    assert columns == pytest.approx(np.asarray(GRID.axes_world).T)


def test_the_recording_has_only_the_touch_timeline(session: SessionRecorder) -> None:
    timelines = {
        timeline
        for entries in rows(session.rrd_path).values()
        for timeline_names, _ in entries
        for timeline in timeline_names
    }
    assert timelines == {"touch"}
    result = subprocess.run(
        [str(rerun_binary()), "rrd", "verify", str(session.rrd_path)],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stderr


def test_estimates_camera_and_patches_are_recorded(session: SessionRecorder) -> None:
    recorded = rows(session.rrd_path)
    (vision,) = recorded["world/estimate/vision"]
    assert vision[0] == ["touch"] and vision[1]["Mesh3D:albedo_factor"] is not None
    first, refined = recorded["world/estimate/current"]
    assert first[1].get("Mesh3D:vertex_colors") is None
    assert len(refined[1]["Mesh3D:vertex_colors"]) == len(refined[1]["Mesh3D:vertex_positions"])
    pinhole = [values for _, values in recorded["world/kinect"] if values.get("Pinhole:resolution")]
    assert pinhole[0]["Pinhole:image_plane_distance"] == [pytest.approx(CAMERA_IMAGE_PLANE_M)]
    ((_, normals),) = recorded["world/contacts/001/normals"]
    assert len(normals["Arrows3D:vectors"]) == 10
    lengths = np.linalg.norm(normals["Arrows3D:vectors"], axis=1)
    assert lengths == pytest.approx(PATCH_ARROW_M, abs=1e-6)


def test_the_std_colours_run_over_0_to_4_mm() -> None:
    colormap = matplotlib.colormaps[STD_COLORMAP]
    colours = std_colours(np.array([0.0, 0.004, 0.01]))
    assert colours[0] == pytest.approx(np.asarray(colormap(0.0)[:3]) * 255, abs=1)
    assert colours[1] == pytest.approx(np.asarray(colormap(1.0)[:3]) * 255, abs=1)
    assert (colours[2] == colours[1]).all()  # beyond the scale: its end
