"""`touchshape calibrate robot`: the registration users paste into their config."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from controller.cli.main import main
from models.geometry import make_transform, transform_points, ur_pose_to_matrix


def write_points(path: Path, world: np.ndarray, robot: np.ndarray) -> None:
    lines = ["world_x,world_y,world_z,robot_x,robot_y,robot_z"]
    lines += [",".join(f"{v:.6f}" for v in (*w, *r)) for w, r in zip(world, robot, strict=True)]
    path.write_text("\n".join(lines) + "\n")


def test_recovers_the_base_pose(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rng = np.random.default_rng(3)
    pose_world_base = make_transform(
        Rotation.from_euler("z", 30, degrees=True).as_matrix(), (0.05, -0.42, 0.01)
    )
    world = rng.uniform(-0.2, 0.2, (6, 3)) * [1, 1, 0.5]
    robot = transform_points(np.linalg.inv(pose_world_base), world) + rng.normal(0, 3e-4, (6, 3))
    write_points(tmp_path / "points.csv", world, robot)
    assert main(["calibrate", "robot", "--points", str(tmp_path / "points.csv")]) == 0
    out = capsys.readouterr().out
    values = [float(v) for v in re.search(r"pose_world_base = \[(.*)\]", out).group(1).split(",")]
    recovered = ur_pose_to_matrix(values)
    assert np.linalg.norm(recovered[:3, 3] - pose_world_base[:3, 3]) < 1e-3
    assert "6 points, rms residual" in out


def test_bad_points_are_clear_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "bad.csv"
    path.write_text("world_x,world_y\n1,2\n")
    assert main(["calibrate", "robot", "--points", str(path)]) == 2
    assert "missing column" in capsys.readouterr().err
    collinear = np.array([[0.0, 0, 0], [0.1, 0, 0], [0.2, 0, 0]])
    write_points(path, collinear, collinear)
    assert main(["calibrate", "robot", "--points", str(path)]) == 2
    assert "collinear" in capsys.readouterr().err


def test_large_residuals_fail(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    world = np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0.1, 0.1, 0]])
    robot = world.copy()
    robot[3] += [0.01, 0, 0]  # one point 1 cm off
    write_points(tmp_path / "p.csv", world, robot)
    assert main(["calibrate", "robot", "--points", str(tmp_path / "p.csv")]) == 1
    assert "re-measure" in capsys.readouterr().out
