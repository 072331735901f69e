"""Replay: perception run again on a recorded session's inputs, without devices.

The camera frame and the touches are read from the session folder (``controller.session_files``)
and go through the same perception steps as on the robot, in the same order: reconstruct, then
for each touch interpret and refine (a touch whose height map is refused changes nothing, as in
the session). The replay is a session of its own: a new folder and recording, its inputs copied
in the same format (so it can be replayed in turn) and ``replay_of`` naming its source. With the
source's own settings it reproduces the source's voxels.
"""

from __future__ import annotations

import json
import logging
import time
import uuid
from collections.abc import Callable, Collection
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from controller.perception.learned import make_perception
from controller.perception.protocol import ShapeEstimate, TouchOutcome, contact_counts
from controller.recording import REQUEST_FILE, SessionRecorder
from controller.request import ExploreRequest, RequestError, parse_explore_request
from controller.scoring import object_size_cm, score_estimate
from controller.session_files import (
    GELSIGHT_REFERENCE_FILE,
    SESSION_LOG_FILE,
    RecordedSession,
    SessionFolderError,
    attach_session_log,
    detach_session_log,
    outcome_record,
    save_artifacts,
    save_camera_frame,
    save_config,
    save_tactile_frame,
    save_truth,
    touch_inputs_record,
    touch_rays,
)
from models.geometry import ur_pose_to_matrix
from models.tactile.reconstruction import HeightMapError

log = logging.getLogger(__name__)

Publish = Callable[[str, dict[str, Any]], None]


def replay_session(
    recorded: RecordedSession,
    logs_dir: Path,
    *,
    update: str | None = None,
    prior: str | None = None,
    on_publish: Publish = lambda name, body: None,
) -> dict[str, Any]:
    """Replay a recorded session (``read_session``) into a new session under ``logs_dir``;
    returns its summary. ``update`` / ``prior`` override the recorded request's (a bad one is a
    ``SessionFolderError`` before anything is written)."""
    perception = make_perception(recorded.config)
    request = _request(recorded, update, prior, perception.prior_names())

    started = time.time()
    session_id = time.strftime("%Y%m%d-%H%M%S-", time.localtime(started)) + uuid.uuid4().hex[:6]
    logs_dir.mkdir(parents=True, exist_ok=True)
    recorder = SessionRecorder(logs_dir, session_id, request.__dict__)
    session_log = attach_session_log(recorder.artifacts_dir / SESSION_LOG_FILE)
    try:
        log.info("replaying %s as %s (%s)", recorded.folder, session_id, request)
        summary = _run(recorded, request, perception, recorder, session_id, on_publish)
    finally:
        recorder.close()
        detach_session_log(session_log)
    summary["started"] = datetime.fromtimestamp(started, tz=UTC).isoformat(timespec="seconds")
    summary["replay_of"] = str(recorded.folder)
    summary["artifacts"]["summary"] = str(recorder.save_summary(summary))
    on_publish("result", summary)
    return summary


def _request(
    recorded: RecordedSession, update: str | None, prior: str | None, priors: Collection[str]
) -> ExploreRequest:
    """The recorded request (checked as the service checks one) with the overrides."""
    body = {**recorded.request, **({"update": update} if update else {})}
    body |= {"prior": prior} if prior else {}
    try:
        return parse_explore_request(json.dumps(body).encode(), ExploreRequest(), priors=priors)
    except RequestError as error:
        raise SessionFolderError(f"{recorded.folder / REQUEST_FILE}: {error}") from None


def _run(
    recorded: RecordedSession,
    request: ExploreRequest,
    perception: Any,
    recorder: SessionRecorder,
    session_id: str,
    publish: Publish,
) -> dict[str, Any]:
    config, folder, truth = recorded.config, recorder.artifacts_dir, recorded.truth_mesh
    save_config(folder, config)
    save_camera_frame(folder, recorded.frame)
    if truth is not None:
        save_truth(folder, truth)
    camera_position = config.cameras.rgbd.pose_world_camera()[:3, 3]
    recorder.log_setup(
        ur_pose_to_matrix(config.robot.arm.pose_world_base),
        config.voxel_grid.grid(tuple(camera_position)),
        truth,
    )
    recorder.log_camera(recorded.frame)
    metrics: dict[str, list[float]] = {}
    clock = time.perf_counter()

    def record_shape(estimate: ShapeEstimate, touch: int) -> None:
        recorder.log_estimate(estimate, vision=touch == 0)
        if truth is None:
            return
        scores = score_estimate(estimate, truth)
        for name, value in scores.items():
            recorder.log_metric(name, value, touch=touch)
            metrics.setdefault(name, []).append(round(value, 3))
        publish("score", {"session": session_id, "touch": touch, **scores})

    estimate = vision = perception.reconstruct(recorded.frame, request)
    record_shape(estimate, 0)
    publish("state", {"session": session_id, "state": "select", "previous": "reconstruct"})
    outcomes: list[TouchOutcome] = []
    outcome_touches: list[int] = []
    references_saved: set[str] = set()
    for touch in recorded.touches:
        measurement = touch.measurement
        reference_file = touch.record["gelsight_reference"]
        if reference_file not in references_saved:
            save_tactile_frame(folder, GELSIGHT_REFERENCE_FILE, measurement.reference)
            references_saved.add(reference_file)
        inputs = touch_inputs_record(session_id, touch.number, measurement)
        save_tactile_frame(folder, inputs["gelsight_image"], measurement.tactile)
        recorder.set_touch(touch.number)
        try:
            outcome = perception.interpret(measurement)
        except HeightMapError as error:
            log.error("touch %d refused: %s; going on without it", touch.number, error)
            recorder.log_touch({**inputs, "refused": str(error)}, None)
            publish("touch", {**inputs, "error": f"refused: {error}"})
            continue
        outcomes.append(outcome)
        outcome_touches.append(touch.number)
        record = {**inputs, **outcome_record(outcome)}
        recorder.log_tactile(measurement.tactile.image_bgr, outcome.height_map_mm)
        recorder.log_touch_patch(outcome.touch)
        recorder.log_touch(record, touch_rays(measurement.pad_start_world, outcome))
        publish("touch", record)
        estimate = perception.refine(estimate, outcomes, request)
        record_shape(estimate, touch.number)
    compute_s = time.perf_counter() - clock
    summary: dict[str, Any] = {
        "session": session_id,
        "state": "done",
        "touches": len(recorded.touches),
        **contact_counts(outcomes),
        "error": None,
        "stop_reason": f"replayed the {len(recorded.touches)} recorded touches",
        "request": request.__dict__,
        "compute_s": round(compute_s, 3),
        "metrics": metrics,
        "object_size_cm": object_size_cm(vision, estimate, truth),
    }
    source_object = _source_object(recorded.folder)
    if source_object is not None:
        summary["object"] = source_object
    summary["artifacts"] = save_artifacts(
        recorder,
        estimate,
        vision,
        outcomes,
        outcome_touches,
        len(recorded.touches),
        truth,
    )
    return summary


def _source_object(folder: Path) -> str | None:
    """The object the source session explored, from its summary (sim sessions name it)."""
    try:
        summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    value = summary.get("object") if isinstance(summary, dict) else None
    return value if isinstance(value, str) else None
