"""Session recording: one Rerun recording (logs/<session>.rrd) and a folder of artifacts
(logs/<session>/) per exploration session. The one module that talks to Rerun.

The viewer layout is ``controller.recording_layout``'s blueprint file. Each session's recording
stream is destroyed when it is closed.

Entity paths mirror the frame tree (``world/kinect``, ``world/tcp``, ``world/pad``); the shape
estimates are ``world/estimate/vision`` (touch 0) and ``world/estimate/current`` (each refine),
the contact patches ``world/contacts/<touch>``, the scores ``metrics/...`` (one plot per
quantity). One timeline, ``touch`` (sequence): a review steps through touches, and wall-clock
time (Rerun's automatic ``log_time`` too) only adds a second, misleading axis.

A crash loses nothing already measured: as each touch completes the recording is flushed to its
file, then the touch is appended to ``touches.jsonl`` (flushed, fsynced), so a line there means
the recording holds that touch. A killed session's folder has no ``summary.json`` and its .rrd
no footer; ``controller.recording_recovery`` (run at service start-up) writes the summary with
``state: "interrupted"`` and rewrites the .rrd with a footer.
"""

from __future__ import annotations

import asyncio
import contextlib
import fcntl
import json
import logging
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib
import numpy as np
import rerun as rr
import rerun_bindings
import rerun_cli
import trimesh
from numpy.typing import NDArray

from controller.recording_layout import (
    LEGEND,
    OBJECT_FRAME,
    STD_COLORMAP,
    STD_RANGE_MM,
    save_blueprint,
)
from drivers.base import RGBDFrame
from models.files import write_json_atomically
from models.geometry import VoxelGrid
from models.touch.constraints import TouchResult
from models.touch.observations import SurfaceObservations

if TYPE_CHECKING:
    from controller.perception.protocol import ShapeEstimate

log = logging.getLogger(__name__)


def _confidence_colours(probabilities: NDArray[np.floating]) -> NDArray[np.uint8]:
    """Red (unsure, v near 0.5) to green (sure) for occupied voxels."""
    confidence = np.clip(np.abs(probabilities - 0.5) * 2.0, 0.0, 1.0)
    colours = np.stack([1.0 - confidence, confidence, np.full_like(confidence, 0.2)], axis=-1)
    return (colours * 255).astype(np.uint8)


PLAIN_ESTIMATE_COLOUR = (120, 170, 230)
"""An estimate without a std (the latent or Direct Edit update)."""
PATCH_ARROWS = 12
"""Normals drawn per contact patch: enough to show its orientation, few enough to read."""
PATCH_ARROW_M = 0.005
CAMERA_IMAGE_PLANE_M = 0.1
"""The camera's frustum and image in 3D: small, so they do not hide the object ~0.7 m off."""

ESTIMATE_KINDS = ("vision", "current")

# Metric names (controller.scoring, the session) -> entity path and series name: the F-scores
# share a plot, every other quantity has its own (their scales differ by orders of magnitude).
_METRICS = {
    "chamfer_mm": ("metrics/chamfer_mm", "chamfer (mm)"),
    "fscore_2mm": ("metrics/fscore/2mm", "F @2 mm"),
    "fscore_5mm": ("metrics/fscore/5mm", "F @5 mm"),
    "voxels_flipped": ("metrics/voxels_flipped", "voxels flipped"),
}
_METRIC_COLOURS = {
    "chamfer_mm": (230, 120, 40),
    "fscore_2mm": (70, 160, 230),
    "fscore_5mm": (150, 90, 220),
    "voxels_flipped": (120, 190, 90),
}

REQUEST_FILE = "request.json"


def std_colours(std_m: NDArray[np.floating]) -> NDArray[np.uint8]:
    """RGB per value of a posterior std (metres) on the ``STD_COLORMAP`` over ``STD_RANGE_MM``."""
    low, high = STD_RANGE_MM
    scaled = (np.asarray(std_m, dtype=float) * 1000.0 - low) / (high - low)
    rgba = matplotlib.colormaps[STD_COLORMAP](np.clip(scaled, 0.0, 1.0))
    return (rgba[..., :3] * 255).astype(np.uint8)


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
        self._rec.set_log_time_enabled(False)  # the one timeline is ``touch``
        self._background = ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="recording", initializer=_lower_thread_priority
        )
        """Recording work the session does not wait for, in order, at a lower priority: on a
        2-core machine it otherwise slows the session's next steps."""
        self._touch = 0
        self._log_styles()
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

    def _log(self, *args: Any, **kwargs: Any) -> None:
        if self._rec is not None:  # after close() nothing is recorded
            self._rec.log(*args, **kwargs)

    def set_touch(self, touch_index: int) -> None:
        self._touch = touch_index

    def _log_styles(self) -> None:
        """Series names and colours (lines with markers: touch 0 alone is a single point) and
        the layout's legend, static."""
        for name, (path, label) in _METRICS.items():
            colour = _METRIC_COLOURS[name]
            self._log(
                path,
                rr.SeriesLines(names=label, colors=colour, widths=2),
                rr.SeriesPoints(names=label, colors=colour, markers="circle", marker_sizes=3),
                static=True,
            )
        self._log("legend", rr.TextDocument(LEGEND, media_type="text/markdown"), static=True)

    # --- static calibration ---------------------------------------------------------------------

    def log_setup(
        self,
        pose_world_base: NDArray[np.float64],
        grid: VoxelGrid,
        object_mesh_world: Any | None = None,
    ) -> None:
        """Robot base, voxel grid bounds and (simulation only) the ground-truth object."""
        self._log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        # The frame the layout's 3D views look from (``controller.recording_layout``).
        self._log(
            OBJECT_FRAME,
            rr.Transform3D(
                translation=grid.origin_world, mat3x3=np.asarray(grid.axes_world, dtype=float).T
            ),
            static=True,
        )
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
                fill_mode="majorwireframe",
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

    def log_event(self, text: str) -> None:
        """A safety event the session recovered from (a warning in the log)."""
        self._now()
        self._log("log", rr.TextLog(text, level="WARN"))

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
                image_plane_distance=CAMERA_IMAGE_PLANE_M,
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

    def log_estimate(self, estimate: ShapeEstimate, *, vision: bool) -> None:
        """An estimate: its sketches (none: nothing logged) and voxels now, its surface coloured
        by the fused shape's std in the background (~1 s of marching cubes the robot need not
        wait for; ``close`` waits for it). ``vision``: the first, also kept as the vision
        estimate."""
        self.log_sketches(estimate.sketches)
        self.log_shape(estimate.probabilities, estimate.grid)
        kinds = ESTIMATE_KINDS if vision else ("current",)
        self._background.submit(self._log_surface, estimate, kinds, self._touch)

    def _log_surface(self, estimate: ShapeEstimate, kinds: tuple[str, ...], touch: int) -> None:
        try:
            mesh = estimate.surface_mesh()
            std = None if estimate.fused is None else estimate.fused.std(mesh.vertices)
            for kind in kinds:
                self.log_estimate_mesh(kind, mesh, std, touch=touch)
        except Exception:  # the recording of a surface must not end the session
            log.exception("recording the surface of touch %d failed", touch)

    def log_estimate_mesh(
        self,
        kind: str,
        mesh: trimesh.Trimesh,
        vertex_std_m: NDArray[np.floating] | None = None,
        *,
        touch: int | None = None,
    ) -> None:
        """A shape estimate's surface (world metres, ``ShapeEstimate.surface_mesh``) as
        ``world/estimate/<kind>``: ``vision`` (touch 0) or ``current`` (each refine). With the
        fused shape's posterior std at its vertices, coloured by it (``STD_RANGE_MM``)."""
        if kind not in ESTIMATE_KINDS:
            raise ValueError(f"estimate kind {kind!r} is not one of {ESTIMATE_KINDS}")
        self._now(touch)
        path = f"world/estimate/{kind}"
        if len(mesh.faces) == 0:  # nothing extracted: do not leave an older surface showing
            self._log(path, rr.Clear(recursive=False))
            return
        colours = None if vertex_std_m is None else std_colours(vertex_std_m)
        self._log(
            path,
            rr.Mesh3D(
                vertex_positions=np.asarray(mesh.vertices, dtype=np.float32),
                triangle_indices=np.asarray(mesh.faces, dtype=np.uint32),
                vertex_normals=np.asarray(mesh.vertex_normals, dtype=np.float32),
                vertex_colors=colours,
                albedo_factor=PLAIN_ESTIMATE_COLOUR if colours is None else None,
            ),
        )

    def log_contact_patch(
        self, points_world: NDArray[np.floating], normals_world: NDArray[np.floating]
    ) -> None:
        """A touch's contact patch as ``world/contacts/<touch>`` (kept for every touch, so the
        current estimate shows all it was fitted to): its points and, for a few dozen of them,
        short arrows along the outward normals."""
        points = np.asarray(points_world, dtype=np.float32).reshape(-1, 3)
        normals = np.asarray(normals_world, dtype=np.float32).reshape(-1, 3)
        if len(points) == 0:
            return
        self._now()
        path = f"world/contacts/{self._touch:03d}"
        self._log(f"{path}/points", rr.Points3D(points, colors=(255, 150, 0), radii=0.0006))
        arrows = np.linspace(0, len(points) - 1, min(PATCH_ARROWS, len(points))).astype(int)
        self._log(
            f"{path}/normals",
            rr.Arrows3D(
                origins=points[arrows],
                vectors=PATCH_ARROW_M * normals[arrows],
                colors=(0, 200, 230),
                radii=0.0003,
            ),
        )

    def log_touch_patch(self, touch: TouchResult | None) -> None:
        """``log_contact_patch`` of a touch's thinned contact points and their normals, as the
        fused update sees them (``SurfaceObservations.from_touch``); nothing for a miss."""
        if touch is None or touch.is_miss:
            return
        observations = SurfaceObservations.from_touch(touch)
        self.log_contact_patch(
            observations.surface_points_world, observations.surface_normals_world
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
        path = _METRICS[name][0] if name in _METRICS else f"metrics/{name}"
        self._log(path, rr.Scalars(value))

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
        """Finish the background work, flush and close the files; the recorder records nothing
        after this."""
        self._background.shutdown(wait=True)
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


def _lower_thread_priority() -> None:
    """Nice 10 for the calling thread (Linux: a thread's own priority, by its id)."""
    with contextlib.suppress(AttributeError, OSError):  # not Linux: the default priority
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 10)


def rerun_binary() -> Path:
    """The ``rerun`` binary the rerun-sdk wheel ships, beside ``rerun_cli``: the binary itself,
    as ``python -m rerun_cli`` exits 0 whatever the command returns."""
    return Path(rerun_cli.__file__).with_name("rerun")


async def record_in_thread(*calls: Callable[[], object]) -> None:
    """Record or publish in a worker thread, in order: Rerun's conversion of images and points,
    the recording's flush at each touch and a shape's encoding take up to tens of milliseconds.
    The work runs to its end even when the awaiting task is cancelled, so a touch is recorded
    whole and the recorder is not closed under it."""
    work = asyncio.ensure_future(asyncio.to_thread(lambda: [call() for call in calls]))
    try:
        await asyncio.shield(work)
    except asyncio.CancelledError:
        await work
        raise
