"""The assembled simulated bench: devices from config, camera frames, and the snapshot command."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from controller.cli.main import main
from controller.config import Config
from drivers.base import DeviceNotConnectedError
from drivers.factory import make_devices


def bench_devices(config: Config, **sim_changes):
    return make_devices(
        arm=config.robot.arm,
        gripper=config.gripper,
        sensor=config.sensor,
        camera=config.cameras.rgbd,
        sim=dataclasses.replace(config.sim, **sim_changes),
        rng=np.random.default_rng(0),
    )


async def test_kinect_sees_the_object_at_the_paper_pose() -> None:
    devices = bench_devices(Config(), object="can", seed=3)
    camera = devices.camera
    with pytest.raises(DeviceNotConnectedError):
        await camera.read()
    await devices.connect()
    try:
        first, second = await camera.read(), await camera.read()
    finally:
        await devices.close()
    height, width = first.depth_m.shape
    assert first.colour_rgb.shape == (height, width, 3) == (540, 960, 3)
    pose = first.pose_world_camera
    assert pose[2, 3] == pytest.approx(0.4572)
    tilt_deg = np.degrees(np.arcsin(-pose[2, 2]))  # optical axis below the horizon
    assert tilt_deg == pytest.approx(30.0)
    # The object is in view, and its depth is the camera-to-object distance.
    assert first.silhouette is not None and first.silhouette.sum() > 500
    _, cols = np.nonzero(first.silhouette)
    assert abs(cols.mean() - width / 2) < width * 0.1
    object_depth = np.median(first.depth_m[first.silhouette & (first.depth_m > 0)])
    assert 0.6 < object_depth < 0.8
    # Consecutive frames differ by sensor noise only.
    both = (first.depth_m > 0) & (second.depth_m > 0)
    difference = first.depth_m[both] - second.depth_m[both]
    assert 0.0005 < np.std(difference) < 0.005
    np.testing.assert_array_equal(first.colour_rgb, second.colour_rgb)


async def test_transparent_object_returns_no_depth() -> None:
    config = Config()
    config = dataclasses.replace(
        config,
        cameras=dataclasses.replace(
            config.cameras, rgbd=dataclasses.replace(config.cameras.rgbd, transparent_object=True)
        ),
    )
    devices = bench_devices(config, object="bottle", seed=1)
    await devices.connect()
    try:
        frame = await devices.camera.read()
    finally:
        await devices.close()
    assert frame.silhouette is not None and frame.silhouette.any()
    # Almost all object pixels show the table behind or nothing, never the object itself.
    object_depth = frame.depth_m[frame.silhouette]
    assert np.mean(object_depth == 0) + np.mean(object_depth > 0.75) > 0.95


def test_snapshot_writes_views_and_a_real_touch(tmp_path: Path) -> None:
    assert main(["sim", "snapshot", "--object", "can", "--seed", "2", "--out", str(tmp_path)]) == 0
    names = {p.name for p in tmp_path.iterdir()}
    assert {
        "kinect_colour.png",
        "kinect_depth.png",
        "tactile.png",
        "tactile_reference.png",
    } <= names
    colour = np.asarray(Image.open(tmp_path / "kinect_colour.png"))
    assert colour.shape == (540, 960, 3)
    tactile = np.asarray(Image.open(tmp_path / "tactile.png")).astype(float)
    reference = np.asarray(Image.open(tmp_path / "tactile_reference.png")).astype(float)
    assert tactile.shape == (480, 640, 3)
    # The touch pressed the gel: a region differs from the no-contact frame far beyond the
    # image noise (sigma 1.5 levels: noise alone exceeds 6 levels in ~0.05 % of pixels).
    changed = np.abs(tactile - reference).max(axis=2) > 6
    assert changed.mean() > 0.05


def test_snapshot_of_a_mesh_file(tmp_path: Path) -> None:
    import trimesh

    mesh_path = tmp_path / "sphere.stl"
    trimesh.creation.icosphere(subdivisions=3, radius=0.04).export(mesh_path)
    out = tmp_path / "out"
    assert main(["sim", "snapshot", "--object", str(mesh_path), "--out", str(out)]) == 0
    assert (out / "tactile.png").exists()


def test_snapshot_of_a_corrupt_file_is_a_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "broken.obj"
    bad.write_bytes(b"\x00\x01garbage")
    assert main(["sim", "snapshot", "--object", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "broken.obj" in capsys.readouterr().err
