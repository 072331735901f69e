"""GelSight camera through OpenCV: a UVC webcam by index or /dev/v4l/by-id path, or a recorded
video file replayed at the sensor's frame rate (for tests and offline runs).

A reader thread owns the ``cv2.VideoCapture`` and keeps only the newest frame with its arrival
time; ``read`` returns it if it is younger than ``max_frame_age_s`` and otherwise waits for a new
one, then raises DeviceTimeoutError: a stalled camera never passes off an old image as current.
Frames are cropped to the gel area (``crop_px``) and scaled to ``image_width_px`` x
``image_height_px``, so the pad's millimetres per pixel stay what the config says. The no-contact
reference is the mean of the first ``reference_frame_count`` frames after connecting (the pad
is free then).
"""

from __future__ import annotations

import logging
import os
import threading
import time
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from drivers.base import (
    DeviceConnectionError,
    DeviceNotConnectedError,
    TactileFrame,
    TactileSensor,
)
from drivers.config import SensorConfig
from drivers.latest_frame import LatestFrameReader, open_in_thread
from drivers.vendor import import_sdk

log = logging.getLogger(__name__)

READ_FAILURES_BEFORE_LOG = 30
"""Consecutive failed grabs after which the reader logs that the camera stopped delivering."""


class VideoCaptureLike(Protocol):
    """The part of ``cv2.VideoCapture`` this driver uses."""

    def isOpened(self) -> bool: ...
    def read(self) -> tuple[bool, Any]: ...
    def set(self, prop_id: int, value: float) -> bool: ...
    def release(self) -> None: ...


def parse_device(device: str) -> int | str:
    """A camera index ("0") as int, anything else (a /dev path, a video file) as is."""
    return int(device) if device.strip().isdigit() else device


def is_video_file(device: int | str) -> bool:
    return isinstance(device, str) and os.path.isfile(device)


def crop_and_scale(
    image: NDArray[np.uint8], crop_px: tuple[int, int, int, int], size_px: tuple[int, int]
) -> NDArray[np.uint8]:
    """Cut ``crop_px`` = (x, y, width, height) out of a BGR image (all zeros = no crop) and scale
    it to ``size_px`` = (width, height). DeviceConnectionError if the crop is outside the image."""
    x, y, width, height = crop_px
    if width:
        if y + height > image.shape[0] or x + width > image.shape[1]:
            raise DeviceConnectionError(
                f"crop_px {crop_px} is outside the camera's {image.shape[1]}x{image.shape[0]} image"
            )
        image = image[y : y + height, x : x + width]
    if (image.shape[1], image.shape[0]) != size_px:
        cv2 = _cv2()
        image = cv2.resize(image, size_px, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(image)


class GelSightCamera(TactileSensor):
    """The real GelSight (``sensor.type = "opencv"``)."""

    def __init__(
        self,
        config: SensorConfig,
        *,
        open_capture: Callable[[int | str], VideoCaptureLike] | None = None,
    ) -> None:
        """``open_capture`` replaces ``cv2.VideoCapture`` (tests pass fakes of a stalling
        camera); it runs in a thread."""
        self.config = config
        self.device = parse_device(config.device)
        self._open_capture = open_capture
        self._reader: LatestFrameReader[NDArray[np.uint8]] | None = None
        self._reference: NDArray[np.uint8] | None = None

    # --- lifecycle ------------------------------------------------------------------------------

    async def connect(self) -> None:
        """Open the camera in a thread and wait for its first frame (``open_timeout_s``)."""
        if self._reader is not None:
            return
        timeout_s = self.config.open_timeout_s
        capture = await open_in_thread(
            self._open,
            timeout_s,
            what=f"opening GelSight camera {self.device!r}",
            close_late=lambda late: late.release(),
        )
        self._reference = None
        self._reader = LatestFrameReader(
            self._grabber(capture),
            capture.release,
            name=f"GelSight camera {self.device!r}",
            poll_s=min(0.005, 0.25 / self.config.frame_rate_hz),
        )
        self._reader.start()
        try:
            await self._reader.wait_until(
                lambda: self._reader is not None and self._reader.frames_seen > 0,
                timeout_s,
                "first frame",
            )
        except BaseException:
            await self.close()
            raise
        log.info("GelSight camera %r open", self.device)

    async def close(self) -> None:
        """Stop the reader (it releases the capture); waits at most a second for it."""
        reader, self._reader = self._reader, None
        if reader is not None:
            await reader.stop()

    @property
    def is_connected(self) -> bool:
        return self._reader is not None

    # --- frames ---------------------------------------------------------------------------------

    async def read(self, *, timeout_s: float = 1.0) -> TactileFrame:
        """The newest frame, no older than ``max_frame_age_s``; waits up to ``timeout_s`` for a
        fresh one, then DeviceTimeoutError (the camera stalled)."""
        reader = self._require_connected()
        image, stamp = await reader.fresh(self.config.max_frame_age_s, timeout_s)
        return TactileFrame(image_bgr=image, timestamp_s=stamp)

    async def reference(self, *, timeout_s: float = 5.0) -> TactileFrame:
        """Mean of the first ``reference_frame_count`` frames after connecting."""
        reader = self._require_connected()
        count = self.config.reference_frame_count
        await reader.wait_until(lambda: self._reference is not None, timeout_s, f"{count} frames")
        assert self._reference is not None
        return TactileFrame(image_bgr=self._reference, timestamp_s=time.monotonic())

    # --- reader thread --------------------------------------------------------------------------

    def _open(self) -> VideoCaptureLike:
        if self._open_capture is not None:
            capture = self._open_capture(self.device)
        else:
            cv2 = _cv2()
            if isinstance(self.device, str) and not is_video_file(self.device):
                # /dev/video* and /dev/v4l/by-id/* are V4L2 devices: ask V4L2 directly.
                capture = cv2.VideoCapture(self.device, cv2.CAP_V4L2)
            else:
                capture = cv2.VideoCapture(self.device)
        if not capture.isOpened():
            capture.release()
            raise DeviceConnectionError(f"OpenCV cannot open GelSight camera {self.device!r}")
        if not is_video_file(self.device) and self._open_capture is None:
            cv2 = _cv2()
            capture.set(cv2.CAP_PROP_FRAME_WIDTH, self.config.image_width_px)
            capture.set(cv2.CAP_PROP_FRAME_HEIGHT, self.config.image_height_px)
            capture.set(cv2.CAP_PROP_FPS, self.config.frame_rate_hz)
            # One buffered frame at most, so a grab is the newest image, not a queued one.
            capture.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        return capture

    def _grabber(
        self, capture: VideoCaptureLike
    ) -> Callable[[threading.Event], NDArray[np.uint8] | None]:
        """One grab per call; a video file is replayed in a loop at ``frame_rate_hz``, and the
        first frames are averaged into the reference."""
        replay = is_video_file(self.device)
        period_s = 1.0 / self.config.frame_rate_hz
        size = (self.config.image_width_px, self.config.image_height_px)
        count = self.config.reference_frame_count
        reference_sum: NDArray[np.float64] | None = None
        averaged = 0
        next_at = time.monotonic()
        failures = 0

        def grab(stop: threading.Event) -> NDArray[np.uint8] | None:
            nonlocal reference_sum, averaged, next_at, failures
            ok, image = capture.read()
            if not ok:
                failures += 1
                if replay:
                    capture.set(_cv2().CAP_PROP_POS_FRAMES, 0)
                elif failures == READ_FAILURES_BEFORE_LOG:
                    log.error("GelSight camera %r stopped delivering frames", self.device)
                stop.wait(0.005 if replay else period_s)
                return None
            failures = 0
            if replay:
                # A file decodes far faster than a camera: pace it like the sensor.
                next_at = max(next_at + period_s, time.monotonic())
                stop.wait(max(0.0, next_at - time.monotonic()))
            image = crop_and_scale(image, self.config.crop_px, size)
            if averaged < count:
                reference_sum = image + (0.0 if reference_sum is None else reference_sum)
                averaged += 1
                if averaged == count:
                    self._reference = (reference_sum / count).round().astype(np.uint8)
            return image

        return grab

    def _require_connected(self) -> LatestFrameReader[NDArray[np.uint8]]:
        if self._reader is None:
            raise DeviceNotConnectedError("GelSight camera is not connected")
        return self._reader


def _cv2() -> Any:
    return import_sdk("cv2", extra="gelsight", device="GelSight camera")
