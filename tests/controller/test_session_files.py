"""A session folder's raw inputs read back exactly as written, and every broken file named."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from controller.config import load_config
from controller.perception.protocol import TouchMeasurement, TouchTarget
from controller.recording import REQUEST_FILE
from controller.session_files import (
    GELSIGHT_REFERENCE_FILE,
    TOUCHES_FILE,
    SessionFolderError,
    read_session,
    save_camera_frame,
    save_config,
    save_tactile_frame,
    touch_inputs_record,
)
from drivers.base import RGBDFrame, TactileFrame, depth_m_from_mm, depth_mm_from_m
from models.camera import CameraIntrinsics


def _measurement(rng: np.random.Generator) -> TouchMeasurement:
    pose = np.eye(4)
    pose[:3, 3] = rng.uniform(-0.1, 0.1, 3)
    return TouchMeasurement(
        target=TouchTarget(rng.normal(size=3), np.array([0.0, 0.0, -1.0]), 0.25, 0.75),
        contact=True,
        tactile=TactileFrame(rng.integers(0, 256, (24, 32, 3), dtype=np.uint8), 12.5),
        reference=TactileFrame(rng.integers(0, 256, (24, 32, 3), dtype=np.uint8), 0.0),
        pose_world_pad=pose,
        pad_start_world=rng.normal(size=3),
        force_n=4.75,
        gripper_width_m=0.05,
    )


def _write_session(folder: Path, rng: np.random.Generator) -> tuple[RGBDFrame, TouchMeasurement]:
    folder.mkdir(parents=True)
    # Sensor depth comes in whole millimetres (drivers convert through the same functions).
    depth_m = depth_m_from_mm(depth_mm_from_m(rng.uniform(0.0, 1.5, (12, 16))))
    frame = RGBDFrame(
        colour_rgb=rng.integers(0, 256, (12, 16, 3), dtype=np.uint8),
        depth_m=depth_m,
        intrinsics=CameraIntrinsics(16, 12, 20.5, 21.0, 7.5, 5.5),
        pose_world_camera=np.eye(4) + 0.01,
        timestamp_s=3.25,
    )
    measurement = _measurement(rng)
    (folder / REQUEST_FILE).write_text(json.dumps({"max_touches": 1, "update": "fused"}))
    save_config(folder, load_config(None))
    save_camera_frame(folder, frame)
    save_tactile_frame(folder, GELSIGHT_REFERENCE_FILE, measurement.reference)
    record = touch_inputs_record("s", 1, measurement)
    save_tactile_frame(folder, record["gelsight_image"], measurement.tactile)
    (folder / TOUCHES_FILE).write_text(json.dumps(record) + "\n")
    return frame, measurement


def test_inputs_read_back_bit_exact(tmp_path: Path, rng: np.random.Generator) -> None:
    frame, measurement = _write_session(tmp_path / "s", rng)
    recorded = read_session(tmp_path / "s")
    assert np.array_equal(recorded.frame.colour_rgb, frame.colour_rgb)
    assert recorded.frame.depth_m.dtype == np.float32
    assert np.array_equal(recorded.frame.depth_m, frame.depth_m)
    assert recorded.frame.intrinsics == frame.intrinsics
    assert np.array_equal(recorded.frame.pose_world_camera, frame.pose_world_camera)
    assert recorded.config == load_config(None)
    [touch] = recorded.touches
    read = touch.measurement
    assert np.array_equal(read.tactile.image_bgr, measurement.tactile.image_bgr)
    assert np.array_equal(read.reference.image_bgr, measurement.reference.image_bgr)
    assert np.array_equal(read.pose_world_pad, measurement.pose_world_pad)
    assert np.array_equal(read.pad_start_world, measurement.pad_start_world)
    assert np.array_equal(read.target.target_world, measurement.target.target_world)
    assert (read.contact, read.force_n, read.target.uncertainty) == (True, 4.75, 0.75)
    assert touch.record["gripper_width_m"] == read.gripper_width_m == 0.05


@pytest.mark.parametrize(
    ("name", "damage", "message"),
    [
        ("gelsight/touch_001.png", "delete", "missing"),
        ("gelsight/touch_001.png", "garbage", "not a readable PNG"),
        ("gelsight/reference.png", "delete", "missing"),
        ("camera/depth_mm.png", "garbage", "not a readable PNG"),
        ("camera/rgb.png", "delete", "missing"),
        ("camera/camera.json", "garbage", "not JSON"),
        ("config.toml", "garbage", "config.toml"),
        ("request.json", "delete", "missing"),
        ("touches.jsonl", "garbage", "line 1: not JSON"),
    ],
)
def test_a_broken_file_is_named(
    tmp_path: Path, rng: np.random.Generator, name: str, damage: str, message: str
) -> None:
    _write_session(tmp_path / "s", rng)
    path = tmp_path / "s" / name
    if damage == "delete":
        path.unlink()
    else:
        path.write_bytes(b"\x89PNG not really {")
    with pytest.raises(SessionFolderError) as error:
        read_session(tmp_path / "s")
    assert str(path) in str(error.value) and message in str(error.value)


def test_a_wrong_size_depth_image_is_refused(tmp_path: Path, rng: np.random.Generator) -> None:
    frame, _ = _write_session(tmp_path / "s", rng)
    other = RGBDFrame(frame.colour_rgb[:6], frame.depth_m[:6], frame.intrinsics, np.eye(4), 0.0)
    save_camera_frame(tmp_path / "t", other)
    (tmp_path / "s" / "camera" / "depth_mm.png").write_bytes(
        (tmp_path / "t" / "camera" / "depth_mm.png").read_bytes()
    )
    with pytest.raises(SessionFolderError, match=r"depth_mm\.png: uint16 \(6, 16\) image"):
        read_session(tmp_path / "s")


def test_an_image_path_outside_the_folder_is_refused(
    tmp_path: Path, rng: np.random.Generator
) -> None:
    _write_session(tmp_path / "s", rng)
    touches = tmp_path / "s" / TOUCHES_FILE
    record = json.loads(touches.read_text())
    record["gelsight_image"] = "../../etc/passwd"
    touches.write_text(json.dumps(record) + "\n")
    with pytest.raises(SessionFolderError, match="outside the session folder"):
        read_session(tmp_path / "s")


def test_a_touch_line_without_a_pose_is_named(tmp_path: Path, rng: np.random.Generator) -> None:
    _write_session(tmp_path / "s", rng)
    touches = tmp_path / "s" / TOUCHES_FILE
    record = json.loads(touches.read_text())
    record["pose_world_pad"] = [[1, 0], [0, 1]]
    touches.write_text(json.dumps(record) + "\n")
    with pytest.raises(SessionFolderError, match="line 1: 'pose_world_pad' is not a finite"):
        read_session(tmp_path / "s")
