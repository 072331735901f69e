"""The pinhole camera model (numpy only, so device interfaces can use it without the renderer).

The camera frame is OpenCV's (x right, y down, z forward); ``pose_world_camera`` is the 4x4
homogeneous transform taking camera-frame points to the z-up world frame, in metres. Pixel centres
sit at integer pixel coordinates (OpenCV convention).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels (no distortion), image size ``width`` x ``height``."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @property
    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix K mapping camera-frame points to homogeneous pixels."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def scaled(self, factor: float) -> CameraIntrinsics:
        """The same camera resampled to ``factor`` times the resolution.

        The principal point is scaled about the image corner (-0.5, -0.5) rather than the first
        pixel centre, so that an image centre stays the image centre: 959.5 -> 479.5 at 0.5.
        """
        return CameraIntrinsics(
            width=round(self.width * factor),
            height=round(self.height * factor),
            fx=self.fx * factor,
            fy=self.fy * factor,
            cx=(self.cx + 0.5) * factor - 0.5,
            cy=(self.cy + 0.5) * factor - 0.5,
        )

    @classmethod
    def kinect_v2_colour(cls, scale: float = 1.0) -> CameraIntrinsics:
        """Kinect v2 colour camera, typical factory values (1920x1080), times ``scale``."""
        return cls(1920, 1080, 1081.37, 1081.37, 959.5, 539.5).scaled(scale)

    @classmethod
    def kinect_v2_depth(cls) -> CameraIntrinsics:
        """Kinect v2 time-of-flight depth camera, typical factory values (512x424)."""
        return cls(512, 424, 365.456, 365.456, 254.878, 205.395)


def look_at_pose(
    eye_world: np.ndarray | tuple[float, float, float],
    target_world: np.ndarray | tuple[float, float, float],
    up_world: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 1.0),
) -> np.ndarray:
    """4x4 ``pose_world_camera`` of a camera at ``eye_world`` looking at ``target_world``.

    Image "up" (-y in the OpenCV camera frame) is as close to ``up_world`` as the viewing
    direction allows. All arguments are world-frame points/directions in metres.
    """
    eye = np.asarray(eye_world, dtype=np.float64)
    forward = np.asarray(target_world, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up_world, dtype=np.float64))
    norm = np.linalg.norm(right)
    if norm < 1e-9:
        raise ValueError("up_world is parallel to the viewing direction")
    right /= norm
    pose = np.eye(4)
    pose[:3, 0] = right
    pose[:3, 1] = np.cross(forward, right)  # camera y points down in the image
    pose[:3, 2] = forward
    pose[:3, 3] = eye
    return pose
