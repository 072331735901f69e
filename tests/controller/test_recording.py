"""Session recordings: one layout file per folder, a recorder that records nothing once closed
(the service logs its last state change after saving the artifacts), recordings read back
touch by touch, and sessions a kill ends: flushed touch by touch, summarised as interrupted and
given a footer at the next start-up."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rerun.chunk import RrdReader

from controller import recording_recovery
from controller.config import Config
from controller.recording import SessionRecorder
from controller.recording_layout import BLUEPRINT_FILE
from controller.recording_recovery import INTERRUPTED, recover_interrupted_sessions
from controller.request import ExploreRequest
from controller.service import TouchshapeService
from tests.fakes.perception import make_cylinder_perception

RERUN = Path(sys.executable).with_name("rerun")
TOUCHSHAPE = Path(sys.executable).with_name("touchshape")
# The batcher writes only when told to: what a killed session's file holds is what the recorder
# flushed itself, not what a timer happened to write.
NO_AUTOMATIC_FLUSH = {
    "RERUN_FLUSH_TICK_SECS": "1000000",
    "RERUN_FLUSH_NUM_BYTES": str(1 << 40),
    "RERUN_FLUSH_NUM_ROWS": str(1 << 40),
}


def rerun_verify(path: Path, *options: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(RERUN), "rrd", "verify", *options, str(path)], capture_output=True, text=True
    )


def rows_by_touch(rrd: Path) -> dict[str, dict[int, dict[str, Any]]]:
    """Every entity's rows on the ``touch`` timeline, read back from the file with Rerun's
    reader: entity path -> touch -> {component column: value} (the last row of that touch)."""
    rows: dict[str, dict[int, dict[str, Any]]] = defaultdict(dict)
    for chunk in RrdReader(rrd).stream():
        if "touch" not in chunk.timeline_names:
            continue
        batch = chunk.to_record_batch()
        columns = {n: batch.column(n).to_pylist() for n in batch.schema.names if ":" in n}
        for row, touch in enumerate(batch.column("touch").to_pylist()):
            values = {name: column[row] for name, column in columns.items()}
            rows[chunk.entity_path.lstrip("/")][touch] = values
    return rows


def image_size(values: dict[str, Any], archetype: str) -> tuple[int, int]:
    (image_format,) = values[f"{archetype}:format"]
    return image_format["width"], image_format["height"]


def assert_touches_recorded(
    rrd: Path,
    touches: list[dict[str, Any]],
    config: Config,
    *,
    refined: int,
    killed: bool = False,
) -> None:
    """The GelSight image, height map, contact point and target of each touch listed in
    touches.jsonl are in the recording at that touch, and the metrics of the first ``refined``
    (the refine step after the last touch logs its metrics later). ``killed``: the session was
    killed, and a surface still being drawn in the background then (``log_estimate``: derived
    data, recomputable from the touches) may be missing, so only the first is required."""
    rows = rows_by_touch(rrd)
    numbers = {t["touch"] for t in touches}
    sensor = config.sensor
    for touch in touches:
        number = touch["touch"]
        image = rows["gelsight/image"][number]
        assert image_size(image, "Image") == (sensor.image_width_px, sensor.image_height_px)
        (buffer,) = image["Image:buffer"]
        assert len(buffer) == sensor.image_width_px * sensor.image_height_px * 3
        assert len(set(buffer[::101])) > 10  # an image of the gel, not a blank frame
        assert image_size(rows["gelsight/height_mm"][number], "DepthImage") == image_size(
            image, "Image"
        )
        if touch["contact_point_world"] is not None:
            (position,) = rows["world/touch/contact"][number]["Points3D:positions"]
            assert position == pytest.approx(touch["contact_point_world"], abs=1e-6)
            patch = rows[f"world/contacts/{number:03d}/points"][number]["Points3D:positions"]
            assert np.linalg.norm(np.mean(patch, axis=0) - position) < 0.02
        (target_origin,) = rows["world/touch/target"][number]["Arrows3D:origins"]
        assert len(target_origin) == 3
    assert set(rows["metrics/voxels_flipped"]) >= set(range(1, refined + 1))
    # The surfaces: vision's at touch 0, the current one from then on at each refine.
    assert set(rows["world/estimate/vision"]) == {0}
    surfaces = {0} if killed else set(range(refined + 1))
    assert set(rows["world/estimate/current"]) >= surfaces
    assert set(rows["gelsight/image"]) == numbers  # nothing of a touch that did not complete


def test_layout_written_once_and_closed_recorder_records_nothing(tmp_path: Path) -> None:
    first = SessionRecorder(tmp_path, "one")
    layout = tmp_path / BLUEPRINT_FILE
    assert first.blueprint_path == layout.resolve() and layout.stat().st_size > 0
    written = layout.stat().st_mtime_ns
    first.log_metric("chamfer_mm", 3.0)
    first.log_metric("chamfer_mm", 2.5, touch=1)
    first.close()
    first.log_state("idle", "done")  # after close: nothing, no error
    second = SessionRecorder(tmp_path, "two")
    second.close()
    assert layout.stat().st_mtime_ns == written
    for path in (first.rrd_path, second.rrd_path, layout):
        result = rerun_verify(path)
        assert result.returncode == 0, result.stderr
    metric = rows_by_touch(first.rrd_path)["metrics/chamfer_mm"]
    assert {touch: values["Scalars:scalars"] for touch, values in metric.items()} == {
        0: [3.0],
        1: [2.5],
    }
    assert "log" not in rows_by_touch(first.rrd_path)


@pytest.mark.slow  # 37-64 s on a shared 2-core machine: the learned perception, two touches
async def test_a_session_recording_holds_every_touch(tmp_path: Path) -> None:
    from controller.perception.learned import make_perception

    config = Config()
    config = dataclasses.replace(config, sim=dataclasses.replace(config.sim, object="can"))
    service = TouchshapeService(config, make_perception, logs_dir=tmp_path)
    await service.start()
    try:
        service._publish = lambda name, body: None  # type: ignore[method-assign]
        service.start_session(ExploreRequest(max_touches=2))
        summary = await service.wait_session()
    finally:
        await service.stop()
    assert summary is not None and summary["state"] == "done" and summary["touches"] == 2
    artifacts = summary["artifacts"]
    touches = [json.loads(line) for line in Path(artifacts["touches"]).read_text().splitlines()]
    rrd = Path(artifacts["recording"])
    assert_touches_recorded(rrd, touches, config, refined=2)
    # The scores of the estimate after reconstruct (touch 0) and after each touch.
    chamfer = rows_by_touch(rrd)["metrics/chamfer_mm"]
    recorded = [chamfer[touch]["Scalars:scalars"][0] for touch in sorted(chamfer)]
    assert recorded == pytest.approx(summary["metrics"]["chamfer_mm"], abs=1e-3)
    assert sorted(chamfer) == [0, 1, 2]


# --- sessions a kill ends ---------------------------------------------------------------------

RECORD_AND_DIE = textwrap.dedent(
    """
    import json, os, signal, sys
    import numpy as np
    from pathlib import Path
    from controller.recording import SessionRecorder

    recorder = SessionRecorder(Path(sys.argv[1]), "killed", {"max_touches": 3})
    for touch in (1, 2):
        recorder.set_touch(touch)
        recorder.log_tactile(np.full((48, 64, 3), touch, np.uint8), np.zeros((48, 64)))
        record = {"session": "killed", "touch": touch, "contact": touch == 1,
                  "target_world": [0, 0, 0.1], "direction_world": [1, 0, 0],
                  "contact_point_world": [0.01, 0.0, 0.1] if touch == 1 else None}
        recorder.log_touch(record, None)
        recorder.log_metric("voxels_flipped", 10.0 * touch)
    with recorder.touches_path.open("a") as touches:  # the line a kill cut short
        touches.write('{"session": "killed", "touch": 3, "target_w')
    os.kill(os.getpid(), signal.SIGKILL)
    """
)


def record_and_kill(logs_dir: Path) -> None:
    """A real process records two touches and is SIGKILLed writing the third's line."""
    result = subprocess.run(
        [sys.executable, "-c", RECORD_AND_DIE, str(logs_dir)],
        cwd=Path(__file__).resolve().parents[2],
        env={**os.environ, **NO_AUTOMATIC_FLUSH},
        capture_output=True,
        text=True,
    )
    assert result.returncode == -signal.SIGKILL, result.stderr


def test_a_killed_session_is_summarised_as_interrupted(tmp_path: Path) -> None:
    record_and_kill(tmp_path)
    folder, rrd = tmp_path / "killed", tmp_path / "killed.rrd"
    assert not (folder / "summary.json").exists()
    assert rerun_verify(rrd).returncode != 0  # no footer: the process never closed it
    assert rerun_verify(rrd, "--check-footers", "false").returncode == 0

    (summary,) = recover_interrupted_sessions(tmp_path)

    assert json.loads((folder / "summary.json").read_text()) == summary
    assert summary["session"] == "killed" and summary["state"] == INTERRUPTED
    assert (summary["touches"], summary["contacts"]) == (2, 1)
    assert summary["request"] == {"max_touches": 3}
    assert summary["recovery"] == {
        "recording": "rewritten with a footer",
        "skipped_touch_lines": [3],
    }
    assert rerun_verify(rrd).returncode == 0
    rows = rows_by_touch(rrd)
    assert set(rows["gelsight/image"]) == {1, 2}
    assert set(rows["gelsight/height_mm"]) == {1, 2}
    assert set(rows["world/touch/contact"]) == {1}
    assert set(rows["world/touch/target"]) == {1, 2}
    assert recover_interrupted_sessions(tmp_path) == []  # once only


def test_recovery_leaves_a_live_session_and_finished_ones_alone(tmp_path: Path) -> None:
    finished = SessionRecorder(tmp_path, "finished")
    finished.close()
    finished.save_summary({"state": "done"})
    (tmp_path / "snapshot").mkdir()  # not a session: no touches.jsonl
    live = SessionRecorder(tmp_path, "live")
    try:
        assert recover_interrupted_sessions(tmp_path) == []
        assert not (tmp_path / "live" / "summary.json").exists()
    finally:
        live.close()
    # Closed without a summary (the service died saving the artifacts): interrupted.
    (summary,) = recover_interrupted_sessions(tmp_path)
    assert summary["session"] == "live" and summary["touches"] == 0
    assert json.loads((tmp_path / "finished" / "summary.json").read_text()) == {"state": "done"}
    assert not (tmp_path / "snapshot" / "summary.json").exists()


def test_a_session_that_cannot_be_summarised_does_not_stop_the_others(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    for name in ("full", "fine"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "touches.jsonl").write_text('{"touch": 1, "contact": false}\n')
    write = recording_recovery.write_json_atomically

    def disk_full_in_one_folder(path: Path, value: Any) -> Path:
        if path.parent.name == "full":
            raise OSError(28, "No space left on device")
        return write(path, value)

    monkeypatch.setattr(recording_recovery, "write_json_atomically", disk_full_in_one_folder)
    assert [s["session"] for s in recover_interrupted_sessions(tmp_path)] == ["fine"]
    assert "full: could not write its interrupted summary" in caplog.text
    monkeypatch.undo()
    assert [s["session"] for s in recover_interrupted_sessions(tmp_path)] == ["full"]


def test_recovery_keeps_a_recording_it_cannot_rewrite(tmp_path: Path) -> None:
    garbage = b"not a recording " * 300
    for name in ("garbage", "empty", "gone"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "touches.jsonl").write_text('{"touch": 1, "contact": true}\n')
    (tmp_path / "garbage.rrd").write_bytes(garbage)  # `rerun rrd merge` refuses it
    (tmp_path / "empty.rrd").write_bytes(b"")  # merged into a file without the recording

    summaries = {s["session"]: s for s in recover_interrupted_sessions(tmp_path)}

    for name in ("garbage", "empty"):
        assert summaries[name]["recovery"]["recording"].startswith("kept as written")
    assert "decoding failures" in summaries["garbage"]["recovery"]["recording"]  # merge's error
    assert "no recording empty" in summaries["empty"]["recovery"]["recording"]
    assert (tmp_path / "garbage.rrd").read_bytes() == garbage
    assert (tmp_path / "empty.rrd").read_bytes() == b""
    assert summaries["gone"]["recovery"]["recording"] == "missing"
    assert all(s["touches"] == 1 and s["contacts"] == 1 for s in summaries.values())
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == ["empty", "empty.rrd", "garbage", "garbage.rrd", "gone"]  # no temporary files


async def start_and_stop(service: TouchshapeService) -> None:
    await service.start()
    await service.stop()


def wait_for_touches(
    logs_dir: Path, count: int, process: subprocess.Popen[bytes], output: Path
) -> Path:
    """touches.jsonl once it lists ``count`` complete touches (polled every 5 ms)."""
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline:
        for path in logs_dir.glob("*/touches.jsonl"):
            if path.read_bytes().count(b"\n") >= count:
                return path
        assert process.poll() is None, output.read_text()
        time.sleep(0.005)
    raise AssertionError(f"no {count} touches in {logs_dir}")


def test_sigkill_after_touch_2_of_3_keeps_touches_recording_and_marks_interrupted(
    tmp_path: Path,
) -> None:
    logs = tmp_path / "logs"
    config_file = tmp_path / "config.toml"
    config_file.write_text(f'[logging]\ndir = "{logs}"\n[sim]\nobject = "can"\n')
    output = tmp_path / "explore.log"
    with output.open("w") as output_file:
        process = subprocess.Popen(
            [str(TOUCHSHAPE), "explore", "--config", str(config_file), "--touches", "3"],
            stdout=output_file,
            stderr=subprocess.STDOUT,
            env={**os.environ, **NO_AUTOMATIC_FLUSH},
        )
    try:
        touches_path = wait_for_touches(logs, 2, process, output)
        process.send_signal(signal.SIGKILL)
        assert process.wait(timeout=30) == -signal.SIGKILL
    finally:
        if process.poll() is None:
            process.kill()
    folder = touches_path.parent
    rrd = folder.with_name(f"{folder.name}.rrd")
    touches = [json.loads(line) for line in touches_path.read_text().splitlines()]
    assert [t["touch"] for t in touches] == [1, 2]
    assert not (folder / "summary.json").exists()
    assert rerun_verify(rrd).returncode != 0  # the kill left it without a footer

    # The restart: the service's start-up finds the session and summarises it.
    config = Config()
    asyncio.run(start_and_stop(TouchshapeService(config, make_cylinder_perception, logs_dir=logs)))

    summary = json.loads((folder / "summary.json").read_text())
    assert summary["state"] == INTERRUPTED and summary["session"] == folder.name
    assert summary["touches"] == 2
    assert summary["contacts"] == sum(t["contact"] for t in touches)
    assert summary["request"]["max_touches"] == 3
    assert summary["recovery"]["recording"] == "rewritten with a footer"
    assert rerun_verify(rrd).returncode == 0
    assert_touches_recorded(rrd, touches, config, refined=1, killed=True)
