"""`touchshape sessions`: the recorded sessions in the logs folder, newest first.

A session is a folder ``logs/<id>/`` (the id is its local start time, ``%Y%m%d-%H%M%S-xxxxxx``,
see ``TouchshapeService.start_session``). A session that ended has ``summary.json``; one still
running, or killed before the next start-up's ``recover_interrupted_sessions`` wrote its
summary, has only ``request.json`` and ``touches.jsonl``. :func:`list_sessions` reads them all
without ever failing on one: a corrupt summary lists its session as "unreadable", so the one
broken folder is the one a person looks at, not a traceback.
"""

from __future__ import annotations

import argparse
import fcntl
import json
import math
import sys
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from controller.config import load_config
from controller.recording import REQUEST_FILE

SUMMARY_FILE = "summary.json"
TOUCHES_FILE = "touches.jsonl"
ID_TIME_FORMAT = "%Y%m%d-%H%M%S"
TABLE_TIME_FORMAT = "%Y-%m-%d %H:%M:%S"

RUNNING = "running"
"""State of a session without a summary whose recorder still holds its touches file."""
INTERRUPTED = "interrupted"
"""State of a session without a summary that no process records any more (killed)."""
UNREADABLE = "unreadable"
"""State of a session whose summary.json is not a readable JSON object."""


@dataclass(frozen=True)
class SessionInfo:
    """One recorded session as listed: None where the folder does not say."""

    id: str
    folder: Path
    started: datetime | None
    """Start time, timezone-aware (from the summary's "started", else the id)."""
    object: str | None
    """Sim object name or mesh path; None on a real robot."""
    touches: int | None
    contacts: int | None
    state: str
    """done / fault / aborted / interrupted from the summary; running, interrupted (no
    summary yet) or unreadable as found."""
    chamfer_mm_before: float | None
    chamfer_mm_after: float | None
    replay_of: str | None
    """The source session's folder when this session is a replay."""

    def to_json(self) -> dict[str, Any]:
        """The JSON form of ``touchshape sessions --json``: start time in ISO 8601, local."""
        return {
            "id": self.id,
            "started": _local(self.started).isoformat(timespec="seconds") if self.started else None,
            "object": self.object,
            "touches": self.touches,
            "contacts": self.contacts,
            "state": self.state,
            "chamfer_mm_before": self.chamfer_mm_before,
            "chamfer_mm_after": self.chamfer_mm_after,
            "folder": str(self.folder),
            "replay_of": self.replay_of,
        }


def list_sessions(logs_dir: Path) -> list[SessionInfo]:
    """Every session folder in ``logs_dir``, newest first (none when it does not exist).

    A folder counts when it holds a summary, a request or a touches file (the logs folder also
    holds benchmark output and the .rrd recordings, which do not).
    """
    logs_dir = Path(logs_dir)
    if not logs_dir.is_dir():
        return []
    sessions = [
        _read_session(folder)
        for folder in logs_dir.iterdir()
        if not folder.name.startswith(".")  # a folder being written atomically
        and folder.is_dir()
        and any((folder / name).is_file() for name in (SUMMARY_FILE, REQUEST_FILE, TOUCHES_FILE))
    ]
    oldest = datetime.min.replace(tzinfo=UTC)
    return sorted(sessions, key=lambda s: (s.started or oldest, s.id), reverse=True)


def find_session(logs_dir: Path, session_id: str) -> SessionInfo | None:
    """The session with id ``session_id`` (or, if unique, the one it is the start of)."""
    sessions = list_sessions(logs_dir)
    exact = [s for s in sessions if s.id == session_id]
    matches = exact or [s for s in sessions if s.id.startswith(session_id)]
    return matches[0] if len(matches) == 1 else None


def _read_session(folder: Path) -> SessionInfo:
    summary_path = folder / SUMMARY_FILE
    if not summary_path.is_file():
        return _read_unfinished(folder)
    try:
        summary = json.loads(summary_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        summary = None
    if not isinstance(summary, dict):
        return _info(folder, state=UNREADABLE)
    metrics = summary.get("metrics")
    chamfer = _chamfers(metrics if isinstance(metrics, dict) else {})
    state = summary.get("state")
    return _info(
        folder,
        started=_parse_iso(summary.get("started")),
        object=_str(summary.get("object")),
        touches=_int(summary.get("touches")),
        contacts=_int(summary.get("contacts")),
        state=state if isinstance(state, str) and state else UNREADABLE,
        chamfer_mm_before=chamfer[0] if chamfer else None,
        chamfer_mm_after=chamfer[-1] if len(chamfer) > 1 else None,
        replay_of=_str(summary.get("replay_of")),
    )


def _read_unfinished(folder: Path) -> SessionInfo:
    """A session without a summary: running, or killed (the touches counted from its file)."""
    touches_path = folder / TOUCHES_FILE
    touches = contacts = 0
    state = INTERRUPTED
    try:
        with touches_path.open("rb") as touches_file:
            if _locked(touches_file):
                state = RUNNING
            for line in touches_file:
                try:
                    record = json.loads(line)
                except (UnicodeDecodeError, json.JSONDecodeError):
                    continue  # the last line a kill cut short
                if isinstance(record, dict) and isinstance(record.get("touch"), int):
                    touches += 1
                    contacts += bool(record.get("contact"))
    except OSError:  # no touches file yet (or unreadable): nothing touched that we know of
        pass
    return _info(folder, touches=touches, contacts=contacts, state=state)


def _locked(touches_file: Any) -> bool:
    """Whether a recorder holds the file: ``SessionRecorder`` keeps an exclusive flock on it.
    A shared lock is taken for an instant and released; it never blocks."""
    try:
        fcntl.flock(touches_file, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    except OSError:
        return False
    fcntl.flock(touches_file, fcntl.LOCK_UN)
    return False


def _info(
    folder: Path, *, state: str, started: datetime | None = None, **fields: Any
) -> SessionInfo:
    values: dict[str, Any] = {
        "object": None,
        "touches": None,
        "contacts": None,
        "chamfer_mm_before": None,
        "chamfer_mm_after": None,
        "replay_of": None,
    }
    values.update(fields)
    return SessionInfo(
        id=folder.name,
        folder=folder,
        started=started or _time_of_id(folder.name),
        state=state,
        **values,
    )


def _time_of_id(session_id: str) -> datetime | None:
    """The start time an id names (local time, as the service writes it)."""
    try:
        naive = datetime.strptime(session_id[:15], ID_TIME_FORMAT)
    except ValueError:
        return None
    return naive.astimezone()  # a naive datetime is taken as local time


def _parse_iso(value: Any) -> datetime | None:
    if not isinstance(value, str):
        return None
    try:
        parsed = datetime.fromisoformat(value)
    except ValueError:
        return None
    return parsed if parsed.tzinfo is not None else parsed.replace(tzinfo=UTC)


def _chamfers(metrics: dict[str, Any]) -> list[float]:
    """The Chamfer distances (mm) in order, unknown ones (null) left out."""
    values = metrics.get("chamfer_mm")
    if not isinstance(values, list):
        return []
    return [
        float(v)
        for v in values
        if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
    ]


def _str(value: Any) -> str | None:
    return value if isinstance(value, str) and value else None


def _int(value: Any) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def _local(moment: datetime) -> datetime:
    return moment.astimezone()


# --- the command ------------------------------------------------------------------------------


def add_commands(groups: argparse._SubParsersAction) -> None:
    """Add `sessions`."""
    sessions = groups.add_parser(
        "sessions",
        help="list the recorded sessions, newest first",
        epilog="examples:\n  touchshape sessions\n  touchshape sessions --logs logs --json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sessions.add_argument(
        "--logs", type=Path, default=None, help="logs folder (default: the config's, logs)"
    )
    sessions.add_argument("--config", type=Path, default=None, help="TOML config (logs folder)")
    sessions.add_argument("--json", action="store_true", help="print a JSON list instead")
    sessions.set_defaults(handler=run_sessions)


def run_sessions(args: argparse.Namespace) -> int:
    """Print the sessions in ``args.logs`` (or the config's logs folder) as a table or JSON."""
    logs_dir = args.logs if args.logs is not None else Path(load_config(args.config).logging.dir)
    sessions = list_sessions(logs_dir)
    if args.json:
        print(json.dumps([session.to_json() for session in sessions], indent=2))
        if not sessions:
            print(f"no sessions in {logs_dir}", file=sys.stderr)
        return 0
    if not sessions:
        print(f"no sessions in {logs_dir}")
        return 0
    print(format_table(sessions))
    return 0


def format_table(sessions: list[SessionInfo]) -> str:
    """The sessions as an aligned plain-text table, one line each (a "replay of" column only
    when some session is a replay)."""
    header = ["id", "started", "object", "touches", "state", "chamfer mm", "folder"]
    replays = any(session.replay_of for session in sessions)
    if replays:
        header.append("replay of")
    rows = [header]
    for session in sessions:
        row = [
            session.id,
            _local(session.started).strftime(TABLE_TIME_FORMAT) if session.started else "-",
            _short_object(session.object),
            "-" if session.touches is None else f"{session.touches}/{_dash(session.contacts)}",
            session.state,
            _chamfer(session.chamfer_mm_before, session.chamfer_mm_after),
            str(session.folder),
        ]
        if replays:
            row.append(Path(session.replay_of).name if session.replay_of else "")
        rows.append(row)
    widths = [max(len(row[column]) for row in rows) for column in range(len(header))]
    return "\n".join(
        "  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip()
        for row in rows
    )


def _short_object(name: str | None) -> str:
    """A sim object's name as is; a mesh file by its file name (the JSON has the path)."""
    if not name:
        return "-"
    return Path(name).name if ("/" in name or "\\" in name) else name


def _chamfer(before: float | None, after: float | None) -> str:
    if before is None and after is None:
        return "-"
    return f"{_mm(before)} -> {_mm(after)}"


def _mm(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def _dash(value: int | None) -> str:
    return "-" if value is None else str(value)
