"""`touchshape calibrate robot`: robot registration, the paper's world<-robot transform from
points measured in both frames."""

from __future__ import annotations

import argparse
import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.geometry import Registration, invert_transform, matrix_to_ur_pose, register_points

COLUMNS = ("world_x", "world_y", "world_z", "robot_x", "robot_y", "robot_z")

EPILOG = """The CSV has a header and one row per calibration point, metres:
  world_x,world_y,world_z,robot_x,robot_y,robot_z
  0,0,0,0.0512,-0.4187,0.0021
  0.1,0,0,0.1511,-0.4190,0.0019
  0,0.1,0,0.0509,-0.3188,0.0022
World points are marks on the table (the object point is the origin, z up); robot points are
the TCP positions the pendant (or `touchshape check arm`) shows with the TCP touching them.
Three points reproduce the paper's registration; more give a least-squares fit and the
residuals say how good it is. Paste the printed [robot.arm] line into your config.

example: touchshape calibrate robot --points calibration.csv
"""


def add_commands(groups: argparse._SubParsersAction) -> None:
    """Add `calibrate robot`."""
    calibrate = groups.add_parser("calibrate", help="register the robot to the world")
    commands = calibrate.add_subparsers(dest="command", required=True)
    robot = commands.add_parser(
        "robot",
        help="world<-robot transform from 3+ points measured in both frames",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    robot.add_argument("--points", type=Path, required=True, help="CSV of point pairs")
    robot.add_argument(
        "--max-residual-mm", type=float, default=2.0, help="fail above this residual (mm)"
    )
    robot.set_defaults(handler=_calibrate_robot)


@dataclass(frozen=True)
class RobotRegistration:
    """Where the robot's base is in the world, and how well the measured points agreed."""

    pose_world_base: np.ndarray
    """4x4; the config's robot.arm.pose_world_base."""
    fit: Registration
    """The paper's x_r = R_r x_w + T_r fitted to the points, with the residuals."""


def register_robot(points_world: np.ndarray, points_robot: np.ndarray) -> RobotRegistration:
    """Register the robot from (N, 3) points measured in the world and robot frames."""
    fit = register_points(points_world, points_robot)
    return RobotRegistration(invert_transform(fit.transform_to_from), fit)


def read_point_pairs(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """World and robot points (N, 3) from the CSV; ValueError naming the problem."""
    try:
        with path.open(newline="", encoding="utf-8") as file:
            rows = list(csv.DictReader(file))
    except OSError as error:
        raise ValueError(f"cannot read {path}: {error}") from None
    if not rows:
        raise ValueError(f"{path}: no calibration points")
    missing = [c for c in COLUMNS if c not in rows[0]]
    if missing:
        raise ValueError(f"{path}: missing column(s) {missing}; need {', '.join(COLUMNS)}")
    try:
        values = np.array([[float(row[c]) for c in COLUMNS] for row in rows])
    except (TypeError, ValueError) as error:
        raise ValueError(f"{path}: not a number: {error}") from None
    return values[:, :3], values[:, 3:]


def _calibrate_robot(args: argparse.Namespace) -> int:
    registration = register_robot(*read_point_pairs(args.points))
    fit = registration.fit
    print(f"registration: {fit.report()}")
    for index, residual in enumerate(fit.residuals_m):
        print(f"  point {index}: residual {residual * 1e3:.2f} mm")
    print("[robot.arm]")
    pose = matrix_to_ur_pose(registration.pose_world_base)
    print("pose_world_base = [" + ", ".join(f"{v:.6f}" for v in pose) + "]")
    if fit.max_residual_m * 1e3 > args.max_residual_mm:
        print(
            f"error: max residual {fit.max_residual_m * 1e3:.2f} mm is above "
            f"{args.max_residual_mm} mm: re-measure the points"
        )
        return 1
    return 0
