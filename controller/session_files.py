"""A session folder: its raw inputs, log and artifacts, written as a session runs; the inputs
read back to replay it.

What the sensors gave is kept as it came, so a session can be re-processed without the robot
(``touchshape replay``): the camera frame (RGB PNG, depth as 16-bit PNG in whole millimetres,
intrinsics and pose in JSON), the GelSight reference and one frame per touch (PNG, RGB order),
and per touch in ``touches.jsonl`` the planned target, the pad poses, the force and the finger
width. The request and the effective config sit beside them. docs/sessions.md describes every
file; this module is the one place that writes and reads them (the Rerun recording and its
per-touch records are ``controller.recording``'s).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import trimesh
from numpy.typing import NDArray
from PIL import Image, UnidentifiedImageError

from controller.config import Config, ConfigError, config_to_toml, load_config
from controller.perception.protocol import (
    ShapeEstimate,
    TouchMeasurement,
    TouchOutcome,
    TouchTarget,
)
from controller.recording import REQUEST_FILE, SessionRecorder
from controller.session_picture import save_shape_picture
from drivers.base import RGBDFrame, TactileFrame, depth_m_from_mm, depth_mm_from_m
from models.camera import CameraIntrinsics
from models.files import write_atomically, write_json_atomically
from models.touch.observations import SurfaceObservations, observations_of

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"

CONFIG_FILE = "config.toml"
TOUCHES_FILE = "touches.jsonl"
CAMERA_RGB_FILE = "camera/rgb.png"
CAMERA_DEPTH_FILE = "camera/depth_mm.png"
CAMERA_FILE = "camera/camera.json"
GELSIGHT_REFERENCE_FILE = "gelsight/reference.png"
SESSION_LOG_FILE = "session.log"
PICTURE_FILE = "shape.png"
TRUTH_FILE = "truth.ply"
"""The simulated object's true surface (world metres): sessions on the sim bench only."""


def gelsight_touch_file(touch: int) -> str:
    """The GelSight frame of touch ``touch`` (1-based), relative to the session folder."""
    return f"gelsight/touch_{touch:03d}.png"


class SessionFolderError(ValueError):
    """A session folder's file is missing or unreadable; the message names the file."""


# --- writing ----------------------------------------------------------------------------------


def save_config(folder: Path, config: Config) -> Path:
    """The effective config the session ran with (TOML, loadable with ``--config``)."""
    path = folder / CONFIG_FILE
    write_atomically(path, lambda temporary: temporary.write_text(config_to_toml(config)))
    return path


def save_camera_frame(folder: Path, frame: RGBDFrame) -> None:
    """The camera frame: colour, depth in whole millimetres (0 = no return), calibration."""
    _save_png(folder / CAMERA_RGB_FILE, frame.colour_rgb)
    _save_png(folder / CAMERA_DEPTH_FILE, depth_mm_from_m(frame.depth_m))
    k = frame.intrinsics
    write_json_atomically(
        folder / CAMERA_FILE,
        {
            "intrinsics": {
                "width": k.width,
                "height": k.height,
                "fx": k.fx,
                "fy": k.fy,
                "cx": k.cx,
                "cy": k.cy,
            },
            "pose_world_camera": np.asarray(frame.pose_world_camera).tolist(),
            "timestamp_s": frame.timestamp_s,
        },
    )


def save_tactile_frame(folder: Path, relative_path: str, frame: TactileFrame) -> str:
    """A GelSight frame as an RGB PNG; returns ``relative_path`` for the touch record."""
    _save_png(folder / relative_path, frame.image_bgr[..., ::-1])
    return relative_path


def save_truth(folder: Path, mesh: trimesh.Trimesh) -> Path:
    """The simulated object's surface, so a replay scores against the same truth."""
    path = folder / TRUTH_FILE
    write_atomically(path, lambda temporary: mesh.export(temporary, file_type="ply"))
    return path


def touch_inputs_record(
    session_id: str, number: int, measurement: TouchMeasurement
) -> dict[str, Any]:
    """The raw-input fields of touch ``number``'s line in ``touches.jsonl``: what
    ``read_session`` rebuilds the measurement from (the images go to ``gelsight_image`` and
    ``gelsight_reference``, which the caller saves)."""
    if measurement.gripper_width_m is None:
        raise ValueError("a recorded touch needs the fingers' opening (gripper_width_m)")
    target = measurement.target
    return {
        "session": session_id,
        "touch": number,
        "target_world": np.asarray(target.target_world).tolist(),
        "direction_world": np.asarray(target.direction_world).tolist(),
        "target_score": float(target.score),
        "target_uncertainty": float(target.uncertainty),
        "contact": bool(measurement.contact),
        "force_n": float(measurement.force_n),
        "gripper_width_m": float(measurement.gripper_width_m),
        "pad_start_world": np.asarray(measurement.pad_start_world).tolist(),
        "pose_world_pad": np.asarray(measurement.pose_world_pad).tolist(),
        "gelsight_timestamp_s": float(measurement.tactile.timestamp_s),
        "gelsight_image": gelsight_touch_file(number),
        "gelsight_reference": GELSIGHT_REFERENCE_FILE,
    }


def touch_rays(
    pad_start_world: NDArray[np.float64],
    outcome: TouchOutcome,
    pad_reach_world: NDArray[np.float64] | None = None,
) -> NDArray[np.float64] | None:
    """Segments from the approach start to (up to 20 of) the contact points, or on a miss the
    full sweep to ``pad_reach_world`` (None without it): what the touch says is empty space."""
    points = outcome.contact_points_world
    if len(points) == 0:
        return None if pad_reach_world is None else np.array([[pad_start_world, pad_reach_world]])
    sample = points[:: max(1, len(points) // 20)]
    return np.stack([np.broadcast_to(pad_start_world, sample.shape), sample], axis=1)


def outcome_record(outcome: TouchOutcome) -> dict[str, Any]:
    """What interpretation added to a touch's line: its mean contact point and point count."""
    point = outcome.contact_point_world
    return {
        "contact_point_world": None if point is None else point.tolist(),
        "contact_points": len(outcome.contact_points_world),
    }


def attach_session_log(path: Path) -> logging.Handler:
    """Every log record while the session runs, also in its folder (``session.log``)."""
    handler = logging.FileHandler(path, encoding="utf-8")
    handler.setFormatter(logging.Formatter(LOG_FORMAT))
    handler.setLevel(logging.INFO)
    logging.getLogger().addHandler(handler)
    return handler


def detach_session_log(handler: logging.Handler) -> None:
    logging.getLogger().removeHandler(handler)
    handler.close()


def save_artifacts(
    recorder: SessionRecorder,
    estimate: ShapeEstimate | None,
    vision_estimate: ShapeEstimate | None,
    outcomes: list[TouchOutcome],
    outcome_touches: list[int],
    touches_made: int,
    true_mesh_world: trimesh.Trimesh | None,
) -> dict[str, str]:
    """What a session leaves besides its inputs: the measured surface (observations.npz), the
    final voxels and surface mesh, and the picture of vision, final shape and truth. Each of
    ``outcomes`` was touch number ``outcome_touches[i]`` of ``touches_made`` (refused touches
    have no outcome). Returns the paths by name (the summary's ``artifacts``)."""
    folder = recorder.artifacts_dir
    artifacts = {
        "recording": str(recorder.rrd_path),
        "blueprint": str(recorder.blueprint_path),
        "touches": str(recorder.touches_path),
        "log": str(folder / SESSION_LOG_FILE),
    }
    touches = observations_of([o.touch for o in outcomes if o.touch is not None])
    camera = estimate.camera_observations if estimate is not None else SurfaceObservations.none()
    observations = SurfaceObservations.merged([camera, touches])
    artifacts["observations"] = str(recorder.save_observations(observations))
    if estimate is None:
        return artifacts
    artifacts["voxels"] = str(recorder.save_voxels(estimate.probabilities, estimate.grid))
    final_mesh = estimate.surface_mesh()
    artifacts["mesh"] = str(recorder.save_mesh(final_mesh))
    if vision_estimate is not None:
        contacts = [
            (number, outcome.contact_point_world)
            for number, outcome in zip(outcome_touches, outcomes, strict=True)
            if outcome.contact_point_world is not None
        ]
        picture = save_shape_picture(
            folder / PICTURE_FILE,
            vision_estimate.surface_mesh(),
            final_mesh,
            np.reshape([point for _, point in contacts], (-1, 3)),
            true_mesh_world,
            touch_numbers=[number for number, _ in contacts],
            touches=touches_made,
            title=recorder.session_id,
        )
        artifacts["picture"] = str(picture)
    return artifacts


def _save_png(path: Path, image: NDArray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    picture = Image.fromarray(np.ascontiguousarray(image))
    # Fast compression: level 6 takes ~340 ms a GelSight frame on the touch's path, level 1
    # ~60 ms for files ~20 % larger.
    write_atomically(
        path, lambda temporary: picture.save(temporary, format="PNG", compress_level=1)
    )


# --- reading ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class RecordedTouch:
    """One touch as recorded: its ``touches.jsonl`` line and the measurement rebuilt from it."""

    number: int
    record: dict[str, Any]
    measurement: TouchMeasurement


@dataclass(frozen=True)
class RecordedSession:
    """A session folder's raw inputs, ready to run perception on again."""

    folder: Path
    request: dict[str, Any]
    config: Config
    frame: RGBDFrame
    touches: list[RecordedTouch]
    truth_mesh: trimesh.Trimesh | None


def read_session(folder: Path) -> RecordedSession:
    """Read and check every raw input of a session folder; ``SessionFolderError`` names the first
    file that is missing or unreadable."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SessionFolderError(f"{folder}: not a session folder")
    request = _read_json(folder / REQUEST_FILE)
    if not isinstance(request, dict):
        raise SessionFolderError(f"{folder / REQUEST_FILE}: not a JSON object")
    config_path = _existing(folder / CONFIG_FILE)
    try:
        config = load_config(config_path)
    except ConfigError as error:
        raise SessionFolderError(f"{config_path}: {error}") from None
    frame = _read_camera_frame(folder)
    touches_path = _existing(folder / TOUCHES_FILE)
    touches = []
    references: dict[str, TactileFrame] = {}
    lines = touches_path.read_text(encoding="utf-8", errors="replace").splitlines()
    for number, line in enumerate(lines, start=1):
        where = f"{touches_path} line {number}"
        try:
            record = json.loads(line)
        except json.JSONDecodeError as error:
            raise SessionFolderError(f"{where}: not JSON ({error.msg})") from None
        if not isinstance(record, dict):
            raise SessionFolderError(f"{where}: not a JSON object")
        touches.append(_recorded_touch(folder, record, where, references))
    truth_path = folder / TRUTH_FILE
    truth = _read_mesh(truth_path) if truth_path.exists() else None
    return RecordedSession(folder, request, config, frame, touches, truth)


def _recorded_touch(
    folder: Path, record: dict[str, Any], where: str, references: dict[str, TactileFrame]
) -> RecordedTouch:
    def field(name: str, shape: tuple[int, ...] | None = None) -> Any:
        if name not in record:
            raise SessionFolderError(
                f"{where}: no '{name}' (recorded before raw inputs were kept?)"
            )
        value = record[name]
        if shape is None:
            return value
        array = np.asarray(value, dtype=np.float64) if _is_numeric(value) else None
        if array is None or array.shape != shape or not np.all(np.isfinite(array)):
            raise SessionFolderError(f"{where}: '{name}' is not a finite {shape} array")
        return array

    number = field("touch")
    if not isinstance(number, int) or number < 1:
        raise SessionFolderError(f"{where}: 'touch' must be a positive integer")
    scalars = {}
    for name in (
        "target_score",
        "target_uncertainty",
        "force_n",
        "gripper_width_m",
        "gelsight_timestamp_s",
    ):
        value = field(name)
        if (
            not isinstance(value, int | float)
            or isinstance(value, bool)
            or not math.isfinite(value)
        ):
            raise SessionFolderError(f"{where}: '{name}' must be a finite number")
        scalars[name] = float(value)
    contact = field("contact")
    if not isinstance(contact, bool):
        raise SessionFolderError(f"{where}: 'contact' must be true or false")
    reference_file = field("gelsight_reference")
    if reference_file not in references:
        references[reference_file] = _read_tactile(folder, reference_file, where)
    measurement = TouchMeasurement(
        target=TouchTarget(
            field("target_world", (3,)),
            field("direction_world", (3,)),
            score=scalars["target_score"],
            uncertainty=scalars["target_uncertainty"],
        ),
        contact=contact,
        tactile=_read_tactile(
            folder, field("gelsight_image"), where, scalars["gelsight_timestamp_s"]
        ),
        reference=references[reference_file],
        pose_world_pad=field("pose_world_pad", (4, 4)),
        pad_start_world=field("pad_start_world", (3,)),
        force_n=scalars["force_n"],
        gripper_width_m=scalars["gripper_width_m"],
    )
    return RecordedTouch(number, record, measurement)


def _is_numeric(value: Any) -> bool:
    try:
        np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return True


def _read_camera_frame(folder: Path) -> RGBDFrame:
    camera_path = folder / CAMERA_FILE
    camera = _read_json(camera_path)
    try:
        k = camera["intrinsics"]
        intrinsics = CameraIntrinsics(
            width=int(k["width"]),
            height=int(k["height"]),
            fx=float(k["fx"]),
            fy=float(k["fy"]),
            cx=float(k["cx"]),
            cy=float(k["cy"]),
        )
        pose = np.asarray(camera["pose_world_camera"], dtype=np.float64)
        timestamp_s = float(camera["timestamp_s"])
    except (KeyError, TypeError, ValueError) as error:
        raise SessionFolderError(f"{camera_path}: not a camera calibration ({error!r})") from None
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise SessionFolderError(f"{camera_path}: 'pose_world_camera' is not a finite 4x4 matrix")
    size = (intrinsics.height, intrinsics.width)
    rgb = _read_png(folder / CAMERA_RGB_FILE, (*size, 3), np.uint8)
    depth_mm = _read_png(folder / CAMERA_DEPTH_FILE, size, np.uint16)
    return RGBDFrame(
        colour_rgb=rgb,
        depth_m=depth_m_from_mm(depth_mm),
        intrinsics=intrinsics,
        pose_world_camera=pose,
        timestamp_s=timestamp_s,
    )


def _read_tactile(
    folder: Path, relative_path: Any, where: str, timestamp_s: float = 0.0
) -> TactileFrame:
    if not isinstance(relative_path, str) or Path(relative_path).is_absolute():
        raise SessionFolderError(f"{where}: an image path must be relative to the folder")
    path = folder / relative_path
    if folder.resolve() not in path.resolve().parents:
        raise SessionFolderError(f"{where}: {relative_path} is outside the session folder")
    rgb = _read_png(path, None, np.uint8)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise SessionFolderError(f"{path}: not an RGB image")
    return TactileFrame(image_bgr=np.ascontiguousarray(rgb[..., ::-1]), timestamp_s=timestamp_s)


def _read_png(path: Path, shape: tuple[int, ...] | None, dtype: type) -> NDArray:
    _existing(path)
    try:
        with Image.open(path) as picture:
            image = np.array(picture)  # writable: torch refuses read-only arrays
    except (OSError, UnidentifiedImageError, ValueError) as error:
        raise SessionFolderError(f"{path}: not a readable PNG ({error})") from None
    if image.dtype != dtype or (shape is not None and image.shape != shape):
        expected = f"{np.dtype(dtype).name} {shape}" if shape else np.dtype(dtype).name
        raise SessionFolderError(f"{path}: {image.dtype} {image.shape} image, expected {expected}")
    return image


def _read_json(path: Path) -> Any:
    _existing(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise SessionFolderError(f"{path}: not JSON ({error})") from None


def _read_mesh(path: Path) -> trimesh.Trimesh:
    try:
        mesh = trimesh.load(path, file_type="ply", force="mesh", process=False)
    except Exception as error:  # trimesh raises many kinds on a corrupt file
        raise SessionFolderError(f"{path}: not a readable PLY mesh ({error})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise SessionFolderError(f"{path}: holds no triangle mesh")
    return mesh


def _existing(path: Path) -> Path:
    if not path.is_file():
        raise SessionFolderError(f"{path}: missing")
    return path
