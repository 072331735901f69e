"""Session recording: one Rerun recording (logs/<session>.rrd) and a folder of artifacts
(logs/<session>/) per exploration session. The one module that talks to Rerun.

The viewer layout is one blueprint file, ``logs/touchshape.rbl``, written once per process
(``rerun logs/touchshape.rbl logs/<session>.rrd``): Rerun 0.41 keeps every blueprint stream it
makes for the life of the process (rerun-io/rerun#2116), so one per session grew a long-running
service by ~1.5 MB a session. Each session's recording stream is destroyed when it is closed.

Entity paths mirror the frame tree (``world/kinect``, ``world/ur5/tcp``, ``world/ur5/pad``);
timelines are ``touch`` (sequence) and ``time`` (wall clock).

A crash loses nothing already measured: as each touch completes the recording is flushed to its
file, then the touch is appended to ``touches.jsonl`` (flushed, fsynced), so a line there means
the recording holds that touch. A killed session's folder has no ``summary.json`` and its .rrd
no footer; ``recover_interrupted_sessions`` (run at service start-up) writes the summary with
``state: "interrupted"`` and rewrites the .rrd with a footer.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import rerun_bindings
import rerun_cli
import trimesh
from numpy.typing import NDArray
from rerun.chunk import RrdReader

from drivers.base import RGBDFrame
from models.files import write_json_atomically
from models.geometry import VoxelGrid
from models.touch.observations import SurfaceObservations

log = logging.getLogger(__name__)


def _confidence_colours(probabilities: NDArray[np.floating]) -> NDArray[np.uint8]:
    """Red (unsure, v near 0.5) to green (sure) for occupied voxels."""
    confidence = np.clip(np.abs(probabilities - 0.5) * 2.0, 0.0, 1.0)
    colours = np.stack([1.0 - confidence, confidence, np.full_like(confidence, 0.2)], axis=-1)
    return (colours * 255).astype(np.uint8)


def _blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="world", origin="world"),
            rrb.Vertical(
                rrb.Spatial2DView(name="kinect", origin="world/kinect"),
                rrb.Spatial2DView(name="gelsight", origin="gelsight"),
                rrb.TimeSeriesView(name="metrics", origin="metrics"),
                rrb.TextLogView(name="log", origin="log"),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


BLUEPRINT_FILE = "touchshape.rbl"
REQUEST_FILE = "request.json"
_blueprints_written: set[Path] = set()
_blueprints_lock = threading.Lock()


def save_blueprint(logs_dir: Path) -> Path:
    """The viewer layout in ``logs_dir`` (written once per process and folder)."""
    path = (logs_dir / BLUEPRINT_FILE).resolve()
    with _blueprints_lock:
        if path not in _blueprints_written or not path.exists():
            _blueprint().save("touchshape", str(path))
            _blueprints_written.add(path)
    return path


class SessionRecorder:
    """Records one session; create it at session start and ``close()`` it at the end."""

    def __init__(
        self, logs_dir: Path, session_id: str, request: dict[str, Any] | None = None
    ) -> None:
        self.session_id = session_id
        self.rrd_path = logs_dir / f"{session_id}.rrd"
        self.artifacts_dir = logs_dir / session_id
        self.artifacts_dir.mkdir(parents=True, exist_ok=True)
        self.touches_path = self.artifacts_dir / "touches.jsonl"
        self.motions_path = self.artifacts_dir / "motions.jsonl"
        self.blueprint_path = save_blueprint(logs_dir)
        if request is not None:  # for the summary of a session a crash ends
            write_json_atomically(self.artifacts_dir / REQUEST_FILE, request)
        self._rec: rr.RecordingStream | None = rr.RecordingStream(
            "touchshape", recording_id=session_id
        )
        self._rec.save(str(self.rrd_path))
        self._touch = 0
        self._touches_file = self.touches_path.open("a", encoding="utf-8")
        # Held while the session records (the kernel drops it when the process dies): start-up
        # recovery leaves a session alone that another process is still recording.
        fcntl.flock(self._touches_file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        self._motions_file = self.motions_path.open("a", encoding="utf-8")

    # --- timelines ------------------------------------------------------------------------------

    def _now(self, touch: int | None = None) -> None:
        # set_time is per thread and per call site: set it right before each log, no await
        # in between, on the thread that logs (the session logs images from worker threads).
        if self._rec is None:
            return
        self._rec.set_time("touch", sequence=self._touch if touch is None else touch)
        self._rec.set_time("time", timestamp=time.time())

    def _log(self, *args: Any, **kwargs: Any) -> None:
        if self._rec is not None:  # after close() nothing is recorded
            self._rec.log(*args, **kwargs)

    def set_touch(self, touch_index: int) -> None:
        self._touch = touch_index

    # --- static calibration ---------------------------------------------------------------------

    def log_setup(
        self,
        pose_world_base: NDArray[np.float64],
        grid: VoxelGrid,
        object_mesh_world: Any | None = None,
    ) -> None:
        """Robot base, voxel grid bounds and (simulation only) the ground-truth object."""
        self._log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self._log(
            "world/ur5",
            rr.Transform3D(translation=pose_world_base[:3, 3], mat3x3=pose_world_base[:3, :3]),
            static=True,
        )
        corners = grid.voxel_to_world(np.array([[0, 0, 0], [grid.resolution] * 3], dtype=float))
        self._log(
            "world/voxel_grid",
            rr.Boxes3D(
                mins=[corners.min(axis=0)],
                sizes=[np.abs(corners[1] - corners[0])],
                colors=[(120, 120, 120)],
            ),
            static=True,
        )
        if object_mesh_world is not None:
            self._log(
                "world/ground_truth",
                rr.Mesh3D(
                    vertex_positions=object_mesh_world.vertices,
                    triangle_indices=object_mesh_world.faces,
                    albedo_factor=(200, 200, 200, 80),
                ),
                static=True,
            )

    # --- per-session data -----------------------------------------------------------------------

    def log_state(self, state: str, previous: str | None, detail: str = "") -> None:
        self._now()
        text = f"{previous or '-'} -> {state}" + (f": {detail}" if detail else "")
        level = "ERROR" if state == "fault" else "INFO"
        self._log("log", rr.TextLog(text, level=level))

    def log_camera(self, frame: RGBDFrame) -> None:
        self._now()
        pose = frame.pose_world_camera
        k = frame.intrinsics
        self._log("world/kinect", rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))
        self._log(
            "world/kinect",
            rr.Pinhole(
                focal_length=(k.fx, k.fy),
                principal_point=(k.cx, k.cy),
                width=k.width,
                height=k.height,
            ),
        )
        self._log("world/kinect/rgb", rr.Image(frame.colour_rgb))
        self._log("world/kinect/depth", rr.DepthImage(frame.depth_m, meter=1.0))

    def log_sketches(self, sketches: dict[str, NDArray]) -> None:
        """2.5D sketches (network resolution) by name: depth, normals, silhouette."""
        self._now()
        for name, image in sketches.items():
            self._log(f"sketches/{name}", rr.Image(np.asarray(image)))

    def log_shape(self, probabilities: NDArray[np.floating], grid: VoxelGrid) -> None:
        """Occupied voxels (v > 0.5) as points coloured by confidence |v - 0.5|."""
        self._now()
        occupied = np.argwhere(probabilities > 0.5)
        points = grid.voxel_to_world(occupied + 0.5)
        colours = _confidence_colours(probabilities[tuple(occupied.T)])
        self._log(
            "world/shape",
            rr.Points3D(points, colors=colours, radii=grid.voxel_size_m / 2),
        )

    def log_robot(
        self, pose_world_tcp: NDArray[np.float64], pose_world_pad: NDArray[np.float64]
    ) -> None:
        self._now()
        for path, pose in (("world/tcp", pose_world_tcp), ("world/pad", pose_world_pad)):
            self._log(
                path,
                rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]),
                rr.TransformAxes3D(0.03),
            )

    def log_touch(self, record: dict[str, Any], rays_world: NDArray[np.float64] | None) -> None:
        """A touch's last record: its target, contact and rays; then the recording is flushed to
        its file (with the tactile image and height map logged before) and the record appended
        to touches.jsonl, so a killed session's .rrd holds every touch that file lists."""
        self._now()
        target = np.asarray(record["target_world"])
        direction = np.asarray(record["direction_world"])
        self._log(
            "world/touch/target",
            rr.Arrows3D(origins=[target - 0.05 * direction], vectors=[0.05 * direction]),
        )
        if record.get("contact_point_world") is not None:
            self._log(
                "world/touch/contact",
                rr.Points3D([record["contact_point_world"]], colors=[(255, 200, 0)], radii=0.003),
            )
        if rays_world is not None and len(rays_world):
            self._log("world/touch/rays", rr.LineStrips3D(rays_world))
        if self._rec is not None:
            self._rec.flush()
        self._touches_file.write(json.dumps(record) + "\n")
        self._touches_file.flush()
        os.fsync(self._touches_file.fileno())

    def log_motion(self, record: dict[str, Any]) -> None:
        """One arm motion (its label, start and end flange poses, speed) appended to
        motions.jsonl: what the arm did, for review and the safety benchmark."""
        self._motions_file.write(json.dumps(record) + "\n")
        self._motions_file.flush()

    def log_tactile(
        self, image_bgr: NDArray[np.uint8], height_map_mm: NDArray[np.floating] | None
    ) -> None:
        self._now()
        self._log("gelsight/image", rr.Image(image_bgr[..., ::-1]))
        if height_map_mm is not None:
            self._log("gelsight/height_mm", rr.DepthImage(height_map_mm, meter=1.0))

    def log_metric(self, name: str, value: float, *, touch: int | None = None) -> None:
        """A scalar on the ``touch`` timeline (the current touch unless given: a score computed
        in the background belongs to the estimate it scored)."""
        self._now(touch)
        self._log(f"metrics/{name}", rr.Scalars(value))

    # --- artifacts ------------------------------------------------------------------------------

    def save_voxels(self, probabilities: NDArray[np.floating], grid: VoxelGrid) -> Path:
        path = self.artifacts_dir / "voxels.npz"
        np.savez_compressed(
            path,
            probabilities=probabilities.astype(np.float16),
            matrix_world_voxel=grid.matrix_world_voxel,
        )
        return path

    def save_mesh(self, mesh: trimesh.Trimesh) -> Path:
        """The shape's surface (world frame, metres; ``ShapeEstimate.surface_mesh``) as PLY."""
        path = self.artifacts_dir / "shape.ply"
        mesh.export(path)
        return path

    def save_observations(self, observations: SurfaceObservations) -> Path:
        """What the touches measured (``models.touch.observations``) as observations.npz."""
        return observations.save(self.artifacts_dir / "observations.npz")

    def save_summary(self, summary: dict[str, Any]) -> Path:
        return write_json_atomically(self.artifacts_dir / "summary.json", summary)

    def close(self) -> None:
        """Flush and close the files; the recorder records nothing after this."""
        self._touches_file.close()
        self._motions_file.close()
        if self._rec is None:
            return
        self._rec.flush()
        rr.disconnect(recording=self._rec)
        # Drop the stream and have Rerun destroy it: merely disconnected, its native state
        # (batcher, buffers) would stay for the life of the process (rerun-io/rerun#2116).
        self._rec = None
        rerun_bindings.flush_and_cleanup_orphaned_recordings()


# --- sessions a crash ended -------------------------------------------------------------------

INTERRUPTED = "interrupted"
REWRITE_TIMEOUT_S = 300.0


def recover_interrupted_sessions(logs_dir: Path) -> list[dict[str, Any]]:
    """Give every session in ``logs_dir`` that a crash left without ``summary.json`` one, with
    ``state: "interrupted"`` and the touches ``touches.jsonl`` lists, and rewrite its recording
    with a footer. Sessions another process is still recording are left alone. Returns the
    summaries written."""
    if not logs_dir.is_dir():
        return []
    summaries = []
    for folder in sorted(logs_dir.iterdir()):
        touches_path = folder / "touches.jsonl"
        if not touches_path.is_file() or (folder / "summary.json").exists():
            continue
        try:
            with touches_path.open("rb") as touches_file:
                try:
                    fcntl.flock(touches_file, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except BlockingIOError:
                    log.info("session %s is being recorded by a running process", folder)
                    continue
                summaries.append(_summarise_interrupted(folder, touches_file.read()))
        except OSError as error:  # an unreadable folder must not keep the service from starting
            log.warning("session %s: could not write its interrupted summary: %s", folder, error)
    return summaries


def _summarise_interrupted(folder: Path, touches_jsonl: bytes) -> dict[str, Any]:
    touches, skipped = _read_touches(folder / "touches.jsonl", touches_jsonl)
    rrd_path = folder.with_name(f"{folder.name}.rrd")
    summary = {
        "session": folder.name,
        "state": INTERRUPTED,
        "touches": len(touches),
        "contacts": sum(bool(touch.get("contact")) for touch in touches),
        "error": "the service ended without closing the session (killed or crashed); "
        "found at the next start-up",
        "request": _read_request(folder / REQUEST_FILE),
        "recovery": {
            "recording": _add_footer(rrd_path, folder.name),
            "skipped_touch_lines": skipped,
        },
        "artifacts": {
            "recording": str(rrd_path),
            "touches": str(folder / "touches.jsonl"),
            "summary": str(folder / "summary.json"),
        },
    }
    write_json_atomically(folder / "summary.json", summary)
    log.warning(
        "session %s was interrupted: %s written (%d touches)",
        folder.name,
        folder / "summary.json",
        len(touches),
    )
    return summary


def _read_touches(path: Path, text: bytes) -> tuple[list[dict[str, Any]], list[int]]:
    """The touch records in ``touches.jsonl``, and the numbers of the lines that are not one
    (the last line a kill cut short): skipped with a warning, the rest kept."""
    touches, skipped = [], []
    for number, line in enumerate(text.splitlines(), start=1):
        try:
            record = json.loads(line)
        except (UnicodeDecodeError, json.JSONDecodeError):
            record = None
        if isinstance(record, dict) and isinstance(record.get("touch"), int):
            touches.append(record)
        else:
            skipped.append(number)
            log.warning("%s line %d: not a complete touch record, skipped", path, number)
    return touches, skipped


def _read_request(path: Path) -> dict[str, Any] | None:
    try:
        request = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return request if isinstance(request, dict) else None


def _add_footer(rrd_path: Path, recording_id: str) -> str:
    """Rewrite a recording a kill left without its footer (its last message maybe cut short)
    with Rerun's own ``rerun rrd merge``, then put it in place in one rename. The original stays
    when the rewrite fails: ``merge`` refuses a file with an undecodable message in it, and
    drops only a last message that ends early. Returns what was done."""
    if not rrd_path.is_file():
        return "missing"
    rewritten = rrd_path.with_name(f".{rrd_path.name}.rewrite.rrd")
    # The binary itself: `python -m rerun_cli` exits 0 whatever the command returns.
    command = [str(Path(rerun_cli.__file__).with_name("rerun")), "rrd", "merge", str(rrd_path)]
    try:
        merged = subprocess.run(
            [*command, "-o", str(rewritten)],
            capture_output=True,
            text=True,
            timeout=REWRITE_TIMEOUT_S,
        )
        if merged.returncode != 0:
            reason = (merged.stderr.strip().splitlines() or ["failed"])[-1]
        elif not _holds_recording(rewritten, recording_id):
            reason = f"the rewrite holds no recording {recording_id}"
        else:
            os.replace(rewritten, rrd_path)
            return "rewritten with a footer"
    except subprocess.TimeoutExpired:
        reason = f"took over {REWRITE_TIMEOUT_S:.0f} s"
    finally:
        rewritten.unlink(missing_ok=True)
    log.warning("%s: kept as written, without a footer: rerun rrd merge: %s", rrd_path, reason)
    return f"kept as written, without a footer (rerun rrd merge: {reason})"


def _holds_recording(rrd_path: Path, recording_id: str) -> bool:
    """Whether the file has a footer and the session's recording (``rerun rrd merge`` turns an
    empty or header-only file into a valid file without any recording)."""
    try:
        reader = RrdReader(rrd_path)
        return any(
            entry.recording_id == recording_id and len(reader.store(store=entry)) > 0
            for entry in reader.recordings()
        )
    except (OSError, RuntimeError, ValueError):
        return False
