"""`touchshape check gripper|tactile|camera` and `touchshape sim wsg` against the emulator, a
recorded GelSight video, a RealSense recording and the Kinect fake."""

from __future__ import annotations

import asyncio
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import fakes.pylibfreenect2 as fake_freenect2
import numpy as np
import pytest

from controller.cli.check import check_camera, check_gripper, check_tactile
from controller.cli.main import main
from drivers.config import ArmConfig, CameraConfig, GripperConfig, SensorConfig, SimConfig
from drivers.factory import make_devices
from drivers.gelsight_camera import GelSightCamera
from drivers.rgbd.kinect_v2 import KinectV2Camera
from drivers.rgbd.realsense import RealSenseCamera
from drivers.sim.wsg50_emulator import WSGEmulator, bench_gripper
from drivers.wsg50.gripper import WSG50Gripper

CONTACT_WIDTH_M = 0.02  # small openings keep the simulated contact planning cheap
EMULATOR_COMMAND = [sys.executable, "-m", "controller.cli.main", "sim", "wsg"]


def _interruptible() -> None:
    """Ctrl-C reaches the child as it does in a terminal: a shell's background job (how a test
    run may be started) ignores SIGINT, and a child inherits that."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture
def emulator_tcp() -> Iterator[tuple[str, int]]:
    """A WSG 50 emulator on its own event loop in a thread (the CLI runs its own loop)."""
    loop = asyncio.new_event_loop()
    emulator = WSGEmulator(bench_gripper(contact_width_m=CONTACT_WIDTH_M, real_time_factor=0.0))
    address = loop.run_until_complete(emulator.serve_tcp("127.0.0.1", 0))
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    yield address
    asyncio.run_coroutine_threadsafe(emulator.close(), loop).result(5.0)
    loop.call_soon_threadsafe(loop.stop)
    thread.join(5.0)
    loop.close()


@pytest.mark.parametrize("link", ["pty", "tcp"])
async def test_check_gripper_passes_against_the_emulator(link: str) -> None:
    emulator = WSGEmulator(bench_gripper(contact_width_m=CONTACT_WIDTH_M, real_time_factor=0.0))
    if link == "pty":
        config = GripperConfig(type="wsg50_serial", serial_port=await emulator.serve_pty())
    else:
        host, port = await emulator.serve_tcp()
        config = GripperConfig(type="wsg50_tcp", host=host, tcp_port=port)
    lines: list[str] = []
    try:
        passed = await check_gripper(config, motion_m=0.005, home=True, report=lines.append)
        # Opening 25 mm from the homed (closed) fingers reaches the cube: a blocked check.
        blocked: list[str] = []
        assert not await check_gripper(config, motion_m=0.025, home=True, report=blocked.append)
    finally:
        await emulator.close()
    assert passed, lines
    assert all(line.startswith("ok") for line in lines)
    assert "homed: width 0.0 mm" in "\n".join(lines)
    assert blocked[-1].startswith("FAIL  blocked at 20.")


async def test_check_gripper_fails_on_a_silent_peer() -> None:
    server = await asyncio.start_server(lambda r, w: None, "127.0.0.1", 0)
    host, port = server.sockets[0].getsockname()[:2]
    config = GripperConfig(type="wsg50_tcp", host=host, tcp_port=port, timeout_s=0.2)
    lines: list[str] = []
    try:
        assert not await check_gripper(config, motion_m=0.0, home=False, report=lines.append)
    finally:
        server.close()
    assert lines == [lines[0]] and lines[0].startswith("FAIL  DeviceTimeoutError")


def test_cli_check_gripper_over_tcp(emulator_tcp, capsys) -> None:
    host, port = emulator_tcp
    assert main(["check", "gripper", "--tcp", f"{host}:{port}", "--motion-mm", "5"]) == 0
    assert "ok    gripper check passed" in capsys.readouterr().out


def test_cli_check_needs_a_real_device(capsys) -> None:
    assert main(["check", "gripper"]) == 2
    assert "--serial or --tcp" in capsys.readouterr().err
    assert main(["check", "gripper", "--tcp", "nohostport"]) == 2
    assert main(["check", "tactile"]) == 2
    assert main(["check", "camera"]) == 2


def test_cli_sim_wsg_serves_until_interrupted() -> None:
    process = subprocess.Popen(
        [*EMULATOR_COMMAND, "--tcp", "127.0.0.1:0", "--contact-mm", "20"],
        stdout=subprocess.PIPE,
        text=True,
        preexec_fn=_interruptible,
    )
    try:
        assert process.stdout is not None
        line = process.stdout.readline()
        address = line.split("--tcp ")[1].strip()
        host, port = address.rsplit(":", 1)
        config = GripperConfig(type="wsg50_tcp", host=host, tcp_port=int(port))
        lines: list[str] = []
        assert asyncio.run(check_gripper(config, motion_m=0.002, home=True, report=lines.append))
    finally:
        process.send_signal(signal.SIGINT)
        assert process.wait(10.0) == 0


# --- tactile and camera ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def gel_video(tmp_path_factory: pytest.TempPathFactory) -> Path:
    cv2 = pytest.importorskip("cv2", reason="needs the gelsight extra")
    path = tmp_path_factory.mktemp("gel") / "free.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, (160, 120))
    rng = np.random.default_rng(5)
    for _ in range(10):
        writer.write(rng.integers(90, 110, (120, 160, 3), dtype=np.uint8))
    writer.release()
    return path


async def test_check_tactile_on_a_video(gel_video: Path) -> None:
    config = SensorConfig(type="opencv", device=str(gel_video), frame_rate_hz=60.0)
    lines: list[str] = []
    assert await check_tactile(config, report=lines.append, duration_s=0.3), lines
    assert "640x480 frames" in lines[1]
    missing = SensorConfig(type="opencv", device=str(gel_video.with_name("none.avi")))
    lines.clear()
    assert not await check_tactile(missing, report=lines.append)
    assert lines[-1].startswith("FAIL  DeviceConnectionError")


def test_cli_check_tactile(gel_video: Path, capsys) -> None:
    assert main(["check", "tactile", "--device", str(gel_video)]) == 0
    assert "ok    tactile check passed" in capsys.readouterr().out


async def test_check_camera_plays_a_realsense_recording(tmp_path: Path) -> None:
    pytest.importorskip("pyrealsense2", exc_type=ImportError)
    from fakes.realsense_recording import record_realsense

    path = record_realsense(tmp_path)
    lines: list[str] = []
    config = CameraConfig(type="realsense", playback_file=str(path))
    assert await check_camera(config, report=lines.append), lines
    assert "realsense: 64x48" in lines[0] and "median 0.60" in lines[1]


async def test_check_camera_kinect(monkeypatch, tmp_path) -> None:
    fake_freenect2.install(monkeypatch, tmp_path)
    lines: list[str] = []
    assert await check_camera(CameraConfig(type="kinect_v2"), report=lines.append), lines
    assert "kinect_v2: 960x540" in lines[0]


def test_sim_wsg_needs_a_pty_or_an_address() -> None:
    with pytest.raises(SystemExit) as exited:
        main(["sim", "wsg"])
    assert exited.value.code == 2


def test_factory_builds_the_real_backends(rng) -> None:
    devices = make_devices(
        arm=ArmConfig(),
        gripper=GripperConfig(type="wsg50_serial"),
        sensor=SensorConfig(type="opencv"),
        camera=CameraConfig(type="kinect_v2"),
        sim=SimConfig(),
        rng=rng,
    )
    assert isinstance(devices.gripper, WSG50Gripper)
    assert isinstance(devices.tactile, GelSightCamera)
    assert isinstance(devices.camera, KinectV2Camera)
    camera = make_devices(
        arm=ArmConfig(),
        gripper=GripperConfig(type="wsg50_tcp"),
        sensor=SensorConfig(),
        camera=CameraConfig(type="realsense"),
        sim=SimConfig(),
        rng=rng,
    ).camera
    assert isinstance(camera, RealSenseCamera)
