"""Configuration of the devices: one frozen dataclass per device kind, sim and real backends alike.

Which backend runs is the ``type`` field, never a flag in code. Units are in the field names.
The full config tree and its TOML loader live in ``controller.config``; these sections are
defined here so that drivers take typed settings without importing the controller.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from models.camera import look_at_pose

Vec3 = tuple[float, float, float]
Vec6 = tuple[float, float, float, float, float, float]


class FieldError(ValueError):
    """A bad value of one field of a config section. The validator
    (``controller.config.build_dataclass``) prefixes the section, so the error names the dotted
    key (``limits.max_force_n must be positive``)."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field} {message}")
        self.field = field
        self.message = message


def require_positive(section: object, *names: str) -> None:
    """Raise ``FieldError`` for the first named field (number or vector) not finite and above 0
    (written so that NaN fails too: every comparison with NaN is false)."""
    for name in names:
        value = getattr(section, name)
        values = value if isinstance(value, tuple) else (value,)
        if not all(math.isfinite(v) and v > 0 for v in values):
            raise FieldError(name, f"must be positive and finite, got {value}")


def require_finite(section: object, *names: str) -> None:
    """Raise ``FieldError`` for the first named field (number or vector) holding NaN or inf."""
    for name in names:
        value = getattr(section, name)
        values = value if isinstance(value, tuple) else (value,)
        if not all(math.isfinite(v) for v in values):
            raise FieldError(name, f"must be finite, got {value}")


@dataclass(frozen=True)
class ArmConfig:
    type: Literal["sim", "ur_rtde"] = "sim"
    model: Literal["ur5"] = "ur5"
    host: str = "127.0.0.2"
    """Controller address for ur_rtde (the sim UR controller emulator binds 127.0.0.2)."""
    pose_world_base: Vec6 = (0.05, -0.42, 0.0, 0.0, 0.0, 0.0)
    """Robot base in the world as a UR pose [m, axis-angle rad]; `touchshape calibrate robot`."""
    tcp_offset: Vec6 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    """TCP relative to the flange; touchshape plans with the flange and its own tool model."""
    home_joints_rad: Vec6 = (-1.5708, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)
    """Tool pointing down 43 cm above the object point with the default base pose."""
    max_joint_speed_rad_s: float = 3.14
    """Hardware limit of the UR5 (180 deg/s); the controller's limits are stricter."""
    control_frequency_hz: float = 125.0
    """RTDE rate: 125 Hz on a CB3 UR5, 500 Hz on e-Series."""
    connect_timeout_s: float = 5.0
    """ur_rtde: one connection attempt (dashboard, RTDE, control-script upload)."""
    connect_attempts: int = 3
    """ur_rtde: attempts of connect(), with exponential backoff between them."""
    max_tool_speed_m_s: float = 1.0
    """ur_rtde: the fastest moveL the driver sends (MotionRejectedError above)."""
    max_tool_acceleration_m_s2: float = 5.0
    max_joint_acceleration_rad_s2: float = 40.0
    watchdog_timeout_s: float = 1.0
    """ur_rtde: no fresh RTDE state for this long means the link is lost (then it reconnects)."""

    def __post_init__(self) -> None:
        require_finite(self, "pose_world_base", "tcp_offset", "home_joints_rad")
        require_positive(
            self,
            "max_joint_speed_rad_s",
            "control_frequency_hz",
            "max_tool_speed_m_s",
            "max_tool_acceleration_m_s2",
            "max_joint_acceleration_rad_s2",
            "connect_timeout_s",
            "watchdog_timeout_s",
        )
        if self.connect_attempts < 1:
            raise FieldError("connect_attempts", f"must be at least 1, got {self.connect_attempts}")


@dataclass(frozen=True)
class GripperConfig:
    """WSG 50 gripper and the fingers it carries (tool frame: z along the fingers from the
    flange, fingers open along +-x, the GelSight finger is the +x one)."""

    type: Literal["sim", "wsg50_serial", "wsg50_tcp"] = "sim"
    serial_port: str = "/dev/ttyUSB0"
    baudrate: int = 115200
    host: str = "192.168.1.20"
    tcp_port: int = 1000
    stroke_m: float = 0.110
    max_speed_m_s: float = 0.42
    max_force_n: float = 80.0
    body_size_m: Vec3 = (0.146, 0.052, 0.072)
    """Gripper body box (x, y, z), its base on the flange."""
    finger_size_m: Vec3 = (0.008, 0.020, 0.100)
    """One finger box (thickness along x, width along y, length along z from the body's top)."""
    timeout_s: float = 3.0
    """WSG 50: longest wait for the reply to a command (a motion's end has its own timeout)."""
    connect_timeout_s: float = 3.0
    """WSG 50: opening the serial port or the TCP connection."""
    state_update_period_ms: int = 20
    """WSG 50: period of the automatic width, force and system-state updates."""
    max_state_age_s: float = 0.25
    """WSG 50: an older state means the gripper went silent (state() raises a timeout)."""

    def __post_init__(self) -> None:
        if not 0 < self.stroke_m <= 0.2:
            raise FieldError("stroke_m", f"must be in (0, 0.2], got {self.stroke_m}")
        require_positive(
            self,
            "body_size_m",
            "finger_size_m",
            "max_speed_m_s",
            "max_force_n",
            "timeout_s",
            "connect_timeout_s",
            "max_state_age_s",
        )
        if not 5 <= self.state_update_period_ms <= 1000:
            raise FieldError(
                "state_update_period_ms", f"must be in [5, 1000], got {self.state_update_period_ms}"
            )
        if self.max_state_age_s * 1e3 < 2 * self.state_update_period_ms:
            raise FieldError(
                "max_state_age_s", "must cover at least two state_update_period_ms periods"
            )
        if self.baudrate <= 0:
            raise FieldError("baudrate", f"must be positive, got {self.baudrate}")
        if not 0 < self.tcp_port < 65536:
            raise FieldError("tcp_port", f"must be in 1..65535, got {self.tcp_port}")


@dataclass(frozen=True)
class SensorConfig:
    """GelSight tactile sensor mounted outward on the +x finger."""

    type: Literal["sim", "opencv"] = "sim"
    device: str = "0"
    """OpenCV camera index, a /dev/v4l/by-id/... path, or a video file (replayed in a loop)."""
    pad_width_mm: float = 19.0
    """Along the finger (tool z), imaged along the 640 px columns."""
    pad_height_mm: float = 14.0
    image_width_px: int = 640
    image_height_px: int = 480
    frame_rate_hz: float = 30.0
    housing_thickness_m: float = 0.025
    """From the finger's outer face to the undeformed gel surface."""
    housing_length_m: float = 0.035
    """Housing extent along the finger, ending at the finger tip."""
    housing_recess_m: float = 0.010
    """The housing's front face this far behind the undeformed gel surface: the gel sits on an
    acrylic window that protrudes from the housing, so the gel, not the housing, meets a
    surface approached within ~50 degrees of its normal."""
    pad_centre_from_tip_m: float = 0.0175
    gel_thickness_mm: float = 2.0
    max_indentation_mm: float = 1.5
    """Deeper than this the object meets the rigid backing."""
    youngs_modulus_mpa: float = 0.3
    image_noise_sigma: float = 1.5
    """Gaussian image noise of the simulated sensor, 8-bit units."""
    calibration_file: str = ""
    """GelSight calibration from `touchshape gelsight calibrate`; empty = built at start-up from
    the real ball presses shipped with taxim (the sensor the simulation's optics come from)."""
    crop_px: tuple[int, int, int, int] = (0, 0, 0, 0)
    """Camera: (x, y, width, height) of the gel area in the captured image; zeros = all of it."""
    reference_frame_count: int = 10
    """Camera: the no-contact reference is the mean of this many consecutive frames."""
    max_frame_age_s: float = 0.5
    """Camera: a newest frame older than this means the camera stalled (read raises)."""
    open_timeout_s: float = 5.0
    """Camera: opening the device and getting its first frame."""

    def __post_init__(self) -> None:
        require_positive(
            self,
            "pad_width_mm",
            "pad_height_mm",
            "image_width_px",
            "image_height_px",
            "frame_rate_hz",
            "housing_thickness_m",
            "housing_length_m",
            "pad_centre_from_tip_m",
            "gel_thickness_mm",
            "youngs_modulus_mpa",
            "max_frame_age_s",
            "open_timeout_s",
        )
        if not (math.isfinite(self.image_noise_sigma) and self.image_noise_sigma >= 0):
            raise FieldError("image_noise_sigma", f"must be >= 0, got {self.image_noise_sigma}")
        x, y, width, height = self.crop_px
        if min(x, y, width, height) < 0 or (width == 0) != (height == 0):
            raise FieldError(
                "crop_px", "is (x, y, width, height) >= 0; width and height both 0 or not"
            )
        if self.reference_frame_count < 1:
            raise FieldError(
                "reference_frame_count", f"must be >= 1, got {self.reference_frame_count}"
            )
        if not 0 < self.max_indentation_mm < self.gel_thickness_mm:
            raise FieldError("max_indentation_mm", "must be in (0, gel_thickness_mm)")
        if not self.max_indentation_mm * 1e-3 < self.housing_recess_m < self.housing_thickness_m:
            raise FieldError(
                "housing_recess_m", "must lie between max_indentation_mm and housing_thickness_m"
            )


@dataclass(frozen=True)
class CameraConfig:
    """The RGB-D camera, placed as in the paper: 45.72 cm high, tilted 30 degrees down."""

    type: Literal["sim", "kinect_v2", "realsense"] = "sim"
    serial: str = ""
    """Real camera's serial number; empty = the first one found."""
    kinect_pipeline: Literal["cpu", "opengl", "opencl"] = "opengl"
    """Kinect v2: libfreenect2's depth decoder (opengl needs a display or EGL; cpu is slow)."""
    playback_file: str = ""
    """RealSense: play back a recording (.bag or .db3) instead of opening a camera."""
    max_frame_age_s: float = 0.5
    """Real camera: a newest frame older than this means the camera stalled (read raises)."""
    open_timeout_s: float = 10.0
    """Real camera: opening the device and getting its first frame."""
    height_m: float = 0.4572
    tilt_deg: float = 30.0
    horizontal_distance_m: float = 0.62
    """From the object point to the camera, on the table plane."""
    yaw_deg: float = 0.0
    """Direction the camera looks in, about world z; 0 = looking along world +x."""
    colour_scale: float = 0.5
    """Colour resolution as a fraction of the Kinect v2's 1920x1080."""
    depth_noise: bool = True
    transparent_object: bool = False
    """Sim: the object returns no depth, like glass on a time-of-flight camera."""
    background: Literal["white", "gradient", "texture"] = "white"

    def __post_init__(self) -> None:
        if not 0.0 < self.tilt_deg < 90.0:
            raise FieldError("tilt_deg", f"must be in (0, 90), got {self.tilt_deg}")
        if not 0.05 <= self.colour_scale <= 1.0:
            raise FieldError("colour_scale", f"must be in [0.05, 1], got {self.colour_scale}")
        require_positive(
            self, "height_m", "horizontal_distance_m", "max_frame_age_s", "open_timeout_s"
        )
        require_finite(self, "yaw_deg")

    def pose_world_camera(self) -> NDArray[np.float64]:
        """Camera pose (OpenCV axes) in the world, from height, tilt, distance and yaw."""
        yaw, tilt = math.radians(self.yaw_deg), math.radians(self.tilt_deg)
        forward = np.array([math.cos(yaw), math.sin(yaw), 0.0])
        eye = -self.horizontal_distance_m * forward + [0.0, 0.0, self.height_m]
        view = math.cos(tilt) * forward - [0.0, 0.0, math.sin(tilt)]
        return look_at_pose(eye, eye + view)


@dataclass(frozen=True)
class SimConfig:
    """The simulated bench: which object stands on the table and how time runs."""

    object: str = "mug"
    """A shape-library category or a mesh file path (OBJ/STL/PLY/GLB)."""
    object_up_axis: str = "z"
    object_scale: float = 1.0
    object_yaw_deg: float = 60.0
    """Turn of the object about the vertical axis through the object point (a mug's handle
    points along +x before it: 60 degrees shows it beside the body to the camera)."""
    seed: int = 0
    real_time_factor: float = 0.0
    """0 = motions complete instantly (tests), 1 = real time (demos)."""
    table_size_m: tuple[float, float] = (1.2, 0.8)
    object_albedo_rgb: Vec3 = (0.75, 0.35, 0.25)
    contact_stiffness_n_per_m: float = 10_000.0
    """A rigid tool part pressed into the object or the table by d pushes back with this
    times d (10 N/mm: a household object, the table and the arm's joints, lumped): the TCP
    force the arm reports."""
    protective_stop_force_n: float = 50.0
    """The simulated UR stops itself (protective stop) when a contact's force exceeds this,
    as its safety configuration's force limit does (50-150 N on a real one)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.real_time_factor) and self.real_time_factor >= 0):
            raise FieldError("real_time_factor", f"must be >= 0, got {self.real_time_factor}")
        require_positive(
            self,
            "object_scale",
            "table_size_m",
            "contact_stiffness_n_per_m",
            "protective_stop_force_n",
        )
        require_finite(self, "object_yaw_deg", "object_albedo_rgb")
