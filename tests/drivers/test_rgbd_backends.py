"""RGB-D backends at their SDK boundary.

RealSense: the real pyrealsense2 plays back a small recording that the test makes with the SDK's
own software device and recorder. Kinect v2: libfreenect2 cannot be installed here, so the
backend runs against a fake of the pylibfreenect2 surface it uses (tests/fakes/pylibfreenect2.py).
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import fakes.pylibfreenect2 as fake_freenect2
import numpy as np
import pytest
from fakes.realsense_recording import (
    REC_FRAMES,
    REC_INTRINSICS,
    record_realsense,
    recorded_colour,
    recorded_depth_mm,
)

from drivers.base import DeviceConnectionError, DeviceNotConnectedError, DeviceTimeoutError
from drivers.config import CameraConfig
from drivers.rgbd.kinect_v2 import KinectV2Camera
from drivers.rgbd.kinect_v2_worker import resample_nearest
from drivers.rgbd.realsense import RealSenseCamera
from drivers.vendor import MissingSDKError
from models.camera import CameraIntrinsics

# --- RealSense ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def realsense_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record_realsense(tmp_path_factory.mktemp("realsense"))


async def test_realsense_plays_back_aligned_metric_frames(realsense_recording: Path) -> None:
    config = CameraConfig(type="realsense", playback_file=str(realsense_recording))
    camera = RealSenseCamera(config)
    await camera.connect()
    try:
        seen = set()
        async with asyncio.timeout(5.0):
            while len(seen) < 3:
                frame = await camera.read()
                # Which recorded frame: depth encodes it in millimetres, colour in blue. The
                # SDK's syncer may pair neighbouring frames, so each is checked on its own.
                index = round(float(frame.depth_m[0, 10]) * 1000) - 600
                assert 0 <= index < REC_FRAMES
                # Co-located cameras: aligned = recorded, in metres, where the SDK's align
                # gave a value (it leaves one-pixel gaps beside holes and on rounding).
                expected = recorded_depth_mm(index) * 1e-3
                valid = frame.depth_m > 0
                np.testing.assert_allclose(frame.depth_m[valid], expected[valid], atol=1e-6)
                assert valid[:, 4:].mean() > 0.9
                colour_index = int(frame.colour_rgb[0, 0, 2]) // 10
                np.testing.assert_array_equal(frame.colour_rgb, recorded_colour(colour_index))
                seen.add(index)
                await asyncio.sleep(0.01)
    finally:
        await camera.close()
    assert frame.depth_m.dtype == np.float32 and frame.colour_rgb.dtype == np.uint8
    assert frame.depth_m[:, :4].max() == 0.0  # no return stays 0
    assert frame.intrinsics == pytest.approx(REC_INTRINSICS)
    np.testing.assert_allclose(frame.pose_world_camera, config.pose_world_camera())
    assert not camera.is_connected


async def test_realsense_missing_recording_is_a_connection_error(tmp_path: Path) -> None:
    pytest.importorskip("pyrealsense2", exc_type=ImportError)
    camera = RealSenseCamera(CameraConfig(type="realsense", playback_file=str(tmp_path / "x.db3")))
    with pytest.raises(DeviceConnectionError, match="no recording"):
        await camera.connect()
    assert not camera.is_connected


async def test_missing_pyrealsense2_names_the_extra(monkeypatch, tmp_path: Path) -> None:
    # The SDK is imported in the worker process, which gets this process's sys.path: a module
    # that fails as the wheel does without libusb stands in front of the real one.
    (tmp_path / "pyrealsense2.py").write_text(
        'raise ImportError("libusb-1.0.so.0: cannot open shared object file")\n'
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(MissingSDKError, match=r"touchshape\[realsense\].*libusb-1\.0\.so"):
        await RealSenseCamera(CameraConfig(type="realsense")).connect()


# --- Kinect v2 ------------------------------------------------------------------------------------


async def test_kinect_registers_depth_to_colour_in_metres(monkeypatch, tmp_path: Path) -> None:
    record = fake_freenect2.install(monkeypatch, tmp_path)
    camera = KinectV2Camera(CameraConfig(type="kinect_v2", colour_scale=0.5))
    await camera.connect()
    try:
        frame = await camera.read()
    finally:
        await camera.close()
    assert frame.colour_rgb.shape == (540, 960, 3) and frame.depth_m.shape == (540, 960)
    index = int(frame.colour_rgb[0, 0, 0])  # the fake's frame number, in red
    # Nearest samples of the SDK's registered depth ("bigdepth", 1082 rows with a padding row
    # above and below the 1080 colour rows), whole millimetres -> metres, no return -> 0.
    rows = np.floor((np.arange(540) + 0.5) * 2).astype(int)
    cols = np.floor((np.arange(960) + 0.5) * 2).astype(int)
    bigdepth = fake_freenect2.bigdepth_mm(fake_freenect2.depth_mm(index))
    expected = np.round(bigdepth[1:-1][np.ix_(rows, cols)]) / 1000.0
    expected[~np.isfinite(expected)] = 0.0
    np.testing.assert_allclose(frame.depth_m, expected, rtol=1e-6)
    assert frame.depth_m[:, :10].max() == 0.0 and frame.depth_m[270, 480] > 0.7
    # BGRX colour -> RGB, copied before the frames went back to the SDK (which reuses them).
    bgrx = fake_freenect2.colour_bgrx(index)
    np.testing.assert_array_equal(frame.colour_rgb, bgrx[np.ix_(rows, cols)][..., 2::-1])
    assert frame.intrinsics == pytest.approx(
        CameraIntrinsics(1920, 1080, *fake_freenect2.COLOUR_PARAMS).scaled(0.5)
    )
    done = fake_freenect2.read_record(record)
    assert done["released"] == done["delivered"] > 0  # every frame map went back
    assert done["device_state"] == "closed"


async def test_kinect_stall_raises_and_serial_selects_the_device(monkeypatch, tmp_path) -> None:
    scenario = fake_freenect2.Scenario(serials=["000111", "000222"], frames_left=3)
    record = fake_freenect2.install(monkeypatch, tmp_path, scenario)
    config = CameraConfig(type="kinect_v2", serial="000222", max_frame_age_s=0.1)
    camera = KinectV2Camera(config)
    await camera.connect()
    try:
        assert fake_freenect2.read_record(record)["opened_serial"] == "000222"
        await asyncio.sleep(0.3)  # three frames at 100 Hz, then nothing
        with pytest.raises(DeviceTimeoutError, match=r"younger than 0\.1 s"):
            await camera.read(timeout_s=0.1)
    finally:
        await camera.close()


async def test_kinect_open_failures_are_typed(monkeypatch, tmp_path) -> None:
    fake_freenect2.install(monkeypatch, tmp_path, fake_freenect2.Scenario(serials=[]))
    with pytest.raises(DeviceConnectionError, match="no Kinect v2"):
        await KinectV2Camera(CameraConfig(type="kinect_v2")).connect()
    fake_freenect2.install(monkeypatch, tmp_path)
    with pytest.raises(DeviceConnectionError, match=r"999.*found 011223344"):
        await KinectV2Camera(CameraConfig(type="kinect_v2", serial="999")).connect()
    fake_freenect2.install(monkeypatch, tmp_path, fake_freenect2.Scenario(open_delay_s=5.0))
    camera = KinectV2Camera(CameraConfig(type="kinect_v2", open_timeout_s=0.3))
    with pytest.raises(DeviceTimeoutError, match="took over"):
        await camera.connect()  # the worker, stuck in openDevice, is killed
    with pytest.raises(DeviceNotConnectedError):
        await camera.read()


async def test_missing_pylibfreenect2_names_the_extra() -> None:
    with pytest.raises(MissingSDKError, match=r"touchshape\[kinect\].*pylibfreenect2"):
        await KinectV2Camera(CameraConfig(type="kinect_v2")).connect()


def test_resample_nearest_keeps_centres() -> None:
    image = np.arange(16, dtype=np.float32).reshape(4, 4)
    np.testing.assert_array_equal(resample_nearest(image, 2, 2), [[5, 7], [13, 15]])
    assert resample_nearest(image, 4, 4) is image
