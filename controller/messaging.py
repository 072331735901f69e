"""The service's Zenoh API (documented in docs/api.md).

Key expressions under ``touchshape/<id>/``: queryables ``explore``, ``abort``, ``status``;
publications ``state``, ``touch``, ``shape``, ``result``; liveliness token ``alive``. Zenoh calls
its callbacks on its own threads: they only hand the query to the event loop
(``call_soon_threadsafe``), where a handler coroutine answers it, so nothing blocks Zenoh and no
Zenoh call happens inside a callback.
"""

from __future__ import annotations

import asyncio
import json
import logging
import re
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import zenoh

from controller.config import MessagingConfig

log = logging.getLogger(__name__)

Handler = Callable[[bytes], Awaitable[dict[str, Any]]]


class EndpointError(ValueError):
    """The Zenoh session cannot be opened on its endpoints (port in use, bad address)."""


def open_session(messaging: MessagingConfig) -> zenoh.Session:
    """Open (and bind) the Zenoh session; ``EndpointError``, one line naming the endpoints,
    when Zenoh refuses them."""
    endpoints = ", ".join(messaging.listen + messaging.connect) or "(no endpoint)"
    try:
        return zenoh.open(zenoh_config(messaging))
    except zenoh.ZError as error:
        raise EndpointError(f"cannot open Zenoh on {endpoints}: {_zenoh_reason(error)}") from None


def _zenoh_reason(error: zenoh.ZError) -> str:
    """Zenoh's message without its source locations (" at /.../file.rs:61."), on one line."""
    text = re.sub(r"\s+at \S+\.rs:\d+\.?", "", str(error))
    return " ".join(text.split())


def zenoh_config(messaging: MessagingConfig) -> zenoh.Config:
    """A Zenoh config from ours: endpoints, scouting, and optional auth and TLS."""
    config = zenoh.Config()
    config.insert_json5("mode", json.dumps(messaging.mode))
    config.insert_json5("listen/endpoints", json.dumps(list(messaging.listen)))
    config.insert_json5("connect/endpoints", json.dumps(list(messaging.connect)))
    config.insert_json5("scouting/multicast/enabled", json.dumps(messaging.multicast_scouting))
    config.insert_json5("scouting/gossip/enabled", "false")
    auth: dict[str, str] = {}
    if messaging.user:
        auth["user"] = messaging.user
        auth["password"] = _read_secret(messaging.password_file)
    if messaging.credentials_file:
        if not Path(messaging.credentials_file).is_file():
            raise FileNotFoundError(f"credentials file not found: {messaging.credentials_file}")
        auth["dictionary_file"] = messaging.credentials_file
    if auth:
        config.insert_json5("transport/auth/usrpwd", json.dumps(auth))
    tls = {
        "root_ca_certificate": messaging.tls_root_ca_certificate,
        "listen_certificate": messaging.tls_certificate,
        "listen_private_key": messaging.tls_private_key,
        "connect_certificate": messaging.tls_certificate,
        "connect_private_key": messaging.tls_private_key,
    }
    tls = {key: path for key, path in tls.items() if path}
    if tls:
        for path in tls.values():
            if not Path(path).is_file():
                raise FileNotFoundError(f"TLS file not found: {path}")
        tls["enable_mtls"] = messaging.tls_mutual  # type: ignore[assignment]
        config.insert_json5("transport/link/tls", json.dumps(tls))
    return config


def _read_secret(path: str) -> str:
    try:
        return Path(path).read_text(encoding="utf-8").strip()
    except OSError as error:
        raise FileNotFoundError(f"cannot read password file {path}: {error}") from None


class ServiceApi:
    """Declares the service's key expressions on an open Zenoh session and routes queries to
    async handlers on ``loop``. Publishing is called from the event loop."""

    def __init__(
        self,
        session: zenoh.Session,
        robot_id: str,
        loop: asyncio.AbstractEventLoop,
        handlers: dict[str, Handler],
    ) -> None:
        self.prefix = f"touchshape/{robot_id}"
        self._session = session
        self._loop = loop
        self._tasks: set[asyncio.Task[None]] = set()
        self._queryables = [
            session.declare_queryable(f"{self.prefix}/{name}", self._on_query(handler))
            for name, handler in handlers.items()
        ]
        self._publishers = {
            name: session.declare_publisher(f"{self.prefix}/{name}")
            for name in ("state", "touch", "event", "score", "shape", "result")
        }
        self._token = session.liveliness().declare_token(f"{self.prefix}/alive")

    def _on_query(self, handler: Handler) -> Callable[[zenoh.Query], None]:
        def callback(query: zenoh.Query) -> None:
            payload = query.payload.to_bytes() if query.payload is not None else b""
            self._loop.call_soon_threadsafe(self._start_answer, handler, query, payload)

        return callback

    def _start_answer(self, handler: Handler, query: zenoh.Query, payload: bytes) -> None:
        task = self._loop.create_task(self._answer(handler, query, payload))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _answer(self, handler: Handler, query: zenoh.Query, payload: bytes) -> None:
        try:
            try:
                body = await handler(payload)
            except Exception as error:  # a handler bug must not take the service down
                log.exception("query handler failed")
                body = {"error": f"internal error: {error}"}
            query.reply(query.key_expr, json.dumps(body))
        finally:
            query.drop()  # sends the final reply marker now rather than at garbage collection

    def publish_json(self, name: str, body: dict[str, Any]) -> None:
        self._publishers[name].put(json.dumps(body))

    def publish_bytes(self, name: str, payload: bytes) -> None:
        self._publishers[name].put(payload)

    async def close(self) -> None:
        for task in list(self._tasks):
            await task
        self._token.undeclare()
        for queryable in self._queryables:
            queryable.undeclare()
        for publisher in self._publishers.values():
            publisher.undeclare()
