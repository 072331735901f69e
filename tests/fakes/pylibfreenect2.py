"""A fake of the pylibfreenect2 surface that the Kinect v2 backend uses.

The backend imports the SDK in a worker process, so tests put this file's folder first on
``sys.path`` (the worker inherits it) and steer the fake through the environment:
``FAKE_FREENECT2`` holds a JSON ``Scenario``; the fake writes what happened (serial opened, frames
delivered and released, device state) to the scenario's ``record_path`` as JSON.

Same names, shapes and dtypes as the real bindings: colour frames are 1920x1080 BGRX uint8,
depth frames 512x424 float32 millimetres, ``Registration.apply`` fills a 1920x1082 "bigdepth"
(a padding row above and below, +inf where there is no depth), serials are bytes. Like
libfreenect2 the listener reuses its buffers: after ``release`` a frame's data is overwritten,
so a backend that keeps views instead of copies sees garbage. Frame ``k`` is a pure function of
``k`` (``depth_mm``, ``colour_bgrx``, ``bigdepth_mm``), so a test can recompute what it should
receive; ``k % 256`` is in the colour's red channel.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import os
import threading
import time
from dataclasses import dataclass, field

import numpy as np

COLOUR_PARAMS = (1081.37, 1081.37, 959.5, 539.5)
IR_PARAMS = (365.456, 365.456, 254.878, 205.395)
FRAME_PERIOD_S = 0.01
ENVIRONMENT = "FAKE_FREENECT2"


@dataclass
class Scenario:
    serials: list[str] = field(default_factory=lambda: ["011223344"])
    frames_left: int | None = None
    """Frames to deliver before stalling (None: no limit)."""
    open_delay_s: float = 0.0
    record_path: str = ""

    def to_env(self) -> str:
        return json.dumps(dataclasses.asdict(self))


def _scenario() -> Scenario:
    return Scenario(**json.loads(os.environ.get(ENVIRONMENT, "{}")))


RECORD: dict[str, object] = {"delivered": 0, "released": 0, "device_state": "none"}


def _record(**changes: object) -> None:
    RECORD.update(changes)
    path = _scenario().record_path
    if path:
        # Atomically: the test may read it while the worker streams.
        with open(path + ".tmp", "w") as file:
            json.dump(RECORD, file)
        os.replace(path + ".tmp", path)


def depth_mm(index: int) -> np.ndarray:
    """Depth frame ``index``: a tilted plane 0.7-0.9 m, no return in the 40 left columns."""
    rows = np.arange(424, dtype=np.float32)[:, None]
    depth = np.broadcast_to(700.0 + 0.5 * rows + index, (424, 512)).astype(np.float32)
    depth[:, :40] = 0.0
    return depth


def colour_bgrx(index: int) -> np.ndarray:
    colour = np.empty((1080, 1920, 4), np.uint8)
    colour[..., 0] = (np.arange(1920) % 256)[None, :]
    colour[..., 1] = (np.arange(1080) % 256)[:, None]
    colour[..., 2] = index % 256
    colour[..., 3] = 255
    return colour


def bigdepth_mm(depth: np.ndarray) -> np.ndarray:
    """Depth seen from the colour camera: each colour pixel takes the depth pixel at the same
    field-of-view fraction (co-located cameras), +inf where that has no return; padding rows."""
    rows = (np.arange(1080) * 424) // 1080
    cols = (np.arange(1920) * 512) // 1920
    out = np.full((1082, 1920), np.inf, np.float32)
    sampled = depth[np.ix_(rows, cols)].astype(np.float32)
    sampled[sampled <= 0] = np.inf
    out[1:-1] = sampled
    return out


class FrameType(enum.IntEnum):
    Color = 1
    Ir = 2
    Depth = 4


class CpuPacketPipeline:
    pass


class OpenGLPacketPipeline:
    pass


class OpenCLPacketPipeline:
    pass


class Frame:
    def __init__(self, width: int, height: int, bytes_per_pixel: int, frame_type: int = -1):
        self.width, self.height, self.bytes_per_pixel = width, height, bytes_per_pixel
        shape = (height, width, 4) if frame_type == FrameType.Color else (height, width)
        dtype = np.uint8 if frame_type == FrameType.Color else np.float32
        self._data = np.zeros(shape, dtype)

    def asarray(self, dtype=None) -> np.ndarray:
        if dtype is not None and np.dtype(dtype) != self._data.dtype:
            raise ValueError(f"frame holds {self._data.dtype}, asked for {np.dtype(dtype)}")
        return self._data  # a view of the SDK's buffer, as in the real bindings


class _Params:
    def __init__(self, values: tuple[float, float, float, float]) -> None:
        self.fx, self.fy, self.cx, self.cy = values


class SyncMultiFrameListener:
    def __init__(self, frame_types: int = 7) -> None:
        self.frame_types = frame_types
        self._colour = Frame(1920, 1080, 4, FrameType.Color)
        self._depth = Frame(512, 424, 4, FrameType.Depth)
        self._next_at = time.monotonic()
        self._index = 0
        self._frames_left = _scenario().frames_left
        self.streaming = False

    def hasNewFrame(self) -> bool:
        return self.streaming and self._frames_left != 0 and time.monotonic() >= self._next_at

    def waitForNewFrame(self) -> dict[str, Frame]:
        while not self.hasNewFrame():
            time.sleep(0.001)
        self._next_at = time.monotonic() + FRAME_PERIOD_S
        self._index += 1
        if self._frames_left is not None:
            self._frames_left -= 1
        self._depth._data[:] = depth_mm(self._index)
        self._colour._data[:] = colour_bgrx(self._index)
        _record(delivered=int(RECORD["delivered"]) + 1)  # type: ignore[call-overload]
        return {"color": self._colour, "depth": self._depth}

    def release(self, frames: dict[str, Frame]) -> None:
        frames["color"]._data[:] = 7  # buffers are reused by the SDK
        frames["depth"]._data[:] = np.nan
        _record(released=int(RECORD["released"]) + 1)  # type: ignore[call-overload]


class Registration:
    def __init__(self, ir_params: _Params, colour_params: _Params) -> None:
        self.ir, self.colour = ir_params, colour_params

    def apply(
        self,
        colour: Frame,
        depth: Frame,
        undistorted: Frame,
        registered: Frame,
        enable_filter: bool = True,
        bigdepth: Frame | None = None,
        color_depth_map: np.ndarray | None = None,
    ) -> None:
        undistorted._data[:] = depth.asarray(np.float32)
        if bigdepth is not None:
            bigdepth._data[:] = bigdepth_mm(depth.asarray(np.float32))


class Freenect2Device:
    def __init__(self, serial: bytes) -> None:
        self.serial = serial
        self._listeners: list[SyncMultiFrameListener] = []

    def setColorFrameListener(self, listener: SyncMultiFrameListener) -> None:
        self._listeners.append(listener)

    def setIrAndDepthFrameListener(self, listener: SyncMultiFrameListener) -> None:
        self._listeners.append(listener)

    def start(self) -> bool:
        for listener in self._listeners:
            listener.streaming = True
        _record(device_state="started")
        return True

    def stop(self) -> bool:
        for listener in self._listeners:
            listener.streaming = False
        _record(device_state="stopped")
        return True

    def close(self) -> bool:
        _record(device_state="closed")
        return True

    def getColorCameraParams(self) -> _Params:
        return _Params(COLOUR_PARAMS)

    def getIrCameraParams(self) -> _Params:
        return _Params(IR_PARAMS)


class Freenect2:
    def enumerateDevices(self) -> int:
        return len(_scenario().serials)

    def getDeviceSerialNumber(self, index: int) -> bytes:
        return _scenario().serials[index].encode()

    def openDevice(self, serial: bytes | str, pipeline: object = None) -> Freenect2Device:
        # The real call blocks in USB setup, holding the GIL.
        threading.Event().wait(_scenario().open_delay_s)
        serial = serial.encode() if isinstance(serial, str) else serial
        # The real bindings wrap a NULL device here (a crash later): backends must check
        # the serial against the enumerated ones first.
        assert serial.decode() in _scenario().serials, f"openDevice({serial!r}) of an absent device"
        _record(opened_serial=serial.decode(), device_state="open")
        return Freenect2Device(serial)


def install(monkeypatch, record_dir, scenario: Scenario | None = None):
    """Make the worker process import this fake as ``pylibfreenect2`` with ``scenario``;
    returns the path of the JSON record it writes."""
    from pathlib import Path

    scenario = scenario or Scenario()
    scenario.record_path = str(Path(record_dir) / "freenect2_record.json")
    monkeypatch.setenv(ENVIRONMENT, scenario.to_env())
    monkeypatch.syspath_prepend(os.path.dirname(os.path.abspath(__file__)))
    return Path(scenario.record_path)


def read_record(path) -> dict[str, object]:
    with open(path) as file:
        return json.load(file)
