"""Fakes of ``cv2.VideoCapture`` for camera failures a video file cannot produce."""

from __future__ import annotations

import threading

import numpy as np


class StallingCapture:
    """Delivers ``frames`` frames at ``period_s``, then blocks in ``read`` (a camera that
    stopped streaming) until ``release``."""

    def __init__(self, frames: int, *, period_s: float = 0.01, shape=(48, 64, 3)) -> None:
        self.frames_left = frames
        self.period_s = period_s
        self.shape = shape
        self.released = threading.Event()

    def isOpened(self) -> bool:
        return True

    def read(self):
        if self.frames_left > 0:
            self.frames_left -= 1
            self.released.wait(self.period_s)
            return True, np.full(self.shape, 100, np.uint8)
        self.released.wait(0.05)  # blocked on the driver; polls so the test can end
        return False, None

    def set(self, prop_id: int, value: float) -> bool:
        return True

    def release(self) -> None:
        self.released.set()


class HangingOpen:
    """``open_capture`` that hangs (a USB camera that does not answer) until ``unblock``."""

    def __init__(self) -> None:
        self.unblock = threading.Event()
        self.captures: list[StallingCapture] = []

    def __call__(self, device):
        self.unblock.wait(10.0)
        capture = StallingCapture(0)
        self.captures.append(capture)
        return capture
