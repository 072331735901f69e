"""`touchshape explore`: one exploration session run locally (no Zenoh), and its summary."""

from __future__ import annotations

import argparse
import asyncio
from dataclasses import replace
from pathlib import Path

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
    explore.add_argument("--policy", choices=["active", "random"], default="active")
    explore.add_argument(
        "--update",
        choices=["fused", "prior", "direct"],
        default=None,
        help="how touches change the shape (default: the config's, fused)",
    )
    explore.add_argument("--input", choices=["rgb", "rgbd"], default="rgb")
    explore.set_defaults(handler=_explore)


def _explore(args: argparse.Namespace) -> int:
    from controller.perception.learned import make_perception
    from controller.service import TouchshapeService

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
        service = TouchshapeService(config, make_perception)
        await service.start()
        try:
            service.start_session(request)
            summary = await service.wait_session()
        finally:
            await service.stop()
        assert summary is not None
        return summary

    summary = asyncio.run(run())
    _print_summary(summary)
    return 0 if summary["state"] == "done" else 1


def _print_summary(summary: dict) -> None:
    rows = [
        ("session", summary["session"]),
        ("result", summary["state"] + (f" ({summary['error']})" if summary["error"] else "")),
        ("touches", f"{summary['touches']} ({summary['contacts']} contacts)"),
        ("compute / motion", f"{summary['compute_s']:.1f} s / {summary['motion_s']:.1f} s"),
    ]
    for metric, values in summary.get("metrics", {}).items():
        rows.append((metric, " -> ".join(f"{v:.2f}" for v in (values[0], values[-1]))))
    rows += [(name, path) for name, path in summary.get("artifacts", {}).items()]
    width = max(len(name) for name, _ in rows)
    for name, value in rows:
        print(f"{name:<{width}}  {value}")
