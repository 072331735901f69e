"""A small RealSense recording made with pyrealsense2's own software device and recorder.

Not a fake: the real SDK writes the file and the backend under test plays it back.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from models.camera import CameraIntrinsics

REC_W, REC_H, REC_FRAMES = 64, 48, 6
REC_PERIOD_S = 0.03
REC_INTRINSICS = CameraIntrinsics(REC_W, REC_H, 60.0, 61.0, 31.5, 23.5)


def recorded_depth_mm(index: int) -> np.ndarray:
    """A 0.6 m plane with a box 10 cm closer in the middle; frame ``index`` shifts the plane
    by ``index`` mm so frames are told apart; a strip without returns on the left."""
    depth = np.full((REC_H, REC_W), 600 + index, np.uint16)
    depth[16:32, 24:40] = 500 + index
    depth[:, :4] = 0
    return depth


def recorded_colour(index: int) -> np.ndarray:
    colour = np.zeros((REC_H, REC_W, 3), np.uint8)
    colour[..., 0] = np.arange(REC_W, dtype=np.uint8)[None, :] * 4
    colour[..., 1] = np.arange(REC_H, dtype=np.uint8)[:, None] * 5
    colour[..., 2] = 10 * index
    return colour


def record_realsense(directory: Path) -> Path:
    """Record REC_FRAMES depth + colour frames from a pyrealsense2 software device."""
    rs = pytest.importorskip("pyrealsense2", exc_type=ImportError)
    device = rs.software_device()
    depth_sensor, colour_sensor = device.add_sensor("Depth"), device.add_sensor("Color")
    intrinsics = rs.intrinsics()
    intrinsics.width, intrinsics.height = REC_W, REC_H
    intrinsics.fx, intrinsics.fy = REC_INTRINSICS.fx, REC_INTRINSICS.fy
    intrinsics.ppx, intrinsics.ppy = REC_INTRINSICS.cx, REC_INTRINSICS.cy
    intrinsics.model, intrinsics.coeffs = rs.distortion.none, [0.0] * 5

    def stream(kind, uid, bytes_per_pixel, pixel_format):
        profile = rs.video_stream()
        profile.type, profile.index, profile.uid = kind, 0, uid
        profile.width, profile.height, profile.fps = REC_W, REC_H, 30
        profile.bpp, profile.fmt, profile.intrinsics = bytes_per_pixel, pixel_format, intrinsics
        return profile

    depth_profile = depth_sensor.add_video_stream(stream(rs.stream.depth, 0, 2, rs.format.z16))
    colour_profile = colour_sensor.add_video_stream(stream(rs.stream.color, 1, 3, rs.format.rgb8))
    depth_sensor.add_read_only_option(rs.option.depth_units, 0.001)
    co_located = rs.extrinsics()
    co_located.rotation, co_located.translation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0], [0.0] * 3
    depth_profile.register_extrinsics_to(colour_profile, co_located)
    device.register_info(rs.camera_info.name, "touchshape test recording")
    # SDK 2.57+ records ROS 2 bags (.db3); older ones ROS 1 (.bag).
    for suffix in (".db3", ".bag"):
        path = directory / f"realsense{suffix}"
        try:
            recorder = rs.recorder(str(path), device)
            break
        except RuntimeError:
            continue
    syncer = rs.syncer()
    for sensor, profile in ((depth_sensor, depth_profile), (colour_sensor, colour_profile)):
        sensor.open(profile)
        sensor.start(syncer)
    for index in range(REC_FRAMES):
        for sensor, profile, pixels, bytes_per_pixel in (
            (depth_sensor, depth_profile, recorded_depth_mm(index), 2),
            (colour_sensor, colour_profile, recorded_colour(index), 3),
        ):
            frame = rs.software_video_frame()
            frame.pixels, frame.bpp, frame.stride = pixels, bytes_per_pixel, bytes_per_pixel * REC_W
            frame.timestamp, frame.frame_number = index * REC_PERIOD_S * 1e3, index
            frame.domain = rs.timestamp_domain.hardware_clock
            frame.profile = profile.as_video_stream_profile()
            sensor.on_video_frame(frame)
        # The recorder stamps messages with their arrival time, and playback replays that
        # timing: spaced frames play back like a camera instead of in a burst.
        time.sleep(REC_PERIOD_S)
    for sensor in (depth_sensor, colour_sensor):
        sensor.stop()
        sensor.close()
    del recorder  # the recording is written out when the recorder goes
    return path
