"""A session as a new user runs it (subprocesses, the committed priors): `explore` is quiet and
leaves a picture and a log; `sessions` lists it; `replay` reproduces its voxels from the
recorded inputs alone, and names a missing input in one line."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rerun_cli
from PIL import Image

# A whole session and its replays on 2 cores: minutes, not the default 120 s.
pytestmark = pytest.mark.timeout(900)

TOUCHSHAPE = str(Path(sys.executable).with_name("touchshape"))
RERUN = str(Path(rerun_cli.__file__).with_name("rerun"))


def _run(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run([TOUCHSHAPE, *args], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def explored(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, subprocess.CompletedProcess]:
    """One two-touch session of the mug in a fresh logs folder: (its folder, the run)."""
    root = tmp_path_factory.mktemp("explore")
    config = root / "config.toml"
    config.write_text(f'[logging]\ndir = "{root / "logs"}"\n')
    run = _run("explore", "--config", str(config), "--object", "mug", "--touches", "2")
    assert run.returncode == 0, run.stdout + run.stderr
    [folder] = [path for path in (root / "logs").iterdir() if path.is_dir()]
    return folder, run


def test_explore_is_quiet_and_leaves_a_picture_and_a_log(explored: tuple) -> None:
    folder, run = explored
    lines = run.stdout.splitlines()
    assert len(lines) <= 25, run.stdout
    assert sum(line.startswith("touch ") for line in lines) == 2
    assert "Chamfer" in run.stdout and "picture" in run.stdout
    assert "INFO" not in run.stderr, run.stderr  # log records go to the file without -v
    log = (folder / "session.log").read_text()
    assert "capture -> reconstruct" in log and "refine -> " in log
    summary = json.loads((folder / "summary.json").read_text())
    assert summary["artifacts"]["picture"] == str(folder / "shape.png")
    assert summary["object"] == "mug" and summary["started"].endswith("+00:00")
    # Three panels (vision, touched, truth), none blank.
    image = np.asarray(Image.open(folder / "shape.png").convert("L"), dtype=float)
    thirds = np.array_split(image, 3, axis=1)
    assert all(panel.std() > 20 for panel in thirds), [panel.std() for panel in thirds]


def test_sessions_lists_the_session(explored: tuple) -> None:
    folder, _ = explored
    listed = _run("sessions", "--logs", str(folder.parent), "--json")
    assert listed.returncode == 0, listed.stderr
    [entry] = json.loads(listed.stdout)
    assert entry["id"] == folder.name and entry["touches"] == 2 and entry["state"] == "done"


def test_replay_reproduces_the_voxels(explored: tuple, tmp_path: Path) -> None:
    folder, _ = explored
    run = _run("replay", str(folder), "--logs", str(tmp_path))
    assert run.returncode == 0, run.stdout + run.stderr
    [replayed] = [path for path in tmp_path.iterdir() if path.is_dir()]
    summary = json.loads((replayed / "summary.json").read_text())
    assert summary["replay_of"] == str(folder) and summary["touches"] == 2
    original = np.load(folder / "voxels.npz")
    again = np.load(replayed / "voxels.npz")
    assert np.array_equal(original["matrix_world_voxel"], again["matrix_world_voxel"])
    difference = np.abs(
        original["probabilities"].astype(np.float32) - again["probabilities"].astype(np.float32)
    )
    assert difference.max() <= 1e-3
    # Its own recording, whole; and its inputs, so the replay replays in turn.
    verify = subprocess.run(
        [RERUN, "rrd", "verify", str(tmp_path / f"{replayed.name}.rrd")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert verify.returncode == 0, verify.stdout + verify.stderr
    assert (replayed / "gelsight" / "touch_002.png").is_file()
    assert (replayed / "camera" / "depth_mm.png").is_file()


def test_replay_names_a_missing_gelsight_image(explored: tuple, tmp_path: Path) -> None:
    folder, _ = explored
    broken = tmp_path / folder.name
    shutil.copytree(folder, broken)
    missing = broken / "gelsight" / "touch_002.png"
    missing.unlink()
    run = _run("replay", str(broken), "--logs", str(tmp_path / "logs"), timeout=120)
    assert run.returncode != 0
    assert run.stderr.strip() == f"touchshape: error: {missing}: missing"
    assert not (tmp_path / "logs").exists()  # nothing written
