"""A reader thread that keeps only the newest frame of a blocking camera SDK.

Camera SDKs block in their grab calls (``cv2.VideoCapture.read``, libfreenect2's
``waitForNewFrame``, RealSense's ``wait_for_frames``), so a daemon thread grabs and the event loop
only ever looks at the newest frame and its arrival time: a frame older than the caller's max
age is never returned as current.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections.abc import Callable
from typing import Generic, TypeVar

from drivers.base import DeviceConnectionError, DeviceTimeoutError

T = TypeVar("T")
R = TypeVar("R")

log = logging.getLogger(__name__)


class LatestFrameReader(Generic[T]):
    """Calls ``grab()`` in a loop in a daemon thread; ``grab`` returns a frame or None (no frame
    this time). ``release`` runs in the thread when it ends, so the SDK handle is never closed
    under a grab in progress."""

    def __init__(
        self,
        grab: Callable[[threading.Event], T | None],
        release: Callable[[], None],
        *,
        name: str,
        poll_s: float = 0.005,
    ) -> None:
        self._grab = grab
        self._release = release
        self.name = name
        self.poll_s = poll_s
        self.stop_requested = threading.Event()
        self._lock = threading.Lock()
        self._latest: tuple[T, float] | None = None
        self.frames_seen = 0
        self.error: Exception | None = None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        self._thread.start()

    async def stop(self, timeout_s: float = 1.0) -> bool:
        """Ask the thread to end and wait up to ``timeout_s``; False if it is stuck in a grab
        (it releases the device when the grab returns)."""
        self.stop_requested.set()
        if self._thread.is_alive():
            await asyncio.to_thread(self._thread.join, timeout_s)
        if self._thread.is_alive():
            log.warning("%s is stuck in a grab; it releases the device when done", self.name)
            return False
        return True

    @property
    def latest(self) -> tuple[T, float] | None:
        """The newest frame and its arrival time (``time.monotonic()`` seconds)."""
        with self._lock:
            return self._latest

    async def wait_until(self, condition: Callable[[], bool], timeout_s: float, what: str) -> None:
        """Poll until ``condition()``; DeviceTimeoutError after ``timeout_s`` naming ``what``,
        DeviceConnectionError if the thread died. Polling (not a thread-to-loop callback) keeps
        the thread free of any event-loop reference."""
        deadline = time.monotonic() + timeout_s
        while not condition():
            if self.error is not None:
                raise DeviceConnectionError(f"{self.name} failed: {self.error}") from self.error
            if time.monotonic() >= deadline:
                raise DeviceTimeoutError(f"{self.name}: no {what} within {timeout_s} s")
            await asyncio.sleep(self.poll_s)

    async def fresh(self, max_age_s: float, timeout_s: float) -> tuple[T, float]:
        """The newest frame if younger than ``max_age_s``, else the next one within
        ``timeout_s``; DeviceTimeoutError when the device stalled."""

        def is_fresh() -> bool:
            latest = self.latest
            return latest is not None and time.monotonic() - latest[1] <= max_age_s

        await self.wait_until(is_fresh, timeout_s, f"frame younger than {max_age_s} s")
        latest = self.latest
        assert latest is not None
        return latest

    def _run(self) -> None:
        try:
            while not self.stop_requested.is_set():
                frame = self._grab(self.stop_requested)
                if frame is not None:
                    with self._lock:
                        self._latest = (frame, time.monotonic())
                    self.frames_seen += 1
        except Exception as error:  # handed to the awaiting side, which raises it
            log.exception("%s failed", self.name)
            self.error = error
        finally:
            with contextlib.suppress(Exception):
                self._release()


async def open_in_thread(
    opener: Callable[[], R],
    timeout_s: float,
    *,
    what: str,
    close_late: Callable[[R], object],
) -> R:
    """``opener()`` in a thread, bounded by ``timeout_s`` (DeviceTimeoutError naming ``what``).
    A result that arrives after the timeout is closed with ``close_late``, not leaked."""
    task: asyncio.Future[R] = asyncio.ensure_future(asyncio.to_thread(opener))
    try:
        async with asyncio.timeout(timeout_s):
            return await asyncio.shield(task)
    except TimeoutError:
        task.add_done_callback(lambda done: _close_result(done, close_late))
        raise DeviceTimeoutError(f"{what} took over {timeout_s} s") from None


def _close_result(done: asyncio.Future[R], close: Callable[[R], object]) -> None:
    if not done.cancelled() and done.exception() is None:
        with contextlib.suppress(Exception):
            close(done.result())
