"""Session recordings: one layout file per folder, a recorder that records nothing once closed
(the service logs its last state change after saving the artifacts)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from controller.recording import BLUEPRINT_FILE, SessionRecorder


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
    rerun = Path(sys.executable).with_name("rerun")
    for path in (first.rrd_path, second.rrd_path, layout):
        result = subprocess.run([str(rerun), "rrd", "verify", str(path)], capture_output=True)
        assert result.returncode == 0, result.stderr
