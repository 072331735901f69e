"""`touchshape serve` and `touchshape explore`: the service and one local session."""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import logging
import signal
from pathlib import Path

from controller.cli.output import print_json
from controller.config import Config, load_config
from controller.request import ExploreRequest

log = logging.getLogger(__name__)


def add_service_commands(
    groups: argparse._SubParsersAction, bench_commands: argparse._SubParsersAction
) -> None:
    serve = groups.add_parser(
        "serve",
        help="run the service: explore on request over Zenoh (Ctrl-C stops it safely)",
        epilog="example: touchshape serve --listen tcp/127.0.0.1:7447 --robot-id sim",
    )
    serve.add_argument("--config", type=Path, default=None, help="TOML config file")
    serve.add_argument("--listen", action="append", help="Zenoh endpoint to listen on")
    serve.add_argument("--connect", action="append", help="Zenoh endpoint to connect to")
    serve.add_argument("--robot-id", help="robot id in the key expressions touchshape/<id>/...")
    serve.set_defaults(handler=_serve)

    explore = groups.add_parser(
        "explore",
        help="run one exploration session locally (no Zenoh) and print its summary",
        epilog="example: touchshape explore --object mug --touches 10",
    )
    explore.add_argument("--config", type=Path, default=None, help="TOML config file")
    explore.add_argument("--object", help="sim object: category or mesh file (default: config)")
    explore.add_argument("--touches", type=int, default=10, help="touch budget (1..100)")
    explore.add_argument("--policy", choices=["active", "random"], default="active")
    explore.add_argument("--update", choices=["prior", "direct"], default="prior")
    explore.add_argument("--input", choices=["rgb", "rgbd"], default="rgb")
    explore.set_defaults(handler=_explore)

    bench = bench_commands.add_parser(
        "service",
        help="trigger-to-capture latency, compute vs motion time, memory over sessions",
    )
    bench.add_argument("--config", type=Path, default=None, help="TOML config file")
    bench.add_argument("--sessions", type=int, default=20, help="sessions in the memory series")
    bench.add_argument("--touches", type=int, default=3, help="touches per session")
    bench.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    bench.set_defaults(handler=_bench_service)


def _with_overrides(args: argparse.Namespace) -> Config:
    config = load_config(args.config)
    messaging = config.messaging
    if getattr(args, "listen", None):
        messaging = dataclasses.replace(messaging, listen=tuple(args.listen))
    if getattr(args, "connect", None):
        messaging = dataclasses.replace(messaging, connect=tuple(args.connect))
    robot = config.robot
    if getattr(args, "robot_id", None):
        robot = dataclasses.replace(robot, id=args.robot_id)
    sim = config.sim
    if getattr(args, "object", None):
        sim = dataclasses.replace(sim, object=args.object)
    return dataclasses.replace(config, messaging=messaging, robot=robot, sim=sim)


def _serve(args: argparse.Namespace) -> int:
    from controller.perception.learned import make_perception
    from controller.service import TouchshapeService

    config = _with_overrides(args)

    async def run() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        service = TouchshapeService(config, make_perception)
        ready = asyncio.Event()
        serving = asyncio.create_task(service.serve(stop, ready))
        await asyncio.wait(
            {serving, asyncio.create_task(ready.wait())}, return_when=asyncio.FIRST_COMPLETED
        )
        if ready.is_set():
            endpoints = ", ".join(config.messaging.listen + config.messaging.connect)
            print(f"touchshape serving robot '{config.robot.id}' on {endpoints}", flush=True)
        await serving

    asyncio.run(run())
    return 0


def _explore(args: argparse.Namespace) -> int:
    from controller.perception.learned import make_perception
    from controller.service import TouchshapeService

    config = _with_overrides(args)
    low, high = ExploreRequest.MAX_TOUCHES_RANGE
    if not low <= args.touches <= high:
        raise ValueError(f"--touches must be in {low}..{high}")
    request = ExploreRequest(
        max_touches=args.touches,
        policy=args.policy,
        update=args.update,
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


def _bench_service(args: argparse.Namespace) -> int:
    import tempfile

    from controller.benchmarks.service import benchmark_service
    from controller.perception.learned import make_perception

    config = load_config(args.config)
    with tempfile.TemporaryDirectory(prefix="touchshape-bench-") as logs:
        result = benchmark_service(
            config, make_perception, Path(logs), sessions=args.sessions, touches=args.touches
        )
    print_json(result, args.json)
    return 0


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
