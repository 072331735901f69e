"""A remote client polling the service's ``status`` at a fixed rate, in its own process.

A client thread inside the service's process would share its GIL and cores' time slices with
the service and add its own delays to every reply; a separate process measures what a remote
client sees. The child imports only Zenoh and the messaging config (it starts in a second).
"""

from __future__ import annotations

import multiprocessing
import time
from multiprocessing.connection import Connection
from multiprocessing.synchronize import Event

import zenoh

from controller.config import MessagingConfig
from controller.messaging import zenoh_config

READY = "ready"


def _poll(endpoint: str, key: str, hz: float, results: Connection, stop: Event) -> None:
    """Child process: connect, say ready, then query ``key`` every 1/hz s (one query at a time,
    as a client polling a robot would) until ``stop``; send the round trips (ms, None for a
    query without a reply)."""
    client = zenoh.open(zenoh_config(MessagingConfig(listen=(), connect=(endpoint,))))
    try:
        time.sleep(0.5)  # the routes to the service settle
        results.send(READY)
        round_trips: list[float | None] = []
        period_s, next_s = 1.0 / hz, time.perf_counter()
        while not stop.is_set():
            sent = time.perf_counter()
            replies = list(client.get(key, timeout=5.0))
            answered = any(reply.ok is not None for reply in replies)
            round_trips.append((time.perf_counter() - sent) * 1e3 if answered else None)
            next_s = max(next_s + period_s, time.perf_counter())
            time.sleep(max(0.0, next_s - time.perf_counter()))
        results.send(round_trips)
    finally:
        client.close()


class StatusPoller:
    """Start the polling process with ``start`` (returns once it polls), end it with ``stop``,
    which returns the round trips in ms (None: no reply within 5 s)."""

    def __init__(self, endpoint: str, key: str, hz: float) -> None:
        context = multiprocessing.get_context("spawn")  # no copy of the service's threads
        self._results, self._child_end = context.Pipe(duplex=False)
        self._stop = context.Event()
        self._process = context.Process(
            target=_poll,
            args=(endpoint, key, hz, self._child_end, self._stop),
            name="status-poller",
        )

    def start(self, timeout_s: float = 60.0) -> None:
        self._process.start()
        self._child_end.close()  # the child's now: if it dies, reading here ends (EOFError)
        try:
            ready = self._results.poll(timeout_s) and self._results.recv() == READY
        except EOFError:
            ready = False
        if not ready:
            self._process.kill()
            self._process.join()
            raise RuntimeError(
                f"the status poller process did not start polling within {timeout_s} s"
                f" (exit code {self._process.exitcode})"
            )

    def stop(self) -> list[float | None]:
        self._stop.set()
        round_trips: list[float | None] = self._results.recv()
        self._process.join(10.0)
        return round_trips
