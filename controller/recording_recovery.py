"""Sessions a crash ended: at start-up the service gives each a summary and its recording a
footer, so nothing already measured is lost (``controller.recording`` flushes each touch)."""

from __future__ import annotations

import fcntl
import json
import logging
import os
import subprocess
from pathlib import Path
from typing import Any

from rerun.chunk import RrdReader

from controller.recording import REQUEST_FILE, rerun_binary
from models.files import write_json_atomically

log = logging.getLogger(__name__)

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
    command = [str(rerun_binary()), "rrd", "merge", str(rrd_path)]
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
