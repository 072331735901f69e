"""The process that runs pylibfreenect2 for ``drivers.rgbd.kinect_v2`` (protocol and why: see
``drivers.rgbd.process_camera``; pylibfreenect2's Cython wrappers call libfreenect2 without
releasing the GIL). Only numpy and pylibfreenect2 are imported here, so the process starts quickly.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.base import depth_m_from_mm

COLOUR_SIZE = (1920, 1080)
DEPTH_SIZE = (512, 424)
POLL_S = 0.002
"""Pause between ``hasNewFrame`` polls (frames come every 33 ms); polling, because
``waitForNewFrame`` has no timeout and would not let the worker notice a stop request."""
PIPELINES = {
    "cpu": "CpuPacketPipeline",
    "opengl": "OpenGLPacketPipeline",
    "opencl": "OpenCLPacketPipeline",
}


class KinectError(Exception):
    """A Kinect that cannot be opened or started (reported to the driver)."""


def resample_nearest(image: NDArray[Any], height: int, width: int) -> NDArray[Any]:
    """Nearest-pixel resampling to ``height`` x ``width`` about pixel centres, consistent with
    ``CameraIntrinsics.scaled``; the same array when the size already matches."""
    if image.shape[:2] == (height, width):
        return image
    rows = np.floor((np.arange(height) + 0.5) * image.shape[0] / height).astype(np.intp)
    cols = np.floor((np.arange(width) + 0.5) * image.shape[1] / width).astype(np.intp)
    return image[np.ix_(rows, cols)]


@dataclass
class _Session:
    """An open, started device with its listener and registration buffers."""

    device: Any
    listener: Any
    registration: Any
    undistorted: Any
    registered: Any
    bigdepth: Any
    intrinsics: tuple[int, int, float, float, float, float]
    """Of the delivered (scaled) colour image: width, height, fx, fy, cx, cy in pixels."""
    size: tuple[int, int]

    def close(self) -> None:
        try:
            self.device.stop()
        finally:
            self.device.close()


def run(connection: Connection, serial: str, pipeline: str, colour_scale: float) -> None:
    """Process entry point: open the Kinect, then stream registered frames until told to stop."""
    try:
        import pylibfreenect2 as sdk
    except ImportError as error:
        connection.send(("error", "ImportError", str(error)))
        return
    try:
        session = _open(sdk, serial, pipeline, colour_scale)
    except (KinectError, RuntimeError) as error:
        connection.send(("error", type(error).__name__, str(error)))
        return
    try:
        connection.send(("ready",))
        while not connection.poll():
            if not session.listener.hasNewFrame():
                time.sleep(POLL_S)
                continue
            colour, depth_m = _registered(session)
            connection.send(("frame", colour, depth_m, session.intrinsics))
    except (BrokenPipeError, EOFError, ConnectionResetError):
        pass  # the driver went away
    finally:
        session.close()


def _open(sdk: Any, serial: str, pipeline: str, colour_scale: float) -> _Session:
    """Find the device (by serial, or the first), open it with the packet pipeline, start it."""
    freenect = sdk.Freenect2()
    serials = [freenect.getDeviceSerialNumber(i) for i in range(freenect.enumerateDevices())]
    if not serials:
        raise KinectError("no Kinect v2 found on USB 3")
    names = [s.decode() if isinstance(s, bytes) else str(s) for s in serials]
    if serial and serial not in names:
        # Checked here: the bindings would wrap a NULL device for an absent serial.
        raise KinectError(f"no Kinect v2 with serial {serial}; found {', '.join(names)}")
    chosen = serials[names.index(serial)] if serial else serials[0]
    device = freenect.openDevice(chosen, pipeline=getattr(sdk, PIPELINES[pipeline])())
    try:
        listener = sdk.SyncMultiFrameListener(sdk.FrameType.Color | sdk.FrameType.Depth)
        device.setColorFrameListener(listener)
        device.setIrAndDepthFrameListener(listener)
        if device.start() is False:
            raise KinectError(f"Kinect v2 {names[serials.index(chosen)]} did not start")
        # Camera parameters come from the device once it streams.
        colour = device.getColorCameraParams()
        width, height = round(COLOUR_SIZE[0] * colour_scale), round(COLOUR_SIZE[1] * colour_scale)
        # Scaled about the image corner, as CameraIntrinsics.scaled does.
        intrinsics = (
            width,
            height,
            colour.fx * colour_scale,
            colour.fy * colour_scale,
            (colour.cx + 0.5) * colour_scale - 0.5,
            (colour.cy + 0.5) * colour_scale - 0.5,
        )
        return _Session(
            device=device,
            listener=listener,
            registration=sdk.Registration(device.getIrCameraParams(), colour),
            undistorted=sdk.Frame(*DEPTH_SIZE, 4),
            registered=sdk.Frame(*DEPTH_SIZE, 4),
            bigdepth=sdk.Frame(COLOUR_SIZE[0], COLOUR_SIZE[1] + 2, 4),
            intrinsics=intrinsics,
            size=(width, height),
        )
    except BaseException:
        device.close()
        raise


def _registered(session: _Session) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
    """RGB colour and registered depth (metres, 0 = no return) at the delivered size."""
    frames = session.listener.waitForNewFrame()  # returns at once: hasNewFrame() said so
    try:
        session.registration.apply(
            frames["color"],
            frames["depth"],
            session.undistorted,
            session.registered,
            bigdepth=session.bigdepth,
        )
        width, height = session.size
        # New arrays (arithmetic, a contiguous copy of the reversed channels), made before
        # release: the SDK reuses the frame buffers.
        bgrx = resample_nearest(frames["color"].asarray(), height, width)
        colour = np.ascontiguousarray(bgrx[..., 2::-1])
        bigdepth_mm = session.bigdepth.asarray(np.float32)[1:-1]  # drop the padding rows
        depth_mm = np.array(resample_nearest(bigdepth_mm, height, width))  # a copy: see above
    finally:
        session.listener.release(frames)
    depth_mm[~np.isfinite(depth_mm) | (depth_mm < 0)] = 0.0
    # Whole millimetres: the sensor's precision, and what the session files store.
    return colour, depth_m_from_mm(np.clip(np.round(depth_mm), 0, 65535).astype(np.uint16))
