"""`touchshape explore`: one exploration session run locally (no Zenoh): a line per touch, then
its summary; log records go to the session's ``session.log`` (and stderr with ``-v``)."""

from __future__ import annotations

import argparse
import asyncio
from dataclasses import replace
from pathlib import Path

from controller.cli.progress import TouchProgress, print_summary
from controller.config import load_config
from controller.request import ExploreRequest


def add_commands(groups: argparse._SubParsersAction) -> None:
    """Add `explore`."""
    explore = groups.add_parser(
        "explore",
        help="run one exploration session locally (no Zenoh) and print its summary",
        epilog="example: touchshape explore --object mug --touches 10",
    )
    explore.add_argument("--config", type=Path, default=None, help="TOML config file")
    explore.add_argument("--object", help="sim object: category or mesh file (default: config)")
    explore.add_argument("--touches", type=int, default=10, help="touch budget (1..100)")
    explore.add_argument(
        "--policy",
        choices=["active", "efficient", "random"],
        default="active",
        help="active: the paper's policy (least confident window); efficient: most expected "
        "uncertainty reduction per second of robot time; random: the baseline",
    )
    explore.add_argument(
        "--update",
        choices=["global", "fused", "prior", "direct"],
        default=None,
        help="how touches change the shape (default: the config's, global)",
    )
    explore.add_argument(
        "--input",
        choices=["auto", "rgb", "rgbd"],
        default="auto",
        help="auto: RGB-D when the camera gives depth (the Kinect v2 and the bench do)",
    )
    explore.set_defaults(handler=_explore, quiet_logging=True)


def _explore(args: argparse.Namespace) -> int:
    from controller.perception.learned import make_perception
    from controller.service import SESSION_LOG_FILE, TouchshapeService

    config = load_config(args.config)
    if args.object:
        config = replace(config, sim=replace(config.sim, object=args.object))
    low, high = ExploreRequest.MAX_TOUCHES_RANGE
    if not low <= args.touches <= high:
        raise ValueError(f"--touches must be in {low}..{high}")
    request = ExploreRequest(
        max_touches=args.touches,
        policy=args.policy,
        update=args.update or config.models.update,
        input=args.input,
        prior=config.models.prior,
    )

    async def run() -> dict:
        progress = TouchProgress(request.max_touches, scored=False)
        service = TouchshapeService(config, make_perception, on_publish=progress)
        await service.start()
        try:
            # Only the simulated bench knows the true shape: then each touch line waits for
            # its score.
            progress.scored = service.devices is not None and service.devices.world is not None
            print(
                f"exploring {config.sim.object if progress.scored else 'the object'}: "
                f"{request.max_touches} touches, {request.policy} policy, "
                f"{request.update} update, {request.input} input"
            )
            session_id = service.start_session(request)
            print(f"session {session_id}: log {service.logs_dir / session_id / SESSION_LOG_FILE}")
            summary = await service.wait_session()
        finally:
            await service.stop()
            progress.finish()
        assert summary is not None
        return summary

    summary = asyncio.run(run())
    print_summary(summary)
    return 0 if summary["state"] == "done" else 1
