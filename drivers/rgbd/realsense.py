"""Intel RealSense RGB-D camera through pyrealsense2 (``cameras.rgbd.type = "realsense"``).

The SDK runs in a worker process (``drivers.rgbd.realsense_worker``; why:
``drivers.rgbd.process_camera``).
Depth is aligned to the colour camera by the SDK (``rs.align``) and scaled to metres with the
device's depth scale (0 stays "no return"). ``playback_file`` replays a recording (.bag, or .db3
from SDK 2.57 on) in a loop instead of opening a camera. The colour image keeps the stream's
resolution (``colour_scale`` is the Kinect's); distortion coefficients are ignored, as RealSense
colour streams are rectified or nearly so. The pyrealsense2 wheel also needs libusb-1.0.
"""

from __future__ import annotations

from drivers.config import CameraConfig
from drivers.rgbd import realsense_worker
from drivers.rgbd.process_camera import WorkerProcessCamera


class RealSenseCamera(WorkerProcessCamera):
    def __init__(self, config: CameraConfig) -> None:
        source = (
            f"recording {config.playback_file}"
            if config.playback_file
            else f"camera {config.serial or '(first found)'}"
        )
        super().__init__(
            config,
            name=f"RealSense {source}",
            target=realsense_worker.run,
            args=(config.playback_file, config.serial),
            missing_sdk="the RealSense backend needs the 'pyrealsense2' package:"
            " pip install 'touchshape[realsense]'; its wheel also needs libusb-1.0"
            " (apt install libusb-1.0-0)",
        )
