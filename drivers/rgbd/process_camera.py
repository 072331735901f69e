"""RGB-D cameras whose SDK runs in a worker process.

The vendor bindings (pyrealsense2, pylibfreenect2) hold the GIL inside blocking calls: measured
with pyrealsense2 2.59.1, ``pipeline.start`` with no camera stalls every Python thread for 15 s;
pylibfreenect2's Cython wrappers call ``openDevice`` and ``waitForNewFrame`` without releasing
it. A thread cannot keep the event loop responsive then, so the SDK lives in a spawned process
(``drivers.rgbd.realsense_worker``, ``drivers.rgbd.kinect_v2_worker``) and a thread here only
waits on the pipe from it, keeping the newest frame for ``read`` (with a max-age check).

The worker protocol, on a multiprocessing pipe: ``("ready",)`` once streaming, then
``("frame", colour_rgb uint8 HxWx3, depth_m float32 HxW, (width, height, fx, fy, cx, cy))`` per
registered frame, or ``("error", kind, message)`` (kind "ImportError" for a missing SDK). Any
message from the driver, or the pipe closing, makes the worker stop its device and exit.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import time
from collections.abc import Callable
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.base import (
    DeviceConnectionError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    RGBDCamera,
    RGBDFrame,
)
from drivers.config import CameraConfig
from drivers.latest_frame import LatestFrameReader
from drivers.vendor import MissingSDKError
from models.camera import CameraIntrinsics

log = logging.getLogger(__name__)

POLL_S = 0.05
"""Longest wait on the worker's pipe per grab, so that close() is noticed quickly."""
STOP_TIMEOUT_S = 2.0
"""How long the worker gets to stop its device before it is killed."""
KILL_NOW_S = 0.1
"""After a failed start there is no stream to wind down: kill the worker almost at once."""

Frame = tuple[NDArray[np.uint8], NDArray[np.float32], CameraIntrinsics]


class WorkerProcessCamera(RGBDCamera):
    """Runs ``target(connection, *args)`` in a spawned process and serves its frames."""

    def __init__(
        self,
        config: CameraConfig,
        *,
        name: str,
        target: Callable[..., None],
        args: tuple[Any, ...],
        missing_sdk: str,
    ) -> None:
        """``missing_sdk`` is the message for a worker that cannot import its SDK (name the
        extra to install)."""
        self.config = config
        self.name = name
        self.pose_world_camera = config.pose_world_camera()
        self._target = target
        self._args = args
        self._missing_sdk = missing_sdk
        self._reader: LatestFrameReader[Frame] | None = None

    async def connect(self) -> None:
        """Start the worker and wait (``open_timeout_s``) until it streams."""
        if self._reader is not None:
            return
        # spawn, not fork: forking a process that runs threads and an event loop is unsafe.
        context = multiprocessing.get_context("spawn")
        ours, theirs = context.Pipe()
        process = context.Process(
            target=self._target, args=(theirs, *self._args), name=f"touchshape {self.name}"
        )
        process.daemon = True
        await asyncio.to_thread(process.start)
        theirs.close()
        try:
            await self._wait_ready(ours)
        except BaseException:
            await asyncio.to_thread(_stop_worker, process, ours, KILL_NOW_S)
            raise
        self._reader = LatestFrameReader(
            lambda _stop: _receive_frame(ours, self.name),
            lambda: _stop_worker(process, ours, STOP_TIMEOUT_S),
            name=self.name,
        )
        self._reader.start()
        try:
            await self._reader.wait_until(
                lambda: self._reader is not None and self._reader.frames_seen > 0,
                self.config.open_timeout_s,
                "first frame",
            )
        except BaseException:
            await self.close()
            raise
        log.info("%s streaming", self.name)

    async def close(self) -> None:
        reader, self._reader = self._reader, None
        if reader is not None:
            await reader.stop(timeout_s=STOP_TIMEOUT_S + 1.0)

    @property
    def is_connected(self) -> bool:
        return self._reader is not None

    async def read(self, *, timeout_s: float = 2.0) -> RGBDFrame:
        """The newest registered frame, no older than ``max_frame_age_s``."""
        if self._reader is None:
            raise DeviceNotConnectedError(f"{self.name} is not connected")
        (colour, depth, intrinsics), stamp = await self._reader.fresh(
            self.config.max_frame_age_s, timeout_s
        )
        return RGBDFrame(
            colour_rgb=colour,
            depth_m=depth,
            intrinsics=intrinsics,
            pose_world_camera=self.pose_world_camera.copy(),
            timestamp_s=stamp,
        )

    async def _wait_ready(self, connection: Connection) -> None:
        timeout_s = self.config.open_timeout_s
        if not await asyncio.to_thread(connection.poll, timeout_s):
            raise DeviceTimeoutError(f"starting {self.name} took over {timeout_s} s")
        try:
            message = await asyncio.to_thread(connection.recv)
        except EOFError:
            raise DeviceConnectionError(f"the {self.name} worker process exited") from None
        if message[0] == "ready":
            return
        _, kind, text = message
        if kind == "ImportError":
            raise MissingSDKError(f"{self._missing_sdk} ({text})")
        raise DeviceConnectionError(f"{self.name}: {text}")


def _receive_frame(connection: Connection, name: str) -> Frame | None:
    """One frame from the worker, or None after POLL_S without one (reader thread)."""
    try:
        if not connection.poll(POLL_S):
            return None
        message = connection.recv()
    except (EOFError, OSError) as error:
        raise DeviceConnectionError(f"the {name} worker process exited") from error
    if message[0] == "error":
        raise DeviceConnectionError(f"{name}: {message[2]}")
    _, colour, depth_m, (width, height, fx, fy, cx, cy) = message
    return colour, depth_m, CameraIntrinsics(width, height, fx, fy, cx, cy)


def _stop_worker(process: Any, connection: Connection, timeout_s: float) -> None:
    """Ask the worker to stop its device; kill it if it has not within ``timeout_s`` (blocking:
    runs in a thread)."""
    with contextlib.suppress(OSError, ValueError):
        connection.send("stop")
    # Keep reading: a worker blocked sending a frame into a full pipe would not see the stop.
    deadline = time.monotonic() + timeout_s
    while process.is_alive() and time.monotonic() < deadline:
        with contextlib.suppress(OSError, EOFError):
            if connection.poll(0.02):
                connection.recv()
    process.join(max(0.0, deadline - time.monotonic()))
    if process.is_alive():
        log.warning("%s did not stop; killing it", process.name)
        process.kill()
        process.join(1.0)
    connection.close()
