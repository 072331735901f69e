"""GelSight camera through real OpenCV on a recorded video, and on fakes of a stalling camera.

The video is rendered by the tactile simulation: free-gel frames first (the reference), then a
2 mm ball pressed into the pad, written losslessly (FFV1) so pixels can be compared exactly.
"""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import numpy as np
import pytest
from fakes.capture import HangingOpen, StallingCapture

from drivers.base import DeviceConnectionError, DeviceNotConnectedError, DeviceTimeoutError
from drivers.config import SensorConfig
from drivers.gelsight_camera import GelSightCamera, crop_and_scale, parse_device
from drivers.vendor import MissingSDKError
from models.tactile.sim import GelPadSpec, GelSightSimulator, sphere_cap_indentation_mm

cv2 = pytest.importorskip("cv2", reason="needs the gelsight extra (opencv-python-headless)")

FREE_FRAMES = 6
PRESSED_FRAMES = 6
VIDEO_SIZE = (320, 240)


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, np.ndarray]:
    """A video file of the simulated sensor and its frames (N x H x W x 3, BGR)."""
    spec = GelPadSpec()
    simulator = GelSightSimulator(spec)
    rng = np.random.default_rng(3)
    free = np.zeros(spec.shape, np.float32)
    pressed = sphere_cap_indentation_mm(spec, (320, 240), radius_mm=2.0, depth_mm=0.6)
    frames = [
        cv2.resize(simulator.render_bgr(indentation, rng), VIDEO_SIZE, interpolation=cv2.INTER_AREA)
        for indentation in [free] * FREE_FRAMES + [pressed] * PRESSED_FRAMES
    ]
    path = tmp_path_factory.mktemp("gelsight") / "touch.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, VIDEO_SIZE)
    assert writer.isOpened()
    for frame in frames:
        writer.write(frame)
    writer.release()
    return path, np.stack(frames)


def config_for(path: Path, **overrides) -> SensorConfig:
    values = dict(
        type="opencv",
        device=str(path),
        image_width_px=VIDEO_SIZE[0],
        image_height_px=VIDEO_SIZE[1],
        frame_rate_hz=200.0,
        reference_frame_count=FREE_FRAMES,
    )
    values.update(overrides)
    return SensorConfig(**values)


async def test_reference_is_the_mean_of_the_first_frames(recording) -> None:
    path, frames = recording
    camera = GelSightCamera(config_for(path))
    await camera.connect()
    try:
        reference = await camera.reference(timeout_s=2.0)
    finally:
        await camera.close()
    expected = frames[:FREE_FRAMES].astype(np.float64).mean(axis=0).round().astype(np.uint8)
    np.testing.assert_array_equal(reference.image_bgr, expected)


async def test_reads_are_the_newest_frames_cropped_and_scaled(recording) -> None:
    path, frames = recording
    crop = (40, 30, 240, 180)
    camera = GelSightCamera(config_for(path, crop_px=crop))
    expected = [crop_and_scale(frame, crop, VIDEO_SIZE) for frame in frames]
    seen = set()
    await camera.connect()
    try:
        for _ in range(60):  # 0.3 s at 200 Hz: the 12-frame file replays in a loop
            frame = await camera.read()
            assert frame.image_bgr.shape == (VIDEO_SIZE[1], VIDEO_SIZE[0], 3)
            matches = [i for i, e in enumerate(expected) if np.array_equal(e, frame.image_bgr)]
            assert matches, "every frame is one of the recording's, cropped and scaled"
            seen.add(matches[0] >= FREE_FRAMES)
            await asyncio.sleep(0.005)
        reference = await camera.reference()
    finally:
        await camera.close()
    assert seen == {False, True}
    # The press shows in the middle of the difference image, not at the border.
    pressed = expected[-1].astype(int) - reference.image_bgr.astype(int)
    middle = np.abs(pressed[90:150, 130:190]).mean()
    border = np.abs(pressed[:30, :30]).mean()
    assert middle > 5 * border


async def test_a_stalled_camera_raises_instead_of_returning_an_old_frame() -> None:
    capture = StallingCapture(frames=4, period_s=0.01)
    camera = GelSightCamera(
        SensorConfig(
            type="opencv",
            device="0",
            image_width_px=64,
            image_height_px=48,
            max_frame_age_s=0.1,
            reference_frame_count=2,
        ),
        open_capture=lambda device: capture,
    )
    await camera.connect()
    try:
        assert (await camera.read()).image_bgr.shape == (48, 64, 3)
        await asyncio.sleep(0.2)
        with pytest.raises(DeviceTimeoutError, match=r"no frame younger than 0\.1 s"):
            await camera.read(timeout_s=0.1)
    finally:
        await camera.close()
    assert capture.released.is_set()


async def test_open_timeout_when_the_camera_hangs() -> None:
    hanging = HangingOpen()
    camera = GelSightCamera(
        SensorConfig(type="opencv", device="2", open_timeout_s=0.2), open_capture=hanging
    )
    with pytest.raises(DeviceTimeoutError, match=r"took over 0\.2 s"):
        await camera.connect()
    assert not camera.is_connected
    hanging.unblock.set()
    await asyncio.sleep(0.05)
    assert hanging.captures[0].released.is_set()  # the late capture is not leaked


async def test_open_errors_are_typed(recording, tmp_path) -> None:
    with pytest.raises(DeviceConnectionError, match="cannot open"):
        await GelSightCamera(config_for(tmp_path / "missing.avi")).connect()
    path, _ = recording
    camera = GelSightCamera(config_for(path, crop_px=(300, 0, 100, 100)))
    with pytest.raises(DeviceConnectionError, match="outside"):
        await camera.connect()
    assert not camera.is_connected
    with pytest.raises(DeviceNotConnectedError):
        await camera.read()


def test_device_strings() -> None:
    assert parse_device("0") == 0
    assert parse_device("/dev/v4l/by-id/usb-GelSight-video-index0") == (
        "/dev/v4l/by-id/usb-GelSight-video-index0"
    )
    with pytest.raises(ValueError, match="crop_px"):
        SensorConfig(crop_px=(0, 0, 10, 0))


def test_missing_opencv_names_the_extra(monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "cv2", None)
    with pytest.raises(MissingSDKError, match=r"touchshape\[gelsight\]"):
        crop_and_scale(np.zeros((4, 4, 3), np.uint8), (0, 0, 0, 0), (2, 2))
