"""`touchshape serve` and `touchshape explore` as users run them (subprocesses), with an
untrained prior written to a temporary weights folder so the test does not depend on training."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from controller.config import MessagingConfig
from controller.messaging import open_session
from models.prior.networks import ShapeNet, SketchNet, get_preset
from models.prior.training import save_weights

TOUCHSHAPE = str(Path(sys.executable).with_name("touchshape"))


@pytest.fixture(scope="module")
def config_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("service_cli")
    weights = folder / "weights"
    weights.mkdir()
    preset = get_preset("cpu")
    save_weights(SketchNet(preset), "sketch", "cpu", weights / "sketch.pt")
    save_weights(ShapeNet(preset), "shape", "cpu", weights / "shape.pt")
    (weights / "priors.json").write_text(
        json.dumps(
            {
                "priors": [
                    {
                        "name": "general",
                        "preset": "cpu",
                        "sketch_weights": "sketch.pt",
                        "shape_weights": "shape.pt",
                        "grid_extent_m": 0.26,
                    }
                ]
            }
        )
    )
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    path = folder / "config.toml"
    path.write_text(
        f'[models]\nweights_dir = "{weights}"\n'
        f'[messaging]\nlisten = ["tcp/127.0.0.1:{port}"]\n'
        f'[logging]\ndir = "{folder / "logs"}"\n'
        '[sim]\nobject = "can"\n'
    )
    return path


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_serve_stops_cleanly_on_signals(config_file: Path, sig: signal.Signals) -> None:
    process = subprocess.Popen(
        [TOUCHSHAPE, "serve", "--config", str(config_file)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert process.stdout is not None
        deadline = time.monotonic() + 120
        lines = []
        for line in process.stdout:
            lines.append(line)
            if "touchshape serving" in line:
                break
            assert time.monotonic() < deadline, "service did not start"
        else:
            pytest.fail(f"service exited early with {process.wait()}")
        # What test_bad_endpoint_fails_before_any_device_moves must not see.
        assert any("homing the gripper" in line for line in lines)
        process.send_signal(sig)
        assert process.wait(timeout=60) == 0
    finally:
        if process.poll() is None:
            process.kill()


@pytest.mark.parametrize("listen", ["taken", "garbage", "tcp/127.0.0.1:99999"])
def test_bad_endpoint_fails_before_any_device_moves(config_file: Path, listen: str) -> None:
    """A second `serve` on a used port, or an endpoint Zenoh cannot bind: one line naming the
    endpoint, rc 2, and no device connected (the gripper is not homed)."""
    holder = None
    if listen == "taken":
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            listen = f"tcp/127.0.0.1:{probe.getsockname()[1]}"
        holder = open_session(MessagingConfig(listen=(listen,)))  # as a first `serve` does
    try:
        started = time.monotonic()
        result = subprocess.run(
            [TOUCHSHAPE, "serve", "--config", str(config_file), "--listen", listen],
            capture_output=True,
            text=True,
            timeout=120,
        )
        elapsed = time.monotonic() - started
    finally:
        if holder is not None:
            holder.close()
    print(f"serve --listen {listen}: rc {result.returncode} after {elapsed:.2f} s")
    assert result.returncode == 2, result.stdout + result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("touchshape: error:"), result.stderr
    assert listen in lines[0]
    assert "homing" not in result.stdout + result.stderr
    assert "touchshape serving" not in result.stdout


def test_explore_rejects_a_bad_budget(config_file: Path) -> None:
    result = subprocess.run(
        [TOUCHSHAPE, "explore", "--config", str(config_file), "--touches", "0"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2 and "--touches" in result.stderr
