"""`touchshape sessions`: the session folders in the logs folder, newest first, as a table or
JSON; a broken or unfinished session is listed, not a traceback."""

from __future__ import annotations

import argparse
import fcntl
import json
import re
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest

from controller.cli import sessions as sessions_cli
from controller.cli.sessions import SessionInfo, find_session, list_sessions

DONE_ID = "20261201-100000-aaaaaa"
REPLAY_ID = "20261202-090000-bbbbbb"
KILLED_ID = "20261202-120000-cccccc"
CORRUPT_ID = "20261130-080000-dddddd"


def _id_time(session_id: str) -> datetime:
    """The local start time an id names, as the service writes it."""
    return datetime.strptime(session_id[:15], "%Y%m%d-%H%M%S").astimezone()


def _local_text(moment: datetime) -> str:
    return moment.astimezone().strftime("%Y-%m-%d %H:%M:%S")


# The summary's own start time wins over the id's: 5 s later than the id says.
DONE_STARTED = _id_time(DONE_ID) + timedelta(seconds=5)
REQUEST = {"max_touches": 3, "policy": "active", "update": "fused", "input": "rgb"}


def _summary(session_id: str, **fields: object) -> dict:
    return {
        "session": session_id,
        "state": "done",
        "touches": 3,
        "contacts": 3,
        "error": None,
        "stop_reason": "the touch budget is spent",
        "request": {**REQUEST, "prior": "general"},
        "metrics": {"chamfer_mm": [6.81, 6.7, 6.47], "fscore_2mm": [0.3, 0.31, 0.32]},
        "artifacts": {},
        **fields,
    }


@pytest.fixture
def logs(tmp_path: Path) -> Path:
    logs = tmp_path / "logs"
    done = logs / DONE_ID
    done.mkdir(parents=True)
    (done / "summary.json").write_text(
        json.dumps(
            _summary(
                DONE_ID,
                started=DONE_STARTED.astimezone(UTC).isoformat(timespec="seconds"),
                object="/data/meshes/mug_07.obj",
                touches=4,
                contacts=3,
                metrics={"chamfer_mm": [13.827, 10.861]},
            )
        )
    )
    (logs / f"{DONE_ID}.rrd").write_bytes(b"RRF2")

    replay = logs / REPLAY_ID
    replay.mkdir()
    # An older summary: no "started" or "object"; replayed from the first session.
    (replay / "summary.json").write_text(
        json.dumps(_summary(REPLAY_ID, replay_of=str(done), state="fault", error="collision"))
    )

    killed = logs / KILLED_ID
    killed.mkdir()
    (killed / "request.json").write_text(json.dumps(REQUEST))
    touch = {"session": KILLED_ID, "target_world": [0, 0, 0.05]}
    (killed / "touches.jsonl").write_text(
        json.dumps({**touch, "touch": 1, "contact": True})
        + "\n"
        + json.dumps({**touch, "touch": 2, "contact": False})
        + "\n"
        + '{"session": "'  # the line the kill cut short
    )

    corrupt = logs / CORRUPT_ID
    corrupt.mkdir()
    (corrupt / "summary.json").write_text('{"session": "2026113')

    # Not sessions: benchmark output, the viewer layout, a folder being written atomically.
    (logs / "bench").mkdir()
    (logs / "bench" / "explore.json").write_text("{}")
    (logs / "touchshape.rbl").write_bytes(b"")
    (logs / f".{REPLAY_ID}.tmp").mkdir()
    (logs / f".{REPLAY_ID}.tmp" / "summary.json").write_text("{}")
    return logs


def _run(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="touchshape")
    sessions_cli.add_commands(parser.add_subparsers(dest="group", required=True))
    args = parser.parse_args(argv)
    return args.handler(args)


def test_lists_sessions_newest_first_with_their_fields(logs: Path) -> None:
    sessions = list_sessions(logs)
    assert [s.id for s in sessions] == [KILLED_ID, REPLAY_ID, DONE_ID, CORRUPT_ID]
    killed, replay, done, corrupt = sessions
    assert all(isinstance(s, SessionInfo) for s in sessions)

    assert done == SessionInfo(
        id=DONE_ID,
        folder=logs / DONE_ID,
        started=DONE_STARTED,
        object="/data/meshes/mug_07.obj",
        touches=4,
        contacts=3,
        state="done",
        chamfer_mm_before=13.827,
        chamfer_mm_after=10.861,
        replay_of=None,
    )
    assert replay.started == _id_time(REPLAY_ID)  # no "started": the id's time
    assert (replay.state, replay.object, replay.replay_of) == ("fault", None, str(logs / DONE_ID))
    assert (replay.chamfer_mm_before, replay.chamfer_mm_after) == (6.81, 6.47)

    # Killed: no summary, no lock on its touches file; the complete lines counted.
    assert (killed.state, killed.touches, killed.contacts) == ("interrupted", 2, 1)
    assert killed.started == _id_time(KILLED_ID)
    assert killed.chamfer_mm_before is None and killed.chamfer_mm_after is None

    assert corrupt.state == "unreadable"
    assert corrupt.started == _id_time(CORRUPT_ID)
    assert (corrupt.touches, corrupt.object, corrupt.chamfer_mm_before) == (None, None, None)


def test_a_session_being_recorded_is_running(logs: Path) -> None:
    """The recorder holds an exclusive flock on touches.jsonl while the session runs."""
    with (logs / KILLED_ID / "touches.jsonl").open("a") as recording:
        fcntl.flock(recording, fcntl.LOCK_EX | fcntl.LOCK_NB)
        assert list_sessions(logs)[0].state == "running"
        # Listing took no lock that would keep the recorder (or start-up recovery) waiting.
        fcntl.flock(recording, fcntl.LOCK_UN)
        fcntl.flock(recording, fcntl.LOCK_EX | fcntl.LOCK_NB)
    assert list_sessions(logs)[0].state == "interrupted"


def test_only_a_session_without_summary_or_touches_file(tmp_path: Path) -> None:
    """Just started: request.json written, nothing else yet."""
    folder = tmp_path / "20261203-080000-eeeeee"
    folder.mkdir()
    (folder / "request.json").write_text(json.dumps(REQUEST))
    [session] = list_sessions(tmp_path)
    assert (session.state, session.touches, session.contacts) == ("interrupted", 0, 0)


def test_summary_with_odd_values_is_listed_with_what_it_says(tmp_path: Path) -> None:
    folder = tmp_path / "not-an-id"
    folder.mkdir()
    odd = _summary(
        "not-an-id",
        started="yesterday",
        touches="three",
        metrics={"chamfer_mm": [None, 7.5]},
        replay_of=12,
    )
    (folder / "summary.json").write_text(json.dumps(odd))
    (tmp_path / "list").mkdir()
    (tmp_path / "list" / "summary.json").write_text("[1, 2]")
    sessions = {s.id: s for s in list_sessions(tmp_path)}
    session = sessions["not-an-id"]
    assert session.started is None and session.touches is None and session.replay_of is None
    assert (session.contacts, session.chamfer_mm_before, session.chamfer_mm_after) == (3, 7.5, None)
    assert sessions["list"].state == "unreadable"


def test_table(logs: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _run(["sessions", "--logs", str(logs)]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert len(lines) == 5
    header = ["id", "started", "object", "touches", "state", "chamfer mm", "folder", "replay of"]
    assert re.split(r"  +", lines[0]) == header
    assert [line.split()[0] for line in lines[1:]] == [KILLED_ID, REPLAY_ID, DONE_ID, CORRUPT_ID]
    # Aligned: every column starts where its header does.
    for name in ("started", "object", "touches", "state", "chamfer mm", "folder"):
        column = lines[0].index(name)
        for line in lines[1:]:
            assert line[column - 2 : column] == "  " and line[column] != " ", (name, line)

    killed, replay, done, corrupt = lines[1:]
    assert _local_text(_id_time(KILLED_ID)) in killed
    assert "  2/1  " in killed and "  interrupted  " in killed
    assert killed.split()[-1] == str(logs / KILLED_ID)  # no replay: the last column empty

    assert _local_text(DONE_STARTED) in done
    assert "  mug_07.obj  " in done and "  4/3  " in done and "  13.83 -> 10.86  " in done
    assert "  done  " in done

    assert "  6.81 -> 6.47  " in replay and "  fault  " in replay
    assert replay.endswith(f"{logs / REPLAY_ID}  {DONE_ID}")

    assert "  unreadable  " in corrupt
    fields = corrupt.split()
    assert fields[3:7] == ["-", "-", "unreadable", "-"]  # object, touches, state, chamfer


def test_json(logs: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert _run(["sessions", "--logs", str(logs), "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert [entry["id"] for entry in listed] == [KILLED_ID, REPLAY_ID, DONE_ID, CORRUPT_ID]
    keys = {"id", "started", "object", "touches", "contacts", "state"}
    keys |= {"chamfer_mm_before", "chamfer_mm_after", "folder", "replay_of"}
    assert all(set(entry) == keys for entry in listed)
    killed, replay, done, corrupt = listed
    assert done == {
        "id": DONE_ID,
        "started": DONE_STARTED.astimezone().isoformat(timespec="seconds"),
        "object": "/data/meshes/mug_07.obj",
        "touches": 4,
        "contacts": 3,
        "state": "done",
        "chamfer_mm_before": 13.827,
        "chamfer_mm_after": 10.861,
        "folder": str(logs / DONE_ID),
        "replay_of": None,
    }
    assert datetime.fromisoformat(done["started"]) == DONE_STARTED
    assert replay["replay_of"] == str(logs / DONE_ID)
    assert (killed["state"], killed["touches"], killed["contacts"]) == ("interrupted", 2, 1)
    assert corrupt["state"] == "unreadable" and corrupt["touches"] is None


@pytest.mark.parametrize("make", [False, True], ids=["missing", "empty"])
def test_no_sessions(tmp_path: Path, capsys: pytest.CaptureFixture[str], make: bool) -> None:
    logs = tmp_path / "logs"
    if make:
        (logs / "bench").mkdir(parents=True)
    assert _run(["sessions", "--logs", str(logs)]) == 0
    assert capsys.readouterr().out == f"no sessions in {logs}\n"
    assert _run(["sessions", "--logs", str(logs), "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out) == []
    assert captured.err == f"no sessions in {logs}\n"


def test_default_logs_folder_is_the_configs(
    logs: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.chdir(logs.parent)  # the default config's logging.dir is "logs"
    assert _run(["sessions"]) == 0
    assert KILLED_ID in capsys.readouterr().out


def test_find_session(logs: Path) -> None:
    found = find_session(logs, DONE_ID)
    assert found is not None and found.folder == logs / DONE_ID
    assert find_session(logs, "20261202-09") is not None  # a unique start of an id
    assert find_session(logs, "202612") is None  # ambiguous
    assert find_session(logs, "nope") is None
