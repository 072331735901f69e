"""Which targets a session still proposes, where on their line, and at which roll of the tool:
what was measured (where the object may be, touches that met nothing, targets the planner
refused) overrides the estimate the policy chose them from; the roll is the one at which the
estimate lets the gel's window meet the surface first."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from controller.config import Config
from controller.motion.poses import TOUCH_ROLLS_RAD, pad_pose_facing, tcp_pose_for_pad
from controller.perception.protocol import TouchOutcome, TouchTarget
from drivers.tool import ToolModel
from models.geometry import invert_transform
from models.object_bound import ObjectBound

REJECTED_TARGET_RADIUS_M = 0.01
"""Targets within this distance of one the planner refused are not proposed again."""
MISSED_LINE_RADIUS_M = 0.015
MISSED_LINE_ANGLE_DEG = 30.0
"""After a touch met nothing, a target within this distance of its line, approached within this
angle of its direction, would be a near repeat: it is not proposed."""
PAD_RADIUS_M = 0.007
"""The measured surface within this distance of a target's approach line is what the gel's
window (19 x 14 mm) meets first."""

LEADING_PARTS = ("gelsight_housing", "finger_sensor_side")
"""The rigid parts beside and behind the gel's window that can meet a surface before it (a touch
that stops on them leaves no imprint)."""
LEADING_PUSHES_M = (0.0, 0.005, 0.01)
"""How far past the estimated surface the pad is placed when a roll is scored: the surface may
be that much further (the window stands ``housing_recess_m``, 10 mm, proud of the housing)."""
LEADING_NEAR_M = 0.12
"""Only estimate points this near the target can meet the parts scored."""

PadPath = tuple[float, float]
"""The pad's path about a target: (approach distance before it, the fingers' reach past it),
metres."""


def pad_path_m(config: Config) -> PadPath:
    """The pad's path about a target: the approach distance before it, the fingers' reach
    past it (half of what the opening can still grow from the approach width)."""
    motion = config.motion
    return motion.approach_distance_m, (config.gripper.stroke_m - motion.touch_width_m) / 2


def onto_measured(
    target: TouchTarget, measured: ObjectBound | None, pad_path_m: PadPath
) -> TouchTarget | None:
    """The target moved along its approach line onto what was measured: back to the measured
    surface when the estimate put it behind that (the gel meets the surface first), forward to
    where the measured bound begins when the estimate put it in space seen free (the pad would
    sweep through nothing). None when the pad's path misses the bound altogether (a sure
    miss); the target itself without a bound."""
    if measured is None:
        return target
    distance, reach = pad_path_m
    direction = target.direction_world / np.linalg.norm(target.direction_world)
    start = target.target_world - distance * direction
    first = measured.first_along(start, direction, distance + reach)
    if first is None:
        return None
    surface = measured.surface_points_world - start
    along = surface @ direction
    lateral = np.linalg.norm(surface - along[:, None] * direction, axis=1)
    ahead = along[(along > 0) & (lateral <= PAD_RADIUS_M)]
    if len(ahead) and ahead.min() < distance:
        first = float(ahead.min())
    elif first <= distance:
        return target
    return dataclasses.replace(target, target_world=start + first * direction)


def pad_paths_meet(
    measured: ObjectBound | None,
    targets_world: NDArray[np.float64],
    direction_world: NDArray[np.float64],
    pad_path_m: PadPath,
) -> NDArray[np.bool_]:
    """Whether each target's pad path (approach start to the fingers' reach) meets the measured
    bound: a path that does not is a sure miss (all True without a bound)."""
    if measured is None:
        return np.ones(len(targets_world), dtype=bool)
    distance, reach = pad_path_m
    direction = direction_world / np.linalg.norm(direction_world)
    starts = targets_world - distance * direction
    return measured.lines_meet(starts, direction, distance + reach)


def skip_record(target: TouchTarget, touch: int, stage: str, reason: str) -> dict[str, Any]:
    """A target not touched, as the session's summary lists it (``skipped_targets``)."""
    where = {
        k: np.round(getattr(target, k), 4).tolist() for k in ("target_world", "direction_world")
    }
    return {"touch": touch, "stage": stage, **where, "reason": reason}


def repeat_reason(
    target: TouchTarget,
    rejected_world: Sequence[NDArray[np.float64]],
    outcomes: Sequence[TouchOutcome],
) -> str | None:
    """Why a target repeats an earlier one (near a refused target, or a near repeat of a touch
    that met nothing), or None."""
    point = target.target_world
    if any(np.linalg.norm(point - r) < REJECTED_TARGET_RADIUS_M for r in rejected_world):
        return "near a target whose motions were refused"
    for outcome in outcomes:
        if not outcome.measurement.contact and _on_the_line_of(target, outcome.measurement.target):
            return "a near repeat of a touch that met nothing"
    return None


def rolls_avoiding_rim_stops(
    target: TouchTarget,
    outcomes: Sequence[TouchOutcome],
    rolls_rad: Sequence[float] = TOUCH_ROLLS_RAD,
) -> tuple[float, ...]:
    """``rolls_rad`` without the rolls at which a touch along nearly the same line stopped by
    force with no imprint (a rigid part met the object before the gel): tried again there at
    that roll, the tool would meet it the same way. All of them when every one has failed."""
    failed = [
        _roll_of(outcome.measurement.pose_world_pad, outcome.measurement.target, rolls_rad)
        for outcome in outcomes
        if outcome.measurement.contact
        and len(outcome.contact_points_world) == 0
        and _on_the_line_of(target, outcome.measurement.target)
    ]
    left = tuple(r for r in rolls_rad if all(abs(r - f) > 1e-9 for f in failed))
    return left or tuple(rolls_rad)


def _on_the_line_of(target: TouchTarget, earlier: TouchTarget) -> bool:
    """Whether ``target`` lies within ``MISSED_LINE_RADIUS_M`` of an earlier touch's approach
    line and is approached within ``MISSED_LINE_ANGLE_DEG`` of its direction."""
    along = earlier.direction_world / np.linalg.norm(earlier.direction_world)
    offset = target.target_world - earlier.target_world
    lateral = np.linalg.norm(offset - (offset @ along) * along)
    cosine = target.direction_world @ along / np.linalg.norm(target.direction_world)
    return bool(
        lateral < MISSED_LINE_RADIUS_M and cosine > np.cos(np.radians(MISSED_LINE_ANGLE_DEG))
    )


def _roll_of(
    pose_world_pad: NDArray[np.float64], target: TouchTarget, rolls_rad: Sequence[float]
) -> float:
    """Which of ``rolls_rad`` the pad was turned by (the planner may have taken another than
    the target's preferred roll): the one whose pad axes lie closest to the measured pose's."""
    direction = target.direction_world / np.linalg.norm(target.direction_world)
    rotation = np.asarray(pose_world_pad)[:3, :3]

    def misfit(roll: float) -> float:
        planned = pad_pose_facing(target.target_world, -direction, 0.0, roll)[:3, :3]
        return float(np.linalg.norm(planned - rotation))

    return float(min(rolls_rad, key=misfit))


def window_leading_roll(
    target: TouchTarget,
    occupied_points_world: NDArray[np.float64],
    tool: ToolModel,
    width_m: float,
    rolls_rad: Sequence[float] = TOUCH_ROLLS_RAD,
) -> float:
    """The roll about the approach line (of ``rolls_rad``, the planner's) at which the estimate
    leaves the GelSight housing and the sensor-side finger clearest while the window presses
    on: the fewest estimate points inside those parts with the pad at the target and
    ``LEADING_PUSHES_M`` past it. The window (19 x 14 mm) is longer than wide and the housing
    reaches 8 mm past its ends but 3 mm past its sides, so on a part narrower than the housing
    or a face tilted along the finger the roll decides which meets the surface first. Ties keep
    the planner's order (its first roll is preferred for the wrist)."""
    direction = np.asarray(target.direction_world, dtype=float)
    direction = direction / np.linalg.norm(direction)
    points = np.asarray(occupied_points_world, dtype=float)
    near = np.linalg.norm(points - target.target_world, axis=1) <= LEADING_NEAR_M
    points = np.c_[points[near], np.ones(int(near.sum()))]
    if len(points) == 0:
        return float(rolls_rad[0])
    boxes = [box for box in tool.rigid_boxes(width_m) if box.name in LEADING_PARTS]
    best_roll, best_inside = float(rolls_rad[0]), None
    for roll in rolls_rad:
        inside = 0
        for push in LEADING_PUSHES_M:
            pose_world_pad = pad_pose_facing(target.target_world, -direction, -push, roll)
            pose_world_tcp = tcp_pose_for_pad(pose_world_pad, tool, width_m)
            for box in boxes:
                in_box = (invert_transform(pose_world_tcp @ box.pose_tcp_box) @ points.T)[:3].T
                inside += int(np.all(np.abs(in_box) <= box.half_extents_m, axis=1).sum())
        if best_inside is None or inside < best_inside:
            best_roll, best_inside = float(roll), inside
    return best_roll
