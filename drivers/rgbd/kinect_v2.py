"""Kinect v2 through libfreenect2's Python bindings, pylibfreenect2 (``type = "kinect_v2"``).

libfreenect2's ``Registration`` maps the 512x424 time-of-flight depth into the 1920x1080 colour
camera ("bigdepth", 1920x1082 with one padding row above and below); the backend takes that
registered depth in millimetres, turns it into metres (no return -> 0.0), converts the BGRX
colour to RGB, and samples both to ``colour_scale`` of full resolution (nearest pixel, so depth
is never blended across an edge). Depth is along the depth camera's axis, which the factory
calibration makes parallel to the colour camera's, 5 cm beside it: the difference from the
colour camera's z is far below the sensor's noise. The SDK runs in a worker process
(``drivers.rgbd.kinect_v2_worker``; why: ``drivers.rgbd.process_camera``).

pylibfreenect2 needs libfreenect2 built from source (it is not in Debian):
``pip install 'touchshape[kinect]'`` after installing libfreenect2.
"""

from __future__ import annotations

from drivers.config import CameraConfig
from drivers.rgbd import kinect_v2_worker
from drivers.rgbd.process_camera import WorkerProcessCamera


class KinectV2Camera(WorkerProcessCamera):
    def __init__(self, config: CameraConfig) -> None:
        super().__init__(
            config,
            name=f"Kinect v2 {config.serial or '(first found)'}",
            target=kinect_v2_worker.run,
            args=(config.serial, config.kinect_pipeline, config.colour_scale),
            missing_sdk="the Kinect v2 backend needs the 'pylibfreenect2' package:"
            " install libfreenect2 (built from source), then pip install 'touchshape[kinect]'",
        )
