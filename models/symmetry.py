"""Symmetry completion: the unseen side of an object from the side the camera saw.

Many household objects are mirror- or rotation-symmetric about their vertical. As in Bohg et
al., "Mind the gap - robotic grasping under incomplete observation" (ICRA 2011), the seen points
are mirrored about candidate vertical planes (and turned about candidate vertical axes); a
candidate is refuted by mirrored points that land where the camera saw empty space (in front of
the measured surface, or on a ray that reached the table: :class:`models.prior.carving.CameraView`).
Of the candidates with few refuted points that put enough points out of sight (they complete
something), the one whose copies stand least far into free space wins; its copies that are not
refuted and lie out of sight become weaker surface observations (source -2) of the fused field.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from models.geometry import rotation_about_axis
from models.prior.carving import CameraView
from models.touch.observations import (
    CAMERA_SPACING_M,
    MAX_CAMERA_POINTS,
    SurfaceObservations,
    thin_to_count,
)

FloatArray = NDArray[np.float64]
Candidate = tuple[str, FloatArray, FloatArray]
"""("plane" or "axis", a point on it, the plane's normal or the axis)."""

SYMMETRY_SOURCE = -2
"""``SurfaceObservations.surface_source`` of the mirrored points."""
PLANE_ANGLES = 12
"""Candidate plane normals every 15 degrees (a plane's normal and its opposite are one)."""
OFFSETS = 9
"""Candidate positions of each plane (or axis) along its normal, across the seen extent."""
AXIS_TURNS = (60.0, 120.0, 180.0, 240.0, 300.0)
"""A rotation-symmetric candidate's copies of the seen points (degrees about the axis)."""
MAX_REFUTED = 0.08
"""A candidate with more of its points in seen-empty space than this fraction is rejected."""
COARSE_KEPT = 4
"""Coarse candidates (the least contradicted) searched finer before one is chosen."""
VIOLATION_NOISE_M = 0.002
"""A copy counts as standing in free space by how far it is in front of the seen surface, less
the depth noise (Kinect v2: 1.5 mm at 0.6-0.8 m)."""
VIOLATION_CAP_M = 0.02
"""... capped, so that a few far copies (a handle mirrored into the open) do not decide."""
MIN_HIDDEN = 0.3
"""A candidate must put at least this fraction of its points out of sight: a plane that only
maps the seen side onto itself completes nothing."""


@dataclass(frozen=True)
class SymmetryFit:
    """The chosen symmetry: a vertical ``plane`` (``direction_world`` its horizontal normal) or
    a vertical ``axis`` (``direction_world`` = +z), through ``point_world``."""

    kind: Literal["plane", "axis"]
    point_world: FloatArray
    direction_world: FloatArray
    refuted_fraction: float
    hidden_fraction: float
    observations: SurfaceObservations
    """The completed points (source :data:`SYMMETRY_SOURCE`) with their mirrored normals."""

    def summary(self) -> dict[str, object]:
        return {
            "kind": self.kind,
            "point_world_m": np.round(self.point_world, 4).tolist(),
            "direction_world": np.round(self.direction_world, 4).tolist(),
            "refuted_fraction": round(self.refuted_fraction, 4),
            "hidden_fraction": round(self.hidden_fraction, 4),
            "points": len(self.observations.surface_points_world),
        }


def _mirror(points: FloatArray, point: FloatArray, normal: FloatArray) -> FloatArray:
    return points - 2.0 * ((points - point) @ normal)[..., None] * normal


def complete_by_symmetry(camera: SurfaceObservations, view: CameraView) -> SymmetryFit | None:
    """The best-supported vertical symmetry of the seen surface ``camera`` (the depth points'
    observations, source -1) judged by what ``view`` (the frame's depth) saw, with its
    completed points; None when no candidate is supported."""
    seen = camera.surface_points_world
    if len(seen) < 10:
        return None
    points, normals = seen, camera.surface_normals_world
    centre = np.array([*points[:, :2].mean(axis=0), 0.0])
    reach = 0.5 * float(np.max(np.ptp(points[:, :2], axis=0))) + 0.01
    offsets = np.linspace(-reach, reach, OFFSETS)
    up = np.array([0.0, 0.0, 1.0])
    turns = [rotation_about_axis(up, math.radians(t)) for t in AXIS_TURNS]

    def copies_of(kind: str, point: FloatArray, direction: FloatArray) -> FloatArray:
        if kind == "plane":
            return _mirror(points, point, direction)
        return np.concatenate([(points - point) @ r.T + point for r in turns])

    def plane(angle: float, offset: float) -> Candidate:
        normal = np.array([math.cos(angle), math.sin(angle), 0.0])
        return ("plane", centre + offset * normal, normal)

    step = offsets[1] - offsets[0]

    def judged(candidates: list[Candidate]) -> NDArray[np.float64]:
        """(refuted fraction, hidden fraction, cost) of each candidate, one row each: the cost
        is how far the copies stand in free space, graded: a plane ahead of the true one pushes
        copies out in front of the seen surface, one behind it pushes the copies of the outline
        off the object, in front of the table. One projection per kind of candidate."""
        scores = np.zeros((len(candidates), 3))
        for kind in ("plane", "axis"):
            rows = [i for i, candidate in enumerate(candidates) if candidate[0] == kind]
            if not rows:
                continue
            verdict = view.judge(np.stack([copies_of(*candidates[i]) for i in rows]))
            refuted, hidden = verdict.empty, verdict.hidden & ~verdict.empty
            ahead = np.clip(verdict.in_front_m - VIOLATION_NOISE_M, 0.0, VIOLATION_CAP_M)
            scores[rows] = np.column_stack(
                [refuted.mean(axis=1), hidden.mean(axis=1), ahead.mean(axis=1)]
            )
        return scores

    def refined(candidate: Candidate, scale: float) -> list[Candidate]:
        """Candidates around ``candidate``: ``scale`` quarter steps apart, planes ``scale`` x 2.5
        degrees apart."""
        kind, point, direction = candidate
        fine_steps = scale * step * np.arange(-4, 5) / 4.0
        if kind == "axis":
            return [
                ("axis", point + np.array([dx, dy, 0.0]), up)
                for dx in fine_steps
                for dy in fine_steps
            ]
        angle = math.atan2(direction[1], direction[0])
        offset = float((point - centre) @ direction)
        return [
            plane(angle + math.radians(scale * d), offset + o)
            for d in (-7.5, -5.0, -2.5, 0.0, 2.5, 5.0, 7.5)
            for o in fine_steps
        ]

    def best_of(candidates: list[Candidate]) -> Candidate | None:
        """Of the candidates that pass (few refuted, enough hidden), the one whose copies stand
        least far in free space."""
        scores = judged(candidates)
        passing = (scores[:, 0] <= MAX_REFUTED) & (scores[:, 1] >= MIN_HIDDEN)
        if not passing.any():
            return None
        return candidates[int(np.argmin(np.where(passing, scores[:, 2], np.inf)))]

    # A coarse search (planes every 15 degrees, planes and axes a ninth of the width apart)
    # ranks the candidates by how little they contradict; the best few are searched finer (a
    # quarter step, 2.5 degrees) before any is judged: on an elongated object (an animal seen
    # from the side) a plane 7.5 degrees off the true one sends the copies of its ends into
    # free space, so no coarse candidate passes. The choice is searched finer once more (a
    # sixteenth of a step, 0.6 degrees): a plane a few millimetres off moves its copies twice
    # as far.
    angles = [math.pi * k / PLANE_ANGLES for k in range(PLANE_ANGLES)]
    coarse = [plane(a, o) for a in angles for o in offsets]
    coarse += [("axis", centre + np.array([dx, dy, 0.0]), up) for dx in offsets for dy in offsets]
    scores = judged(coarse)
    rank = scores[:, 0] + scores[:, 2] / VIOLATION_CAP_M
    ranked = [i for i in np.argsort(rank, kind="stable") if scores[i, 1] >= MIN_HIDDEN]
    fine = [c for i in ranked[:COARSE_KEPT] for c in [coarse[i], *refined(coarse[i], 1.0)]]
    found = best_of(fine) if fine else None
    if found is None:
        return None
    found = best_of([found, *refined(found, 0.25)]) or found
    kind, point, direction = found
    copies = copies_of(kind, point, direction)
    if kind == "plane":
        copy_normals = _mirror(normals, np.zeros(3), direction)
    else:
        copy_normals = np.concatenate([normals @ r.T for r in turns])
    verdict = view.judge(copies)
    refuted, hidden = verdict.empty, verdict.hidden & ~verdict.empty
    kept = np.flatnonzero(hidden & (copies[:, 2] > 0))
    kept = kept[thin_to_count(copies[kept], CAMERA_SPACING_M, MAX_CAMERA_POINTS)]
    observations = SurfaceObservations(
        copies[kept],
        copy_normals[kept],
        np.zeros((0, 3)),
        np.full(len(kept), SYMMETRY_SOURCE, np.int64),
    )
    return SymmetryFit(
        kind,  # type: ignore[arg-type]
        point,
        direction,
        float(refuted.mean()),
        float(hidden.mean()),
        observations,
    )
