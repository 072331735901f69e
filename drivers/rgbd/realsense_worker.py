"""The process that runs pyrealsense2 for ``drivers.rgbd.realsense`` (protocol and why: see
``drivers.rgbd.process_camera``). pyrealsense2 holds the GIL inside its blocking calls (measured
with
2.59.1: ``pipeline.start`` with no camera attached stalls every Python thread for 15 s,
``query_devices`` for 100 ms, ``try_wait_for_frames`` for tens of milliseconds). Only numpy and
pyrealsense2 are imported here, so the process starts quickly.
"""

from __future__ import annotations

import os
from multiprocessing.connection import Connection
from typing import Any

import numpy as np

GRAB_TIMEOUT_MS = 200
"""One wait for a frameset, so that a stop request is seen within this."""


def run(connection: Connection, playback_file: str, serial: str) -> None:
    """Process entry point: start the pipeline, then stream aligned frames until told to stop."""
    try:
        import pyrealsense2 as rs
    except ImportError as error:
        connection.send(("error", "ImportError", str(error)))
        return
    try:
        pipeline, depth_scale = _start(rs, playback_file, serial)
    except (RuntimeError, FileNotFoundError) as error:
        connection.send(("error", type(error).__name__, str(error)))
        return
    align = rs.align(rs.stream.color)
    try:
        connection.send(("ready",))
        while not connection.poll():
            ok, frames = pipeline.try_wait_for_frames(GRAB_TIMEOUT_MS)
            if ok and (message := _aligned(rs, align, frames, depth_scale)) is not None:
                connection.send(message)
    except (BrokenPipeError, EOFError, ConnectionResetError):
        pass  # the driver went away
    finally:
        pipeline.stop()


def _start(rs: Any, playback_file: str, serial: str) -> tuple[Any, float]:
    config = rs.config()
    if playback_file:
        if not os.path.isfile(playback_file):
            raise FileNotFoundError(f"no recording at {playback_file}")
        config.enable_device_from_file(playback_file, repeat_playback=True)
        config.enable_stream(rs.stream.depth)
        config.enable_stream(rs.stream.color)
    else:
        if serial:
            config.enable_device(serial)
        config.enable_stream(rs.stream.depth, rs.format.z16)
        config.enable_stream(rs.stream.color, rs.format.rgb8)
    pipeline = rs.pipeline()
    profile = pipeline.start(config)
    try:
        depth_scale = float(profile.get_device().first_depth_sensor().get_depth_scale())
    except RuntimeError:
        pipeline.stop()
        raise
    return pipeline, depth_scale


def _aligned(rs: Any, align: Any, frames: Any, depth_scale: float) -> tuple[Any, ...] | None:
    aligned = align.process(frames)
    depth, colour = aligned.get_depth_frame(), aligned.get_color_frame()
    if not depth or not colour:
        return None
    image = np.asanyarray(colour.get_data())
    layouts = {
        rs.format.rgb8: lambda: image.copy(),
        rs.format.bgr8: lambda: image[..., ::-1].copy(),
        rs.format.rgba8: lambda: image[..., :3].copy(),
        rs.format.bgra8: lambda: image[..., 2::-1].copy(),
    }
    to_rgb = layouts.get(colour.profile.format())
    if to_rgb is None:
        return ("error", "RuntimeError", f"colour format {colour.profile.format()} unsupported")
    k = colour.profile.as_video_stream_profile().get_intrinsics()
    intrinsics = (k.width, k.height, k.fx, k.fy, k.ppx, k.ppy)
    depth_m = np.asanyarray(depth.get_data()).astype(np.float32) * np.float32(depth_scale)
    return ("frame", to_rgb(), depth_m, intrinsics)
