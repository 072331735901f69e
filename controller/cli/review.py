"""`touchshape review <session>`: a session's recording in the Rerun viewer, with the layout
file the recorder writes beside it (``rerun logs/touchshape.rbl logs/<id>.rrd``)."""

from __future__ import annotations

import argparse
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import IO
from urllib.parse import quote

from controller.cli.sessions import find_session
from controller.config import load_config

LOOPBACK = "127.0.0.1"
"""The web viewer and its gRPC server listen here only: a recording is not for the network."""
WEB_PORT = 9090
GRPC_PORT = 9876
SERVER_START_S = 60.0


def add_commands(groups: argparse._SubParsersAction) -> None:
    """Add `review`."""
    review = groups.add_parser(
        "review",
        help="open a session's recording in the Rerun viewer, with the session layout",
        epilog="examples: touchshape review 20261202-023700-0fad86\n"
        "          touchshape review logs/20261202-023700-0fad86 --web",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    review.add_argument("session", help="session folder (logs/<id>) or session id")
    review.add_argument("--config", type=Path, default=None, help="TOML config file")
    review.add_argument(
        "--logs",
        type=Path,
        default=None,
        help="where a session id is looked up (default: the config's logging dir)",
    )
    review.add_argument(
        "--web",
        action="store_true",
        help=f"serve the web viewer on {LOOPBACK} (not the network) and print its URL",
    )
    review.add_argument("--port", type=int, default=WEB_PORT, help="web viewer HTTP port (--web)")
    review.add_argument(
        "--grpc-port", type=int, default=GRPC_PORT, help="port the web viewer loads data from"
    )
    review.set_defaults(handler=_review)


def session_folder(session: str, logs_dir: Path | None, config: Path | None = None) -> Path:
    """The session's folder: ``session`` itself when it is a folder (or its ``.rrd``), else the
    id (or a unique start of it) in ``logs_dir`` (default: the config's logging dir)."""
    path = Path(session)
    if path.suffix == ".rrd":
        return path.with_suffix("")
    if path.is_dir() or len(path.parts) > 1:
        return path
    if logs_dir is None:
        logs_dir = Path(load_config(config).logging.dir)
    found = find_session(logs_dir, session)  # the id, or a unique start of it
    return found.folder if found is not None else logs_dir / session


def recording_of(session_dir: Path) -> Path:
    return session_dir.with_name(f"{session_dir.name}.rrd")


def web_url(port: int = WEB_PORT, grpc_port: int = GRPC_PORT) -> str:
    """The web viewer's address with the recording's source (its gRPC proxy) in ``url``."""
    source = quote(f"rerun+http://{LOOPBACK}:{grpc_port}/proxy", safe="")
    return f"http://{LOOPBACK}:{port}/?url={source}"


def review_command(
    session_dir: Path,
    web: bool = False,
    *,
    port: int = WEB_PORT,
    grpc_port: int = GRPC_PORT,
    rerun: Path | None = None,
) -> list[str]:
    """The viewer's command line: the layout file, then the recording. ``web``: the web viewer
    served on loopback (``--serve-web``, which opens no browser) instead of the native one."""
    # Imported here: Rerun and the recorder's dependencies slow every CLI start.
    from controller.recording import rerun_binary
    from controller.recording_layout import BLUEPRINT_FILE

    files = [str(session_dir.parent / BLUEPRINT_FILE), str(recording_of(session_dir))]
    command = [str(rerun or rerun_binary())]
    if web:
        command += ["--serve-web", "--bind", LOOPBACK]
        command += ["--web-viewer-port", str(port), "--port", str(grpc_port)]
    return command + files


def start_web_viewer(
    command: list[str], port: int, grpc_port: int, timeout_s: float = SERVER_START_S
) -> subprocess.Popen[bytes]:
    """Start the web viewer's server and return once its page answers on ``port``. Its log
    goes to a temporary file (a pipe nobody reads would stall it once full): the last line
    of it is the error when it does not start."""
    for taken in (port, grpc_port):
        # Else the page of whatever answers there would pass for this viewer's.
        if _answers(taken):
            raise RuntimeError(f"port {taken} is in use (another viewer?): choose another")
    with tempfile.TemporaryFile() as log:  # the server keeps its own descriptor of it
        process = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=log, stderr=log)
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if process.poll() is not None:
                raise RuntimeError(_last_line(log) or f"rerun exited with {process.returncode}")
            try:
                with urllib.request.urlopen(f"http://{LOOPBACK}:{port}/", timeout=1.0):
                    return process
            except (urllib.error.URLError, OSError):
                time.sleep(0.2)
    _stop(process)
    raise RuntimeError(f"the web viewer did not answer on port {port} in {timeout_s:.0f} s")


def _answers(port: int) -> bool:
    with socket.socket() as probe:
        probe.settimeout(1.0)
        return probe.connect_ex((LOOPBACK, port)) == 0


def _last_line(log: IO[bytes]) -> str:
    log.seek(0)
    lines = log.read().decode(errors="replace").strip().splitlines()
    return lines[-1] if lines else ""


def _review(args: argparse.Namespace) -> int:
    session_dir = session_folder(args.session, args.logs, args.config)
    recording = recording_of(session_dir)
    if not recording.is_file():
        print(f"touchshape: error: no recording {recording}", file=sys.stderr)
        return 2
    from controller.recording_layout import BLUEPRINT_FILE, save_blueprint

    if not (session_dir.parent / BLUEPRINT_FILE).is_file():  # a folder copied without it
        save_blueprint(session_dir.parent)
    command = review_command(session_dir, args.web, port=args.port, grpc_port=args.grpc_port)
    if not args.web:
        return subprocess.run(command).returncode
    try:
        process = start_web_viewer(command, args.port, args.grpc_port)
    except RuntimeError as error:
        print(f"touchshape: error: rerun web viewer: {error}", file=sys.stderr)
        return 1
    # Stopped any way (Ctrl-C, a kill), the command takes its server with it. Ctrl-C too when
    # the command was started with SIGINT ignored (a background job of a shell inherits that).
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, lambda number, frame: sys.exit(0))
    try:
        print(f"open {web_url(args.port, args.grpc_port)}  (Ctrl-C stops the viewer)", flush=True)
        return process.wait()
    except KeyboardInterrupt:
        return 0
    finally:
        _stop(process)


def _stop(process: subprocess.Popen[bytes]) -> None:
    """Terminate the viewer's server; kill it if it has not ended in 5 s (a loaded machine)."""
    if process.poll() is not None:
        return
    process.terminate()
    try:
        process.wait(timeout=5)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
