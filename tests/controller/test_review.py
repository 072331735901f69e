"""`touchshape review`: the viewer command it builds (without launching a viewer), the one-line
error for a session without a recording, and the web viewer really served, on loopback only."""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
import urllib.request
from pathlib import Path

import pytest

from controller.cli import review
from controller.recording import SessionRecorder, rerun_binary
from controller.recording_layout import BLUEPRINT_FILE


def parse(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="touchshape")
    review.add_commands(parser.add_subparsers(dest="group", required=True))
    return parser.parse_args(argv)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def recorded_session(logs: Path, session: str = "s1") -> Path:
    SessionRecorder(logs, session).close()
    return logs / session


def test_the_native_viewer_gets_the_layout_then_the_recording(tmp_path: Path) -> None:
    command = review.review_command(tmp_path / "logs" / "s1")
    assert command == [
        str(rerun_binary()),
        str(tmp_path / "logs" / BLUEPRINT_FILE),
        str(tmp_path / "logs" / "s1.rrd"),
    ]
    assert rerun_binary().is_file() and os.access(rerun_binary(), os.X_OK)


def test_the_web_viewer_is_served_on_loopback_without_a_browser(tmp_path: Path) -> None:
    command = review.review_command(tmp_path / "s1", web=True, port=8001, grpc_port=8002)
    flags = command[1:-2]
    assert flags == [
        "--serve-web",
        "--bind",
        "127.0.0.1",
        "--web-viewer-port",
        "8001",
        "--port",
        "8002",
    ]
    assert "--web-viewer" not in command  # that one also opens a browser
    assert review.web_url(8001, 8002) == (
        "http://127.0.0.1:8001/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A8002%2Fproxy"
    )


def test_a_session_is_a_folder_a_recording_or_an_id_in_the_logs(tmp_path: Path) -> None:
    config = tmp_path / "config.toml"
    config.write_text(f'[logging]\ndir = "{tmp_path / "configured"}"\n')
    assert review.session_folder("logs/s1", None) == Path("logs/s1")
    assert review.session_folder("logs/s1.rrd", None) == Path("logs/s1")
    assert review.session_folder("s1", tmp_path / "other") == tmp_path / "other" / "s1"
    assert review.session_folder("s1", None, config) == tmp_path / "configured" / "s1"
    assert review.session_folder("s1", None) == Path("logs") / "s1"  # the default config's
    (tmp_path / "other" / "20261202-101500-a1b2c3").mkdir(parents=True)
    (tmp_path / "other" / "20261202-101500-a1b2c3" / "request.json").write_text("{}")
    started = review.session_folder("20261202-1015", tmp_path / "other")
    assert started == tmp_path / "other" / "20261202-101500-a1b2c3"


def test_a_missing_recording_is_one_line_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = parse(["review", "20990101-000000-abcdef", "--logs", str(tmp_path)])
    assert args.handler(args) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == (
        f"touchshape: error: no recording {tmp_path / '20990101-000000-abcdef.rrd'}\n"
    )


def listening_addresses(port: int) -> set[str]:
    """Local addresses with a socket listening on ``port`` (Linux /proc/net/tcp*)."""
    addresses = set()
    for table, size in (("/proc/net/tcp", 8), ("/proc/net/tcp6", 32)):
        for line in Path(table).read_text().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            address, hex_port = local.split(":")
            if state == "0A" and int(hex_port, 16) == port:  # 0A: LISTEN
                addresses.add(address if len(address) == size else "?")
    return addresses


SERVE = textwrap.dedent(
    """
    import argparse, sys
    from controller.cli import review

    parser = argparse.ArgumentParser()
    review.add_commands(parser.add_subparsers(dest="group"))
    args = parser.parse_args(sys.argv[1:])
    sys.exit(args.handler(args))
    """
)


# ~4.5 s each on a shared 2-core machine (8-9 s under load): the kill, less likely, is slow.
@pytest.mark.parametrize(
    "stop",
    [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.slow)],
    ids=["ctrl-c", "kill"],
)
def test_review_web_serves_the_session_on_loopback_until_stopped(
    tmp_path: Path, stop: signal.Signals
) -> None:
    session = recorded_session(tmp_path)
    port, grpc_port = free_port(), free_port()
    ports = ["--port", str(port), "--grpc-port", str(grpc_port)]
    process = subprocess.Popen(
        [sys.executable, "-c", SERVE, "review", str(session), "--web", *ports],
        cwd=Path(__file__).resolve().parents[2],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert process.stdout is not None
        line = process.stdout.readline()  # printed once the viewer's page answers
        assert line.startswith(f"open {review.web_url(port, grpc_port)}"), process.stderr
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/?url=x", timeout=10) as page:
            assert page.status == 200 and b"<html" in page.read().lower()
        # 0100007F: 127.0.0.1 in /proc's byte order.
        assert listening_addresses(port) == {"0100007F"}
        assert listening_addresses(grpc_port) == {"0100007F"}
        process.send_signal(stop)
        assert process.wait(timeout=20) == 0
    finally:
        if process.poll() is None:
            process.kill()
    deadline = time.monotonic() + 10
    while listening_addresses(port) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not listening_addresses(port)  # the viewer went with the command


def test_a_taken_port_is_refused_not_mistaken_for_the_viewer(tmp_path: Path) -> None:
    session = recorded_session(tmp_path)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        command = review.review_command(session, web=True, port=port, grpc_port=free_port())
        with pytest.raises(RuntimeError, match=f"port {port} is in use"):
            review.start_web_viewer(command, port, free_port())
