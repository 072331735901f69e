"""`touchshape sim snapshot|ur-controller|wsg`: look at the simulated bench, and emulate the real
devices' controllers on it for the drivers and the bring-up checks."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
from pathlib import Path

from controller.cli.check import parse_host_port
from controller.config import load_config

WSG_EPILOG = """examples:
  touchshape sim wsg --pty
  touchshape sim wsg --tcp 127.0.0.1:1000

The emulated gripper holds its GelSight pad in front of a cube: opening past --contact-mm
presses the gel on it and blocks the axis, as a touch does. Homing closes the fingers.
"""


def add_commands(groups: argparse._SubParsersAction) -> None:
    """Add the `sim` group: snapshot, ur-controller, wsg."""
    sim = groups.add_parser("sim", help="the simulated bench")
    commands = sim.add_subparsers(dest="command", required=True)
    config_help = "TOML config file (default: the sim bench)"
    snapshot = commands.add_parser(
        "snapshot",
        help="write PNGs of the Kinect colour and depth views and one tactile image",
        epilog="example: touchshape sim snapshot --object mug --out logs/snapshot",
    )
    snapshot.add_argument("--config", type=Path, default=None, help=config_help)
    snapshot.add_argument("--object", help="shape-library category or mesh file (default: config)")
    snapshot.add_argument("--up-axis", default=None, help="up axis of a mesh file (e.g. y)")
    snapshot.add_argument("--seed", type=int, default=None, help="object and noise seed")
    snapshot.add_argument("--out", type=Path, required=True, help="output folder")
    snapshot.set_defaults(handler=_snapshot)

    ur_controller = commands.add_parser(
        "ur-controller",
        help="emulate a UR5 controller (RTDE, dashboard, script port) moving the sim arm",
        epilog="example: touchshape sim ur-controller --host 127.0.0.2  (then: check arm)",
    )
    ur_controller.add_argument("--config", type=Path, default=None, help=config_help)
    ur_controller.add_argument("--host", default="127.0.0.2", help="loopback address to bind")
    ur_controller.add_argument(
        "--real-time-factor", type=float, default=1.0, help="1 real time, 2 half speed"
    )
    ur_controller.set_defaults(handler=_ur_controller)

    wsg = commands.add_parser(
        "wsg",
        help="emulate a WSG 50 (binary protocol) on a pty or a TCP port",
        epilog=WSG_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    where = wsg.add_mutually_exclusive_group(required=True)
    where.add_argument("--pty", action="store_true", help="serve on a new pseudo-terminal")
    where.add_argument("--tcp", metavar="HOST:PORT", help="serve on this TCP address")
    wsg.add_argument("--contact-mm", type=float, default=80.0, help="opening at contact, mm")
    wsg.set_defaults(handler=_wsg)


def _snapshot(args: argparse.Namespace) -> int:
    from controller.snapshot import capture_snapshot, save_images

    config = load_config(args.config)
    images = asyncio.run(
        capture_snapshot(config, object_spec=args.object, up_axis=args.up_axis, seed=args.seed)
    )
    for path in save_images(images, args.out):
        print(path)
    return 0


def _ur_controller(args: argparse.Namespace) -> int:
    from drivers.sim.ur_emulator import serve_forever
    from drivers.sim.world import SimWorld

    config = load_config(args.config)
    sim = dataclasses.replace(config.sim, real_time_factor=args.real_time_factor)
    world = SimWorld.from_config(sim, config.robot.arm, config.gripper, config.sensor)
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve_forever(world, config.robot.arm, host=args.host))
    return 0


def _wsg(args: argparse.Namespace) -> int:
    from drivers.sim.wsg50_emulator import WSGEmulator, bench_gripper

    address = parse_host_port(args.tcp) if args.tcp else None

    async def serve() -> None:
        emulator = WSGEmulator(bench_gripper(contact_width_m=args.contact_mm / 1e3))
        try:
            if address is None:
                path = await emulator.serve_pty()
                where, hint = path, f"--serial {path}"
            else:
                host, port = await emulator.serve_tcp(*address)
                where = f"{host}:{port}"
                hint = f"--tcp {where}"
            print(f"WSG 50 emulator on {where}; try: touchshape check gripper {hint}", flush=True)
            await asyncio.Event().wait()
        finally:
            await emulator.close()

    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve())
    return 0
