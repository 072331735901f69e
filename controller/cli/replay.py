"""`touchshape replay`: perception run again on a recorded session, without devices."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from controller.cli.progress import TouchProgress, print_summary
from controller.config import load_config


def add_commands(groups: argparse._SubParsersAction) -> None:
    """Add `replay`."""
    replay = groups.add_parser(
        "replay",
        help="re-run perception on a recorded session's inputs (no devices) as a new session",
        epilog="examples:\n  touchshape replay logs/20261202-101500-a1b2c3\n"
        "  touchshape replay logs/20261202-101500-a1b2c3 --update prior --prior box",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    replay.add_argument("session", type=Path, help="the recorded session's folder")
    replay.add_argument(
        "--update",
        choices=["global", "fused", "prior", "direct"],
        default=None,
        help="how touches change the shape (default: the recorded session's)",
    )
    replay.add_argument("--prior", default=None, help="shape prior (default: the recorded one)")
    replay.add_argument(
        "--logs",
        type=Path,
        default=None,
        help="where the new session goes (default: the config's logs folder)",
    )
    replay.add_argument("--config", type=Path, default=None, help="TOML config (logs folder)")
    replay.set_defaults(handler=_replay, quiet_logging=True)


def _replay(args: argparse.Namespace) -> int:
    from controller.replay import replay_session
    from controller.session_files import SessionFolderError, read_session

    logs_dir = args.logs or Path(load_config(args.config).logging.dir)
    try:
        # Read (and check) before loading the networks: a broken folder fails in a second.
        recorded = read_session(args.session)
        touches = len(recorded.touches)
        progress = TouchProgress(max(touches, 1), scored=recorded.truth_mesh is not None)
        print(f"replaying {args.session}: {touches} touches")
        summary = replay_session(
            recorded, logs_dir, update=args.update, prior=args.prior, on_publish=progress
        )
    except SessionFolderError as error:
        print(f"touchshape: error: {error}", file=sys.stderr)
        return 2
    progress.finish()
    print_summary(summary)
    return 0
