"""Generated shape families that cover everyday objects beyond the paper's 14 categories.

Each family draws a random watertight solid from a ``numpy.random.Generator`` only (a seed
reproduces it exactly) and scales it to a largest extent drawn log-uniformly in
:data:`SIZE_RANGE_M`, so the priors see objects from a 3 cm lemon to a 30 cm helmet. Meshes are
in the table frame of :mod:`models.shapes` (metres, z up, bottom centre at the origin).

Star-shaped families (superquadrics, blobs, some fruit) warp a geodesic sphere radially, which
keeps the surface closed and free of self-intersections; the others are revolutions, extrusions
and boolean unions in manifold3d, closed by construction.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import trimesh
from manifold3d import CrossSection, Manifold

from models import solids
from models.procedural import ALL_CATEGORIES
from models.shapes import ShapeError, place_on_table

SIZE_RANGE_M = (0.03, 0.30)
"""Largest extent of a family shape: log-uniform in this range (metres)."""

_SPHERE_SEGMENTS = 48


def _log_uniform(rng: np.random.Generator, low: float, high: float) -> float:
    return float(math.exp(rng.uniform(math.log(low), math.log(high))))


def _radial_warp(radius: Callable[[np.ndarray], np.ndarray]) -> Manifold:
    """A unit sphere whose surface point in direction d moves to ``radius(d) * d``."""

    def warp(points: np.ndarray) -> np.ndarray:
        directions = points / np.linalg.norm(points, axis=1, keepdims=True)
        return directions * radius(directions)[:, None]

    return Manifold.sphere(1.0, _SPHERE_SEGMENTS).warp_batch(warp)


def _superquadric(rng: np.random.Generator) -> Manifold:
    """Superellipsoid: from a box with round edges (exponents near 0.2) to a pinched star."""
    a, b, c = rng.uniform(0.3, 1.0, 3)
    e1, e2 = rng.uniform(0.25, 1.6, 2)  # vertical and horizontal roundness

    def radius(d: np.ndarray) -> np.ndarray:
        x, y, z = np.abs(d).T + 1e-12
        horizontal = ((x / a) ** (2 / e2) + (y / b) ** (2 / e2)) ** (e2 / e1)
        return (horizontal + (z / c) ** (2 / e1)) ** (-e1 / 2)

    return _radial_warp(radius)


def _blob(rng: np.random.Generator) -> Manifold:
    """A smooth organic blob: a sphere displaced by a few low-frequency waves, then stretched."""
    waves = rng.normal(size=(int(rng.integers(3, 7)), 3))
    frequencies = rng.uniform(1.0, 3.0, len(waves))
    phases = rng.uniform(0, 2 * math.pi, len(waves))
    amplitudes = rng.uniform(0.05, 0.2, len(waves))
    unit_waves = waves / np.linalg.norm(waves, axis=1, keepdims=True)

    def radius(d: np.ndarray) -> np.ndarray:
        bumps = np.cos(d @ unit_waves.T * frequencies + phases) @ amplitudes
        return np.exp(bumps)

    return _radial_warp(radius).scale(tuple(rng.uniform(0.5, 1.0, 3)))


def _smooth_profile(rng: np.random.Generator, points: int, low: float, high: float) -> np.ndarray:
    """``points`` radii from ``low`` to ``high`` times the base, varying smoothly."""
    knots = rng.uniform(low, high, int(rng.integers(3, 6)))
    return np.interp(np.linspace(0, 1, points), np.linspace(0, 1, len(knots)), knots)


def _hollowed(
    body: Manifold, radii: np.ndarray, z: np.ndarray, wall: float, floor: float
) -> Manifold:
    """A revolved ``body`` (``radii`` at heights ``z``) hollowed from the top: a wall ``wall``
    thick and a floor at height ``floor``."""
    height = float(z[-1])
    inner_radii = np.maximum(radii - wall, 0.5 * wall)[z > floor]
    inner = [(0.0, floor), *zip(inner_radii.tolist(), z[z > floor].tolist(), strict=True)]
    inner += [(float(inner_radii[-1]), height + 0.1), (0.0, height + 0.1)]
    return body - solids.revolve(inner)


def _revolved(rng: np.random.Generator) -> Manifold:
    """A random solid of revolution (vase, bottle, spool, cup); a third are hollow vessels."""
    height = rng.uniform(0.5, 2.0)
    z = np.linspace(0.0, height, 24)
    radii = np.convolve(_smooth_profile(rng, 28, 0.25, 1.0), np.ones(5) / 5, mode="valid")
    outline = [(0.0, 0.0), *zip(radii.tolist(), z.tolist(), strict=True), (0.0, height)]
    body = solids.revolve(outline)
    if rng.random() < 1 / 3:  # hollow from the top, with a floor and a wall
        wall = rng.uniform(0.04, 0.12) * float(radii.min())
        body = _hollowed(body, radii, z, wall, rng.uniform(0.05, 0.2) * height)
    return body


def _extruded(rng: np.random.Generator) -> Manifold:
    """A random smooth outline (star-shaped, up to 4 lobes) extruded, tapered, maybe lying."""
    angles = np.linspace(0, 2 * math.pi, 64, endpoint=False)
    harmonics = np.arange(1, 5)
    amplitudes = rng.uniform(0, 0.25, 4) / harmonics
    radii = 1.0 + np.cos(np.outer(angles, harmonics) + rng.uniform(0, 2 * math.pi, 4)) @ amplitudes
    outline = np.column_stack([radii * np.cos(angles), radii * np.sin(angles)])
    outline *= rng.uniform(0.3, 1.0, 2)
    taper = rng.uniform(0.6, 1.0) if rng.random() < 0.3 else 1.0
    body = CrossSection([outline]).extrude(rng.uniform(0.2, 2.0), scale_top=(taper, taper))
    if rng.random() < 0.3:  # lying on its side
        body = body.rotate((90.0, 0.0, 0.0))
    return body


def _box(rng: np.random.Generator) -> Manifold:
    """A box of any aspect ratio (flat tile to tall column), sometimes with rounded edges."""
    size = np.array([_log_uniform(rng, 0.1, 1.0) for _ in range(3)])
    radius = rng.uniform(0.0, 0.3) * float(min(size[:2])) if rng.random() < 0.4 else 0.0
    if radius < 1e-3:
        return Manifold.cube(tuple(size.tolist()), center=True)
    return solids.slab(float(size[0]), float(size[1]), float(size[2]), radius)


def _primitive(rng: np.random.Generator) -> Manifold:
    kind = rng.integers(3)
    a, b, c = rng.uniform(0.15, 0.6, 3)
    if kind == 0:
        return Manifold.cube((a, b, c), center=True)
    if kind == 1:
        return solids.cylinder(a / 2, c).translate((0.0, 0.0, -c / 2))
    return solids.ellipsoid(a / 2, b / 2, c / 2, segments=32)


def _primitive_union(rng: np.random.Generator) -> Manifold:
    """2-4 boxes, cylinders and ellipsoids, each overlapping the last (a lamp, a toy, a tool)."""
    body = _primitive(rng)
    for _ in range(int(rng.integers(1, 4))):
        low, high = np.asarray(body.bounding_box()[:3]), np.asarray(body.bounding_box()[3:])
        # Attach at a random point of the bounding box's middle half: the parts overlap.
        anchor = low + (high - low) * rng.uniform(0.25, 0.75, 3)
        part = _primitive(rng).rotate(tuple(rng.uniform(-45, 45, 3).tolist()))
        body = body + part.translate(tuple(anchor.tolist()))
    return body


def _fruit(rng: np.random.Generator) -> Manifold:
    """Apple, orange, pear, lemon or bread roll: rounded solids with their typical features."""
    kind = rng.integers(5)
    if kind == 0:  # apple: a sphere dimpled at both poles
        dimple = rng.uniform(0.1, 0.25)
        return _radial_warp(lambda d: 1.0 - dimple * np.abs(d[:, 2]) ** 8).scale((1, 1, 0.9))
    if kind == 1:  # orange: a slightly squashed sphere
        return Manifold.sphere(1.0, _SPHERE_SEGMENTS).scale((1.0, 1.0, rng.uniform(0.85, 1.0)))
    if kind == 2:  # pear: two bulbs along z
        profile = [(0.0, 0.0)]
        z = np.linspace(0, math.pi, 33)[1:-1]
        small = rng.uniform(0.45, 0.7)
        radii = np.sin(z) * (1.0 - (1.0 - small) * np.clip((z / math.pi - 0.4) / 0.4, 0, 1))
        profile += list(zip(radii.tolist(), (z / math.pi * 2.4).tolist(), strict=True))
        return solids.revolve([*profile, (0.0, 2.4)])
    if kind == 3:  # lemon: an ellipsoid with pointed tips, lying on its side
        tip = rng.uniform(0.1, 0.3)
        body = _radial_warp(lambda d: 1.0 + tip * np.abs(d[:, 0]) ** 12)
        return body.scale((1.0, rng.uniform(0.6, 0.8), rng.uniform(0.6, 0.8)))
    # bread roll: a flattened ellipsoid with a flat bottom
    roll = solids.ellipsoid(1.0, rng.uniform(0.6, 1.0), rng.uniform(0.4, 0.7))
    return roll.trim_by_plane((0.0, 0.0, 1.0), -0.1)


def _limb(start: np.ndarray, end: np.ndarray, radius: float) -> Manifold:
    """A round-ended limb (a capsule) from ``start`` to ``end``."""
    axis = end - start
    length = float(np.linalg.norm(axis))
    tube = solids.cylinder(radius, length) + Manifold.sphere(radius, 16)
    tube = tube + Manifold.sphere(radius, 16).translate((0.0, 0.0, length))
    tilt = math.degrees(math.acos(np.clip(axis[2] / length, -1.0, 1.0)))
    heading = math.degrees(math.atan2(axis[1], axis[0]))
    return tube.rotate((0.0, tilt, 0.0)).rotate((0.0, 0.0, heading)).translate(tuple(start))


def _creature(rng: np.random.Generator) -> Manifold:
    """An animal or figurine: an ellipsoid body on two or four legs, a head, maybe a tail.

    Figurines, toys and ornaments are mostly limbed bodies that no primitive family draws: a
    four-legged body (long along x) half the time, an upright body on two legs otherwise.
    """
    upright = rng.random() < 0.5
    a, b, c = (rng.uniform(0.25, 0.5), rng.uniform(0.2, 0.35), rng.uniform(0.4, 0.8))
    if not upright:
        a = rng.uniform(0.6, 1.0)
        b, c = rng.uniform(0.3, 0.6) * a, rng.uniform(0.2, 0.45)
    leg_length = rng.uniform(0.15, 0.8) * (c if upright else 2 * c + 0.2)
    centre = np.array([0.0, 0.0, leg_length + 0.7 * c])
    parts = [solids.ellipsoid(a, b, c, segments=32).translate(tuple(centre))]
    leg_radius = rng.uniform(0.25, 0.5) * min(b, c)
    hips = [(0.0, 0.6 * b)] if upright else [(0.6 * a, 0.6 * b), (-0.6 * a, 0.6 * b)]
    for x, y in hips:
        for side in (1.0, -1.0):
            hip = centre + np.array([x, side * y, -0.5 * c])
            foot = np.array([x + rng.uniform(-0.1, 0.1), side * y * rng.uniform(0.8, 1.3), 0.0])
            parts.append(_limb(hip, foot + np.array([0.0, 0.0, leg_radius]), leg_radius))
    head_size = rng.uniform(0.3, 0.6) * (b + c) / 2
    if upright:
        head = centre + np.array([0.0, 0.0, c + 0.6 * head_size])
        arm = np.array([rng.uniform(-0.3, 0.3), b + 0.3 * c, -0.3 * c])
        for side in (1.0, -1.0):
            shoulder = centre + np.array([0.0, side * 0.8 * b, 0.5 * c])
            parts.append(_limb(shoulder, centre + arm * [1.0, side, 1.0], 0.7 * leg_radius))
    else:
        head = centre + np.array([a + 0.4 * head_size, 0.0, rng.uniform(0.3, 1.5) * c])
        parts.append(_limb(centre + np.array([0.7 * a, 0.0, 0.3 * c]), head, 0.6 * head_size))
        if rng.random() < 0.6:
            tail_end = centre + np.array([-a - rng.uniform(0.2, 0.6), 0.0, rng.uniform(-c, c)])
            parts.append(_limb(centre - [0.8 * a, 0.0, 0.0], tail_end, 0.3 * leg_radius))
    stretch = rng.uniform(0.8, 1.3, 3) * [1.0, 0.8, 1.0]
    parts.append(solids.ellipsoid(*(head_size * stretch), segments=24).translate(tuple(head)))
    return solids.union(parts)


def _vessel(rng: np.random.Generator) -> Manifold:
    """A vessel with a handle: a mug or jug (open), or a teapot, kettle or watering can (lidded,
    half of them with a spout).

    Household objects are often revolved bodies with parts off the axis, which the revolved
    family lacks: the handle and the spout are what single-view completion must guess.
    """
    height = rng.uniform(0.8, 2.2)
    z = np.linspace(0.0, height, 20)
    radii = np.convolve(_smooth_profile(rng, 24, 0.55, 1.0), np.ones(5) / 5, mode="valid")
    body = solids.revolve(
        [(0.0, 0.0), *zip(radii.tolist(), z.tolist(), strict=True), (0.0, height)]
    )
    parts = []
    if rng.random() < 0.5:  # open: hollow from the top, as a mug or a jug
        wall = rng.uniform(0.05, 0.12) * float(radii.min())
        body = _hollowed(body, radii, z, wall, rng.uniform(0.05, 0.15) * height)
    else:  # lidded: a knob on top, and a spout half the time
        knob = rng.uniform(0.08, 0.2)
        parts.append(
            solids.ellipsoid(knob, knob, 0.7 * knob, segments=24).translate((0, 0, height))
        )
        if rng.random() < 0.5:
            z_spout = rng.uniform(0.2, 0.5) * height
            r_spout = float(np.interp(z_spout, z, radii))
            length = rng.uniform(0.4, 0.9)
            rise = rng.uniform(0.5, 1.5)
            start = np.array([-0.7 * r_spout, 0.0, z_spout])
            end = np.array([-r_spout - length, 0.0, z_spout + rise * length])
            parts.append(_limb(start, end, rng.uniform(0.06, 0.14)))
    # The handle: a C-shaped tube arc whose ends sink into the body's side (+x).
    z_low, z_high = np.sort(rng.uniform(0.15, 0.9, 2)) * height
    z_high = max(z_high, z_low + 0.25 * height)
    span = (z > z_low - 0.05) & (z < z_high + 0.05)
    major = (z_high - z_low) / 2
    degrees = rng.uniform(200.0, 250.0)
    minor = rng.uniform(0.04, 0.1)
    # Stretched along x so that it stands out of the body by 0.3-0.8 of the body's radius.
    reach = float(radii[span].max() - radii[span].min()) + rng.uniform(0.3, 0.8) * float(
        radii.max()
    )
    stretch = max(1.0, reach / (major + minor))
    handle = solids.ring_arc(major, minor, degrees).scale((stretch, 1.0, 1.0))
    parts.append(handle.translate((float(radii[span].min()), 0.0, (z_low + z_high) / 2)))
    return solids.union([body, *parts])


_FAMILIES: dict[str, Callable[[np.random.Generator], Manifold]] = {
    "superquadric": _superquadric,
    "revolved": _revolved,
    "extruded": _extruded,
    "box_any": _box,
    "primitive_union": _primitive_union,
    "blob": _blob,
    "fruit": _fruit,
    "creature": _creature,
    "vessel": _vessel,
}

FAMILIES: tuple[str, ...] = tuple(_FAMILIES)
"""The generated families, in a fixed order (their index seeds their shapes)."""

HELD_OUT_FAMILIES: tuple[str, ...] = ("extruded", "fruit")
"""Families never trained on: evaluation measures how the priors generalise to them."""

SHAPE_GROUPS: tuple[str, ...] = (*ALL_CATEGORIES, *FAMILIES)
"""Everything generated shapes are drawn from: the 14 categories, the box family, the families.
A group's index here seeds its shapes, so new groups are only ever appended."""


def make_family_shape(family: str, rng: np.random.Generator) -> trimesh.Trimesh:
    """A random watertight shape of ``family``, scaled to a size in :data:`SIZE_RANGE_M`.

    Raises:
        ShapeError: ``family`` is not one of :data:`FAMILIES`.
    """
    try:
        builder = _FAMILIES[family]
    except KeyError:
        raise ShapeError(
            f"unknown shape family {family!r}; expected one of {', '.join(FAMILIES)}"
        ) from None
    solid = builder(rng)
    low, high = np.asarray(solid.bounding_box()[:3]), np.asarray(solid.bounding_box()[3:])
    size = _log_uniform(rng, *SIZE_RANGE_M)
    mesh = solids.to_trimesh(solid.scale((size / float(np.max(high - low)),) * 3))
    if not (mesh.is_volume and mesh.body_count == 1):
        raise RuntimeError(f"shape family {family!r} produced an invalid solid")
    return place_on_table(mesh)
