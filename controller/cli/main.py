"""The `touchshape` command line: its top-level groups, each added by its module, and the
entry point."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence

from controller.cli import (
    bench,
    calibrate,
    check,
    config,
    explore,
    gelsight,
    prior,
    replay,
    review,
    serve,
    sessions,
    sim,
)
from controller.config import ConfigError
from drivers.base import DeviceError

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


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="touchshape",
        description="3D shape perception from vision, touch and shape priors, on a robot.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    groups = parser.add_subparsers(dest="group", required=True, metavar="COMMAND")
    for module in (
        config,
        sim,
        bench,
        prior,
        check,
        gelsight,
        serve,
        explore,
        sessions,
        review,
        replay,
        calibrate,
    ):
        module.add_commands(groups)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # A command that prints its own progress (explore, replay) logs to the session's log file
    # only, unless -v: no stderr handler (the null one keeps Python's last-resort one quiet).
    quiet = getattr(args, "quiet_logging", False) and not args.verbose
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        handlers=[logging.NullHandler()] if quiet else None,
    )
    handler: Callable[[argparse.Namespace], int] = args.handler
    try:
        return handler(args)
    except (ConfigError, FileNotFoundError, NotADirectoryError, ValueError, DeviceError) as error:
        print(f"touchshape: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
