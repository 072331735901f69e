"""`touchshape serve`: the service, exploring on request over Zenoh until stopped."""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import signal
from pathlib import Path

from controller.config import Config, ConfigError, load_config
from controller.messaging import open_session
from drivers.config import FieldError

OPTIONS = {"listen": "--listen", "connect": "--connect", "id": "--robot-id"}


def add_commands(groups: argparse._SubParsersAction) -> None:
    """Add `serve`."""
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


def _service_config(args: argparse.Namespace) -> Config:
    """The config with the endpoints and robot id the arguments give."""
    config = load_config(args.config)
    messaging = config.messaging
    robot = config.robot
    try:
        if args.listen:
            messaging = dataclasses.replace(messaging, listen=tuple(args.listen))
        if args.connect:
            messaging = dataclasses.replace(messaging, connect=tuple(args.connect))
        if args.robot_id:
            robot = dataclasses.replace(robot, id=args.robot_id)
    except FieldError as error:
        raise ConfigError(f"{OPTIONS[error.field]}: {error.message}") from None
    return dataclasses.replace(config, messaging=messaging, robot=robot)


def _serve(args: argparse.Namespace) -> int:
    config = _service_config(args)
    # Bind before the slow imports (torch) and before any device connects: a taken port or a
    # bad endpoint is one line (EndpointError), rc 2, within a second or two.
    session = open_session(config.messaging)

    from controller.perception.learned import make_perception
    from controller.service import TouchshapeService

    async def run() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        service = TouchshapeService(config, make_perception)
        ready = asyncio.Event()
        serving = asyncio.create_task(service.serve(stop, ready, session))
        await asyncio.wait(
            {serving, asyncio.create_task(ready.wait())}, return_when=asyncio.FIRST_COMPLETED
        )
        if ready.is_set():
            endpoints = ", ".join(config.messaging.listen + config.messaging.connect)
            print(f"touchshape serving robot '{config.robot.id}' on {endpoints}", flush=True)
        await serving

    asyncio.run(run())
    return 0
