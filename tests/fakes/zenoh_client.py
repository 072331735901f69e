"""A remote user's side of the Zenoh API, for tests: a client session and a free loopback port."""

from __future__ import annotations

import asyncio
import json
import socket
from typing import Any

import zenoh

from controller.config import MessagingConfig
from controller.messaging import zenoh_config


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class Client:
    """A remote user's Zenoh session, collecting what the service publishes."""

    def __init__(self, messaging: MessagingConfig) -> None:
        self.session = zenoh.open(zenoh_config(messaging))
        self.messages: dict[str, list[dict[str, Any]]] = {}
        self._subscriber = self.session.declare_subscriber("touchshape/sim/*", self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        topic = str(sample.key_expr).rsplit("/", 1)[-1]
        self.messages.setdefault(topic, []).append(json.loads(sample.payload.to_string()))

    def query(self, name: str, body: str | bytes = b"") -> list[dict[str, Any]]:
        replies = self.session.get(f"touchshape/sim/{name}", payload=body, timeout=3.0)
        return [json.loads(reply.ok.payload.to_string()) for reply in replies if reply.ok]

    async def aquery(self, name: str, body: str | bytes = b"") -> list[dict[str, Any]]:
        return await asyncio.to_thread(self.query, name, body)

    def close(self) -> None:
        self._subscriber.undeclare()
        self.session.close()
