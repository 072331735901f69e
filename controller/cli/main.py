"""`touchshape` command line: thin commands over library code, grouped by what they act on."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import dataclasses
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from controller.cli.bench import add_explore_benchmark_command
from controller.cli.calibrate import add_calibrate_commands
from controller.cli.check import add_check_commands
from controller.cli.check_devices import add_hardware_commands
from controller.cli.gelsight import add_gelsight_commands
from controller.cli.output import print_json
from controller.cli.prior import add_prior_commands
from controller.cli.serve import add_service_commands
from controller.config import ConfigError, config_to_toml, load_config
from drivers.base import DeviceError

log = logging.getLogger("touchshape")

EXAMPLES = """examples:
  touchshape sim snapshot --object mug --out logs/snapshot
  touchshape sim snapshot --object path/to/model.obj --up-axis y --out logs/snapshot
  touchshape config show --config configs/sim.toml
  touchshape bench sim --json logs/bench_sim.json
  touchshape sim ur-controller --host 127.0.0.2
  touchshape check arm --host 127.0.0.2
  touchshape sim wsg --pty            (then: touchshape check gripper --serial /dev/pts/N)
  touchshape check tactile --device 0
  touchshape gelsight calibrate --frames even --out logs/gelsight/calib.npz
  touchshape gelsight reconstruct --calib logs/gelsight/calib.npz --frames 1,3 --out rec
  touchshape bench gelsight --json
"""


def _config_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config", type=Path, default=None, help="TOML config file (default: the sim bench)"
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="touchshape",
        description="3D shape perception from vision, touch and shape priors, on a robot.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    groups = parser.add_subparsers(dest="group", required=True, metavar="COMMAND")

    config = groups.add_parser("config", help="show the effective configuration")
    config_commands = config.add_subparsers(dest="command", required=True)
    show = config_commands.add_parser("show", help="print the effective config as TOML")
    _config_argument(show)
    show.set_defaults(handler=_config_show)

    sim = groups.add_parser("sim", help="the simulated bench")
    sim_commands = sim.add_subparsers(dest="command", required=True)
    snapshot = sim_commands.add_parser(
        "snapshot",
        help="write PNGs of the Kinect colour and depth views and one tactile image",
        epilog="example: touchshape sim snapshot --object mug --out logs/snapshot",
    )
    _config_argument(snapshot)
    snapshot.add_argument("--object", help="shape-library category or mesh file (default: config)")
    snapshot.add_argument("--up-axis", default=None, help="up axis of a mesh file (e.g. y)")
    snapshot.add_argument("--seed", type=int, default=None, help="object and noise seed")
    snapshot.add_argument("--out", type=Path, required=True, help="output folder")
    snapshot.set_defaults(handler=_sim_snapshot)
    ur_controller = sim_commands.add_parser(
        "ur-controller",
        help="emulate a UR5 controller (RTDE, dashboard, script port) moving the sim arm",
        epilog="example: touchshape sim ur-controller --host 127.0.0.2  (then: check arm)",
    )
    _config_argument(ur_controller)
    ur_controller.add_argument("--host", default="127.0.0.2", help="loopback address to bind")
    ur_controller.add_argument(
        "--real-time-factor", type=float, default=1.0, help="1 real time, 2 half speed"
    )
    ur_controller.set_defaults(handler=_sim_ur_controller)

    bench = groups.add_parser("bench", help="performance benchmarks (JSON)")
    bench_commands = bench.add_subparsers(dest="command", required=True)
    bench_sim = bench_commands.add_parser(
        "sim", help="time the bench's renderer and tactile simulation per frame"
    )
    _config_argument(bench_sim)
    bench_sim.add_argument("--frames", type=int, default=20, help="frames timed per measurement")
    bench_sim.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    bench_sim.set_defaults(handler=_bench_sim)
    add_prior_commands(groups, bench_commands)
    add_hardware_commands(add_check_commands(groups), sim_commands)
    add_gelsight_commands(groups, bench_commands)
    add_service_commands(groups, bench_commands)
    add_calibrate_commands(groups)
    add_explore_benchmark_command(bench_commands)
    return parser


def _config_show(args: argparse.Namespace) -> int:
    print(config_to_toml(load_config(args.config)), end="")
    return 0


def _sim_snapshot(args: argparse.Namespace) -> int:
    from controller.snapshot import capture_snapshot, save_images

    config = load_config(args.config)
    images = asyncio.run(
        capture_snapshot(config, object_spec=args.object, up_axis=args.up_axis, seed=args.seed)
    )
    for path in save_images(images, args.out):
        print(path)
    return 0


def _sim_ur_controller(args: argparse.Namespace) -> int:
    from drivers.sim.ur_emulator import serve_forever
    from drivers.sim.world import SimWorld

    config = load_config(args.config)
    sim = dataclasses.replace(config.sim, real_time_factor=args.real_time_factor)
    world = SimWorld.from_config(sim, config.robot.arm, config.gripper, config.sensor)
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve_forever(world, config.robot.arm, host=args.host))
    return 0


def _bench_sim(args: argparse.Namespace) -> int:
    from controller.benchmarks.sim import benchmark_sim

    print_json(benchmark_sim(load_config(args.config), frames=args.frames), args.json)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    handler: Callable[[argparse.Namespace], int] = args.handler
    try:
        return handler(args)
    except (ConfigError, FileNotFoundError, ValueError, DeviceError) as error:
        print(f"touchshape: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
