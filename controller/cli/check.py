"""`touchshape check ...`: bring-up checks users run first on a real robot.

Each check connects to one device, reads its state, makes a small safe motion where relevant,
prints one line per step (``ok`` or ``FAIL`` with the reason) and returns exit code 0 only when
every step passed. They pass against the emulators (`touchshape sim ur-controller`, ...).
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from controller.config import load_config
from drivers.base import DeviceError
from drivers.config import ArmConfig
from drivers.ur5.kinematics import forward_kinematics
from drivers.ur5.rtde_arm import URRtdeArm
from models.geometry import ur_pose_to_matrix

ARM_EPILOG = """examples:
  touchshape check arm --host 192.168.1.10
  touchshape check arm --config configs/real_robot.toml
  touchshape sim ur-controller --host 127.0.0.2 &  touchshape check arm --host 127.0.0.2

Connects through ur-rtde, reads the TCP pose, checks that the controller's TCP equals
robot.arm.tcp_offset, then moves the TCP up by --motion-mm (base +z, 20 mm/s) and back.
"""
CHECK_SPEED_M_S = 0.02
CHECK_ACCELERATION_M_S2 = 0.2
TCP_POSITION_TOLERANCE_M = 1e-3
TCP_ROTATION_TOLERANCE_RAD = 0.01
RETURN_TOLERANCE_M = 5e-4


def add_check_commands(groups: argparse._SubParsersAction) -> argparse._SubParsersAction:
    """Add the `check` group; returns its subcommands so other devices' checks join it."""
    check = groups.add_parser("check", help="bring-up checks of the real devices")
    commands = check.add_subparsers(dest="command", required=True)
    arm = commands.add_parser(
        "arm",
        help="connect to the UR controller, read the pose, make a small motion",
        epilog=ARM_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    arm.add_argument("--config", default=None, help="TOML config file (robot.arm section)")
    arm.add_argument("--host", default=None, help="controller address (overrides the config)")
    arm.add_argument(
        "--motion-mm", type=float, default=10.0, help="up-and-back motion, mm (0: none)"
    )
    arm.set_defaults(handler=_check_arm_command)
    return commands


def _check_arm_command(args: argparse.Namespace) -> int:
    config = load_config(args.config).robot.arm
    config = dataclasses.replace(config, type="ur_rtde", host=args.host or config.host)
    passed = asyncio.run(check_arm(config, motion_m=args.motion_mm / 1e3, report=print))
    return 0 if passed else 1


async def check_arm(config: ArmConfig, *, motion_m: float, report: Callable[[str], None]) -> bool:
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
