"""Which targets a session still proposes, and where on their line: what was measured (where
the object may be, touches that met nothing, targets the planner refused) overrides the
estimate the policy chose them from."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from controller.perception.protocol import TouchOutcome, TouchTarget
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

PadPath = tuple[float, float]
"""The pad's path about a target: (approach distance before it, the fingers' reach past it),
metres."""


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


def repeat_reason(
    target: TouchTarget,
    rejected_world: Sequence[NDArray[np.float64]],
    outcomes: Sequence[TouchOutcome],
) -> str | None:
    """Why a target repeats an earlier one (near a refused target, or a near repeat of a touch
    that met nothing), or None."""
    point, direction = target.target_world, target.direction_world
    if any(np.linalg.norm(point - r) < REJECTED_TARGET_RADIUS_M for r in rejected_world):
        return "near a target whose motions were refused"
    for outcome in outcomes:
        if outcome.measurement.contact:
            continue
        missed = outcome.measurement.target
        along = missed.direction_world / np.linalg.norm(missed.direction_world)
        offset = point - missed.target_world
        lateral = np.linalg.norm(offset - (offset @ along) * along)
        cosine = direction @ along / np.linalg.norm(direction)
        if lateral < MISSED_LINE_RADIUS_M and cosine > np.cos(np.radians(MISSED_LINE_ANGLE_DEG)):
            return "a near repeat of a touch that met nothing"
    return None
