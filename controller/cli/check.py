"""`touchshape check arm|gripper|tactile|camera`: bring-up checks users run first on a real
robot.

Each check connects to one device (from the config, or from the command-line overrides), reads
its state, makes a small safe motion where relevant, prints one line per step (``ok`` or
``FAIL`` with the reason) and returns exit code 0 only when every step passed. They pass
against the emulators (`touchshape sim ur-controller`, `touchshape sim wsg`), a recorded
GelSight video and a RealSense recording.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import time
from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from controller.config import ConfigError, load_config
from drivers.base import DeviceError, GripperState
from drivers.config import ArmConfig, CameraConfig, GripperConfig, SensorConfig
from drivers.ur5.kinematics import forward_kinematics
from drivers.ur5.rtde_arm import URRtdeArm
from models.geometry import ur_pose_to_matrix

Report = Callable[[str], None]

ARM_EPILOG = """examples:
  touchshape check arm --host 192.168.1.10
  touchshape check arm --config configs/real_robot.toml
  touchshape sim ur-controller --host 127.0.0.2 &  touchshape check arm --host 127.0.0.2

Connects through ur-rtde, reads the TCP pose, checks that the controller's TCP equals
robot.arm.tcp_offset, then moves the TCP up by --motion-mm (base +z, 20 mm/s) and back.
"""
GRIPPER_EPILOG = """examples:
  touchshape check gripper --serial /dev/ttyUSB0 --baud 115200
  touchshape check gripper --tcp 192.168.1.20:1000
  touchshape check gripper --config configs/real_robot.toml
  touchshape sim wsg --pty &   (prints the pty to pass to --serial)

Connects, reads width, force and system state, homes the fingers, opens or closes them by
--motion-mm at 20 mm/s under a 10 N force limit and back. Keep the fingers clear.
"""
TACTILE_EPILOG = """examples:
  touchshape check tactile --device 0
  touchshape check tactile --device /dev/v4l/by-id/usb-GelSight_GelSight_Mini-video-index0
  touchshape check tactile --device logs/gelsight/touch.avi

Opens the camera, reads frames for a second (frame rate, age), builds the no-contact reference
(mean of the first sensor.reference_frame_count frames) and checks exposure. Do not touch the gel.
"""
CAMERA_EPILOG = """examples:
  touchshape check camera --config configs/real_robot.toml
  touchshape check camera --type realsense --playback recording.db3

Opens the RGB-D camera, reads a registered frame and reports resolution, intrinsics, the share
of pixels with depth and the median depth.
"""
CHECK_SPEED_M_S = 0.02
CHECK_ACCELERATION_M_S2 = 0.2
TCP_POSITION_TOLERANCE_M = 1e-3
TCP_ROTATION_TOLERANCE_RAD = 0.01
RETURN_TOLERANCE_M = 5e-4

GRIPPER_CHECK_SPEED_M_S = 0.02
GRIPPER_CHECK_FORCE_N = 10.0
MIN_EXPOSURE, MAX_EXPOSURE = 10.0, 245.0
"""Mean 8-bit intensity outside this range: the LEDs are off, the lens covered, or saturated."""
MIN_DEPTH_FRACTION = 0.1


def add_commands(groups: argparse._SubParsersAction) -> None:
    """Add the `check` group: arm, gripper, tactile, camera."""
    check = groups.add_parser("check", help="bring-up checks of the real devices")
    commands = check.add_subparsers(dest="command", required=True)
    raw = argparse.RawDescriptionHelpFormatter
    arm = commands.add_parser(
        "arm",
        help="connect to the UR controller, read the pose, make a small motion",
        epilog=ARM_EPILOG,
        formatter_class=raw,
    )
    arm.add_argument("--config", default=None, help="TOML config file (robot.arm section)")
    arm.add_argument("--host", default=None, help="controller address (overrides the config)")
    arm.add_argument(
        "--motion-mm", type=float, default=10.0, help="up-and-back motion, mm (0: none)"
    )
    arm.set_defaults(handler=_check_arm_command)

    gripper = commands.add_parser(
        "gripper",
        help="connect to the WSG 50, read its state, home, move a little",
        epilog=GRIPPER_EPILOG,
        formatter_class=raw,
    )
    gripper.add_argument("--config", default=None, help="TOML config file ([gripper] section)")
    link = gripper.add_mutually_exclusive_group()
    link.add_argument("--serial", metavar="DEVICE", help="serial port, e.g. /dev/ttyUSB0")
    link.add_argument("--tcp", metavar="HOST:PORT", help="TCP address, e.g. 192.168.1.20:1000")
    gripper.add_argument("--baud", type=int, default=None, help="serial speed (with --serial)")
    gripper.add_argument("--motion-mm", type=float, default=10.0, help="finger motion (0: none)")
    gripper.add_argument("--no-home", action="store_true", help="skip homing")
    gripper.set_defaults(handler=_check_gripper_command)

    tactile = commands.add_parser(
        "tactile",
        help="open the GelSight camera, read frames, build the reference",
        epilog=TACTILE_EPILOG,
        formatter_class=raw,
    )
    tactile.add_argument("--config", default=None, help="TOML config file ([sensor] section)")
    tactile.add_argument(
        "--device", metavar="INDEX_OR_PATH_OR_VIDEO_FILE", help="camera index, path or video"
    )
    tactile.set_defaults(handler=_check_tactile_command)

    camera = commands.add_parser(
        "camera",
        help="open the RGB-D camera and read a registered frame",
        epilog=CAMERA_EPILOG,
        formatter_class=raw,
    )
    camera.add_argument("--config", default=None, help="TOML config file ([cameras.rgbd])")
    camera.add_argument("--type", choices=["kinect_v2", "realsense"], default=None)
    camera.add_argument("--serial", default=None, help="camera serial number")
    camera.add_argument("--playback", metavar="FILE", help="RealSense recording to play back")
    camera.set_defaults(handler=_check_camera_command)


# --- arm ------------------------------------------------------------------------------------------


def _check_arm_command(args: argparse.Namespace) -> int:
    config = load_config(args.config).robot.arm
    config = dataclasses.replace(config, type="ur_rtde", host=args.host or config.host)
    passed = asyncio.run(check_arm(config, motion_m=args.motion_mm / 1e3, report=print))
    return 0 if passed else 1


async def check_arm(config: ArmConfig, *, motion_m: float, report: Report) -> bool:
    """Run the arm's bring-up steps, reporting each; True when all passed. ``motion_m`` is how
    far the TCP moves up (base +z) and back; 0 skips the motion."""
    arm = URRtdeArm(config)
    try:
        await arm.connect()
        info = arm.controller_info
        report(
            f"ok    connected to {config.host}: PolyScope {info['polyscope_version']},"
            f" {info['robot_mode']}, {info['safety_status']}"
        )
        state = await arm.state()
        report(
            f"ok    TCP pose (base) {np.round(state.pose_base_tcp, 4).tolist()},"
            f" joints {np.round(state.joints_rad, 4).tolist()} rad"
        )
        steps = [
            _check("robot powered and running", "RUNNING" in info["robot_mode"]),
            _check(
                "no protective stop",
                not state.protective_stopped,
                "unlock it on the teach pendant, or recover_protective_stop()",
            ),
            _tcp_matches_config(config, state.joints_rad, state.pose_base_tcp),
        ]
        for line in steps:
            report(line)
        if not all(line.startswith("ok") for line in steps):
            return False
        if motion_m > 0.0:
            report(await _up_and_back(arm, state.pose_base_tcp, motion_m))
        report("ok    arm check passed")
        return True
    except DeviceError as error:
        report(f"FAIL  {type(error).__name__}: {error}")
        return False
    finally:
        await arm.close()


async def _up_and_back(arm: URRtdeArm, start: np.ndarray, motion_m: float) -> str:
    up = start + np.array([0.0, 0.0, motion_m, 0.0, 0.0, 0.0])
    timeout_s = 5.0 + 4.0 * motion_m / CHECK_SPEED_M_S
    for target in (up, start):
        await arm.move_linear(
            target,
            speed_m_s=CHECK_SPEED_M_S,
            acceleration_m_s2=CHECK_ACCELERATION_M_S2,
            timeout_s=timeout_s,
        )
    await asyncio.sleep(0.05)  # the next state report after the move
    error_m = float(np.linalg.norm((await arm.state()).pose_base_tcp[:3] - start[:3]))
    if error_m > RETURN_TOLERANCE_M:
        raise DeviceError(f"moved up {motion_m * 1e3:.1f} mm and back, {error_m * 1e3:.2f} mm off")
    return f"ok    moved up {motion_m * 1e3:.1f} mm and back ({error_m * 1e3:.3f} mm off)"


def _check(what: str, passed: bool, advice: str = "") -> str:
    return f"ok    {what}" if passed else f"FAIL  {what}" + (f": {advice}" if advice else "")


def _tcp_matches_config(config: ArmConfig, joints: np.ndarray, pose_base_tcp: np.ndarray) -> str:
    """The controller's TCP pose against forward kinematics with the config's tcp_offset."""
    expected = forward_kinematics(joints) @ ur_pose_to_matrix(config.tcp_offset)
    reported = ur_pose_to_matrix(pose_base_tcp)
    position_m = float(np.linalg.norm(expected[:3, 3] - reported[:3, 3]))
    angle_rad = float(Rotation.from_matrix(expected[:3, :3].T @ reported[:3, :3]).magnitude())
    passed = position_m <= TCP_POSITION_TOLERANCE_M and angle_rad <= TCP_ROTATION_TOLERANCE_RAD
    return _check(
        f"controller TCP matches robot.arm.tcp_offset ({position_m * 1e3:.2f} mm,"
        f" {np.degrees(angle_rad):.2f} deg off)",
        passed,
        f"set the installation's TCP to robot.arm.tcp_offset = {list(config.tcp_offset)}",
    )


# --- gripper --------------------------------------------------------------------------------------


def parse_host_port(text: str) -> tuple[str, int]:
    """Split "HOST:PORT" into (host, port); ConfigError if malformed."""
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit() or not 0 <= int(port) < 65536:
        raise ConfigError(f"expected HOST:PORT, got {text!r}")
    return host, int(port)


def gripper_config_from_args(args: argparse.Namespace) -> GripperConfig:
    config = load_config(args.config).gripper
    if args.serial:
        config = dataclasses.replace(config, type="wsg50_serial", serial_port=args.serial)
    elif args.tcp:
        host, port = parse_host_port(args.tcp)
        config = dataclasses.replace(config, type="wsg50_tcp", host=host, tcp_port=port)
    if args.baud is not None:
        config = dataclasses.replace(config, baudrate=args.baud)
    if config.type == "sim":
        raise ConfigError("no real gripper: pass --serial or --tcp, or a config with gripper.type")
    return config


def _check_gripper_command(args: argparse.Namespace) -> int:
    config = gripper_config_from_args(args)
    passed = asyncio.run(
        check_gripper(config, motion_m=args.motion_mm / 1e3, home=not args.no_home, report=print)
    )
    return 0 if passed else 1


async def check_gripper(
    config: GripperConfig, *, motion_m: float, home: bool, report: Report
) -> bool:
    """Bring-up steps of the WSG 50, reported line by line; True when all passed."""
    from drivers.wsg50.gripper import WSG50Gripper
    from drivers.wsg50.protocol import FAULT_FLAGS, SystemFlag, describe_flags

    gripper = WSG50Gripper(config)
    try:
        await gripper.connect()
        report(f"ok    connected over {gripper.transport.description} (loop echo)")
        state = await gripper.state()
        flags = gripper.system_flags
        report(f"ok    {_describe(state)}, force limit {gripper.force_limit_n:.1f} N")
        report(f"ok    system state: {describe_flags(flags)}")
        faults = flags & FAULT_FLAGS
        if faults:
            report(
                f"FAIL  gripper reports {describe_flags(faults)}: acknowledge a fast stop,"
                " clear other faults on the gripper's web page"
            )
            return False
        if home:
            await gripper.home(timeout_s=20.0)
            report(f"ok    homed: {_describe(await gripper.state())}")
        elif SystemFlag.REFERENCED not in flags:
            report("FAIL  gripper is not referenced: run without --no-home")
            return False
        if motion_m > 0.0:
            start = (await gripper.state()).width_m
            target = start + motion_m if start + motion_m <= config.stroke_m else start - motion_m
            timeout_s = 5.0 + 2.0 * motion_m / GRIPPER_CHECK_SPEED_M_S
            for width in (target, start):
                state = await gripper.move(
                    max(0.0, width),
                    speed_m_s=GRIPPER_CHECK_SPEED_M_S,
                    force_limit_n=min(GRIPPER_CHECK_FORCE_N, config.max_force_n),
                    timeout_s=timeout_s,
                )
                if state.blocked:
                    report(f"FAIL  blocked at {state.width_m * 1e3:.1f} mm: clear the fingers")
                    return False
            report(f"ok    moved {motion_m * 1e3:.1f} mm and back: {_describe(state)}")
        report("ok    gripper check passed")
        return True
    except DeviceError as error:
        report(f"FAIL  {type(error).__name__}: {error}")
        return False
    finally:
        await gripper.close()


def _describe(state: GripperState) -> str:
    return f"width {state.width_m * 1e3:.1f} mm, force {state.force_n:.2f} N"


# --- tactile --------------------------------------------------------------------------------------


def sensor_config_from_args(args: argparse.Namespace) -> SensorConfig:
    config = load_config(args.config).sensor
    if args.device:
        config = dataclasses.replace(config, type="opencv", device=args.device)
    if config.type == "sim":
        raise ConfigError("no real GelSight: pass --device, or a config with sensor.type")
    return config


def _check_tactile_command(args: argparse.Namespace) -> int:
    passed = asyncio.run(check_tactile(sensor_config_from_args(args), report=print))
    return 0 if passed else 1


async def check_tactile(config: SensorConfig, *, report: Report, duration_s: float = 1.0) -> bool:
    """Bring-up steps of the GelSight camera; True when all passed."""
    from drivers.gelsight_camera import GelSightCamera

    camera = GelSightCamera(config)
    try:
        await camera.connect()
        report(f"ok    opened {config.device!r}")
        reference = await camera.reference()
        stamps = set()
        started = time.monotonic()
        while time.monotonic() - started < duration_s:
            frame = await camera.read()
            stamps.add(frame.timestamp_s)
            await asyncio.sleep(0.25 / config.frame_rate_hz)
        rate_hz = len(stamps) / duration_s
        height, width = frame.image_bgr.shape[:2]
        report(
            f"ok    {width}x{height} frames at {rate_hz:.1f} Hz"
            f" (configured {config.frame_rate_hz:g} Hz)"
        )
        exposure = float(reference.image_bgr.mean())
        if not MIN_EXPOSURE <= exposure <= MAX_EXPOSURE:
            report(
                f"FAIL  reference mean intensity {exposure:.0f}: LEDs off, lens covered or"
                " saturated"
            )
            return False
        difference = np.abs(frame.image_bgr.astype(np.int16) - reference.image_bgr).mean()
        report(
            f"ok    reference from {config.reference_frame_count} frames, mean intensity"
            f" {exposure:.0f}; latest frame differs by {difference:.1f} (contact shows as more)"
        )
        if rate_hz < 0.5 * config.frame_rate_hz:
            report(f"FAIL  {rate_hz:.1f} Hz is under half the configured frame rate")
            return False
        report("ok    tactile check passed")
        return True
    except DeviceError as error:
        report(f"FAIL  {type(error).__name__}: {error}")
        return False
    finally:
        await camera.close()


# --- RGB-D camera ---------------------------------------------------------------------------------


def camera_config_from_args(args: argparse.Namespace) -> CameraConfig:
    config = load_config(args.config).cameras.rgbd
    if args.type:
        config = dataclasses.replace(config, type=args.type)
    if args.serial:
        config = dataclasses.replace(config, serial=args.serial)
    if args.playback:
        config = dataclasses.replace(config, type="realsense", playback_file=args.playback)
    if config.type == "sim":
        raise ConfigError("no real camera: pass --type, or a config with cameras.rgbd.type")
    return config


def _check_camera_command(args: argparse.Namespace) -> int:
    passed = asyncio.run(check_camera(camera_config_from_args(args), report=print))
    return 0 if passed else 1


async def check_camera(config: CameraConfig, *, report: Report) -> bool:
    """Bring-up steps of the RGB-D camera; True when all passed."""
    from drivers.base import RGBDCamera

    camera: RGBDCamera
    if config.type == "kinect_v2":
        from drivers.rgbd.kinect_v2 import KinectV2Camera

        camera = KinectV2Camera(config)
    else:
        from drivers.rgbd.realsense import RealSenseCamera

        camera = RealSenseCamera(config)
    try:
        await camera.connect()
        frame = await camera.read()
        k = frame.intrinsics
        report(
            f"ok    {config.type}: {k.width}x{k.height}, fx {k.fx:.1f} fy {k.fy:.1f}"
            f" cx {k.cx:.1f} cy {k.cy:.1f} px"
        )
        valid = frame.depth_m > 0
        fraction = float(valid.mean())
        median = float(np.median(frame.depth_m[valid])) if valid.any() else 0.0
        line = f"{fraction:.0%} of pixels with depth, median {median:.3f} m"
        if fraction < MIN_DEPTH_FRACTION:
            report(f"FAIL  {line}: nothing in range, or the depth stream is off")
            return False
        report(f"ok    {line}")
        report("ok    camera check passed")
        return True
    except DeviceError as error:
        report(f"FAIL  {type(error).__name__}: {error}")
        return False
    finally:
        await camera.close()
