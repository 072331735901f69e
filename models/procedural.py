"""Procedural shapes: random watertight meshes of the paper's 14 categories and the box family.

Each category is built from the parts of :mod:`models.solids` with proportions drawn only from the
``numpy.random.Generator`` passed in, so a seed reproduces a shape exactly. Meshes are in the
table frame of :mod:`models.shapes`. :func:`object_mesh` resolves an object given as a category
name or a mesh file.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh
from manifold3d import CrossSection, JoinType, Manifold

from models import solids
from models.shapes import MESH_SUFFIXES, ShapeError, load_mesh_file, place_on_table

__all__ = [
    "ALL_CATEGORIES",
    "BOX_CATEGORY",
    "CATEGORIES",
    "make_box_shape",
    "make_shape",
    "object_mesh",
    "procedural_shape",
]


# Each builder returns a Manifold in metres with z up; placement happens in make_shape.
# Ranges are scaled-down real sizes where the real object would not fit the 25 x 20 x 20 cm
# work volume (keyboard, laptop, headphones, helmet, cap).


def _bag(rng: np.random.Generator) -> Manifold:
    width = rng.uniform(0.14, 0.19)
    depth = rng.uniform(0.06, 0.09)
    height = rng.uniform(0.10, 0.15)
    top_scale = (rng.uniform(0.75, 0.95), rng.uniform(0.6, 0.85))  # handbags narrow upwards
    body = solids.rounded_rect(width, depth, rng.uniform(0.012, 0.025)).extrude(
        height, scale_top=top_scale
    )
    # Handle: a tube arc rising from the top; its ends are buried in the body.
    span = width * top_scale[0] * rng.uniform(0.25, 0.35)  # half the distance between the feet
    rise = rng.uniform(0.05, 0.08)
    handle = (
        solids.ring_arc(span, rng.uniform(0.004, 0.007), 200)
        .rotate((0, -90, 0))  # arc symmetric about +z instead of +x
        .scale((1, 1, rise / span))
        .translate((0, 0, height - 0.01))
    )
    flap_depth = height * rng.uniform(0.3, 0.45)
    # Front flap: a thin slab on the (sloping) front face, tilted like the face.
    slope = np.degrees(np.arctan2(depth * (1 - top_scale[1]) / 2, height))
    flap = (
        solids.slab(width * top_scale[0] * 0.9, 0.006, flap_depth, 0.002)
        .translate((0, 0, -flap_depth))
        .rotate((-slope, 0, 0))
        .translate((0, -depth * top_scale[1] / 2, height - 0.002))  # below the top face
    )
    return solids.union([body, handle, flap])


def _bottle(rng: np.random.Generator) -> Manifold:
    radius = rng.uniform(0.028, 0.038)
    body_h = rng.uniform(0.10, 0.14)
    shoulder_h = rng.uniform(0.03, 0.05)
    neck_r = rng.uniform(0.010, 0.013)
    neck_h = rng.uniform(0.025, 0.04)
    cap_r = neck_r + rng.uniform(0.0015, 0.003)
    cap_h = neck_h * rng.uniform(0.5, 0.8)  # the cap covers the top of the neck only
    waist = rng.uniform(0.0, 0.1)  # some bottles are pinched in the middle
    bevel = 0.004
    z_body = np.linspace(bevel, body_h, 12)
    r_body = radius * (1 - waist * np.sin(np.pi * (z_body - bevel) / (body_h - bevel)))
    s = np.linspace(0, 1, 12)[1:]
    r_shoulder = neck_r + (radius - neck_r) * (1 + np.cos(np.pi * s)) / 2
    z_shoulder = body_h + shoulder_h * s
    top = body_h + shoulder_h + neck_h
    profile = [(0.0, 0.0), (radius - bevel, 0.0)]
    profile += list(zip(r_body, z_body, strict=True))
    profile += list(zip(r_shoulder, z_shoulder, strict=True))
    profile += [(neck_r, top - cap_h), (cap_r, top - cap_h), (cap_r, top), (0.0, top)]
    return solids.revolve(profile)


def _bowl(rng: np.random.Generator) -> Manifold:
    rim_r = rng.uniform(0.06, 0.09)
    height = rng.uniform(0.045, 0.08)
    wall = rng.uniform(0.003, 0.005)
    foot_r = rim_r * rng.uniform(0.4, 0.6)
    floor = wall * 1.5
    # Walls are quarter ellipses centred on the rim plane's axis point (0, height); the vertical
    # semi-axis is chosen so the outer ellipse meets z = 0 exactly at the foot radius.
    semi_z = height / np.sqrt(1 - (foot_r / rim_r) ** 2)
    z_out = np.linspace(0, height, 24)
    r_out = rim_r * np.sqrt(1 - ((height - z_out) / semi_z) ** 2)
    z_in = np.linspace(height, floor, 24)
    r_in = (rim_r - wall) * np.sqrt(1 - ((height - z_in) / (semi_z - wall)) ** 2)
    profile = [(0.0, 0.0)]
    profile += list(zip(r_out, z_out, strict=True))
    profile += list(zip(r_in, z_in, strict=True))
    profile += [(0.0, floor)]
    return solids.revolve(profile)


def _camera(rng: np.random.Generator) -> Manifold:
    width = rng.uniform(0.10, 0.14)
    depth = rng.uniform(0.035, 0.05)
    height = rng.uniform(0.06, 0.085)
    body = solids.slab(width, depth, height, rng.uniform(0.005, 0.012))
    # Grip on the right of the front face, a shutter button on top of it.
    grip_w = width * rng.uniform(0.15, 0.22)
    grip_x = width / 2 - grip_w / 2 - 0.003
    grip = solids.slab(grip_w, 0.02, height * 0.85, 0.006).translate((grip_x, -depth / 2, 0.004))
    shutter = solids.cylinder(rng.uniform(0.004, 0.006), 0.006, height - 0.001).translate(
        (grip_x, -depth * 0.2, 0)
    )
    # Lens: barrel along -y out of the front face with a wider front ring; its radius is
    # limited by the body height and by the room left of the grip.
    lens_x = width * rng.uniform(-0.1, 0.05)
    lens_z = height * rng.uniform(0.42, 0.5)
    room = min(grip_x - grip_w / 2 - lens_x, lens_x + width / 2) / 1.08 - 0.003
    lens_r = min(min(lens_z, height - lens_z) * rng.uniform(0.6, 0.85), room)
    lens_len = rng.uniform(0.02, 0.05)
    ring_len = rng.uniform(0.005, 0.01)
    barrel = solids.cylinder(lens_r, lens_len + 0.005, segments=solids.SEG_BIG)
    ring = solids.cylinder(
        lens_r * 1.08, ring_len, lens_len - ring_len + 0.005, segments=solids.SEG_BIG
    )
    glass = solids.cylinder(lens_r * 0.75, 0.004, lens_len + 0.002, segments=solids.SEG_BIG)
    lens = (
        ((barrel + ring) - glass)  # recessed front element
        .rotate((90, 0, 0))  # +z axis -> -y
        .translate((lens_x, -depth / 2 + 0.005, lens_z))
    )
    # Viewfinder hump above the lens: a frustum-like hull of two thin slabs.
    hump_w = width * rng.uniform(0.25, 0.35)
    hump_h = rng.uniform(0.008, 0.016)
    hump = Manifold.batch_hull(
        [
            solids.slab(hump_w, depth * 0.8, 0.002, 0.003, height - 0.002),
            solids.slab(hump_w * 0.55, depth * 0.5, 0.002, 0.002, height + hump_h - 0.002),
        ]
    ).translate((lens_x, 0, 0))
    dial = solids.cylinder(rng.uniform(0.008, 0.011), 0.005, height - 0.001).translate(
        (-width / 2 + 0.018, 0, 0)
    )
    return solids.union([body, grip, shutter, lens, hump, dial])


def _can(rng: np.random.Generator) -> Manifold:
    radius = rng.uniform(0.026, 0.034)
    height = rng.uniform(0.09, 0.13)
    lid_r = radius * 0.85
    profile = [
        (0.0, 0.0),
        (radius * 0.82, 0.0),
        (radius, 0.012),  # conical base of a drinks can
        (radius, height - 0.012),
        (radius * 0.9, height - 0.002),  # necked-in top
        (radius * 0.9, height),
        (lid_r, height),
        (lid_r, height - 0.004),  # the lid sits below the rim
        (0.0, height - 0.004),
    ]
    return solids.revolve(profile)


def _cap(rng: np.random.Generator) -> Manifold:
    # Scaled-down baseball cap: crown radius + brim length must fit 20 cm.
    crown_a = rng.uniform(0.058, 0.07)
    crown_b = crown_a * rng.uniform(0.88, 0.96)
    crown_h = crown_a * rng.uniform(1.0, 1.2)  # crowns are a little taller than wide
    wall = rng.uniform(0.003, 0.005)
    brim_len = rng.uniform(0.04, 0.055)
    crown = solids.dome_shell(crown_a, crown_b, crown_h, wall)
    brim = solids.half_ellipse_brim(
        crown_a + brim_len, crown_b * 0.97, crown_a - wall, crown_b - wall, 0.004
    ).translate((0, 0, 0.001))  # not flush with the crown's rim: coplanar faces leave slivers
    button = Manifold.sphere(0.006, solids.SEG_SMALL).translate((0, 0, crown_h - 0.002))
    return solids.union([crown, brim, button])


def _keyboard(rng: np.random.Generator) -> Manifold:
    # Compact keyboard lying flat, scaled so its length fits 20 cm.
    length = rng.uniform(0.17, 0.195)
    depth = rng.uniform(0.06, 0.08)
    thick = rng.uniform(0.010, 0.016)
    tilt = rng.uniform(0.2, 0.6)  # back edge is this fraction higher than the front edge

    def wedge(p: np.ndarray) -> np.ndarray:
        # Scaling z linearly in y keeps the top face planar, now sloping down to the front.
        return np.column_stack([p[:, 0], p[:, 1], p[:, 2] * (1 + tilt * (p[:, 1] / depth + 0.5))])

    slab = solids.slab(length, depth, thick, rng.uniform(0.003, 0.008)).warp_batch(wedge)
    n_cols = int(rng.integers(12, 15))
    n_rows = 5
    margin = 0.006
    pitch_x = (length - 2 * margin) / n_cols
    pitch_y = (depth - 2 * margin) / n_rows
    key_h = rng.uniform(0.003, 0.006)
    # The bottom row holds modifiers and a space bar; widths are in key units.
    rows = [[1.0] * n_cols] * (n_rows - 1) + [[1.5, 1.5, n_cols - 6.0, 1.5, 1.5]]
    keys = []
    for i, units in enumerate(rows):
        y = depth / 2 - margin - pitch_y * (i + 0.5)
        top = thick * (1 + tilt * (y / depth + 0.5))
        x = -length / 2 + margin
        for u in units:
            cap = CrossSection.square((pitch_x * u - 0.0025, pitch_y - 0.0025), center=True)
            key = cap.extrude(key_h + 0.0015, scale_top=(0.85, 0.8))
            keys.append(key.translate((x + pitch_x * u / 2, y, top - 0.0015)))
            x += pitch_x * u
    return solids.union([slab, *keys])


def _earphone(rng: np.random.Generator) -> Manifold:
    # Over-ear headphones standing on their ear cups: headband arc in the x-z plane.
    band_r = rng.uniform(0.065, 0.078)
    band_w = rng.uniform(0.018, 0.03)
    band_t = rng.uniform(0.005, 0.009)
    cup_r = rng.uniform(0.035, 0.045)
    cup_t = rng.uniform(0.025, 0.032)
    cup_stretch = rng.uniform(1.0, 1.25)  # oval cups, taller than wide
    cup_z = cup_r * cup_stretch
    # Rounded puck: a flat inner face at z = 0 and a rounded outer edge at z = cup_t.
    round_r = cup_t * 0.4
    a = np.linspace(0, np.pi / 2, 8)
    profile = [(0.0, 0.0), (cup_r, 0.0)]
    profile += list(
        zip(
            cup_r - round_r + round_r * np.cos(a),
            cup_t - round_r + round_r * np.sin(a),
            strict=True,
        )
    )
    profile += [(0.0, cup_t)]
    cup = solids.revolve(profile).scale((cup_stretch, 1, 1))
    pad = (
        CrossSection.circle(cup_t * 0.3, 12)
        .translate((cup_r * 0.72, 0))
        .revolve(solids.SEG_BIG)
        .scale((cup_stretch, 1, 1))
    )
    earcup = cup + pad
    # Local +z (outer face) -> world +x for the right cup; local x (the stretched axis) -> z.
    right = earcup.rotate((0, 90, 0)).translate((band_r - cup_t / 2, 0, cup_z))
    left = earcup.rotate((0, -90, 0)).translate((-band_r + cup_t / 2, 0, cup_z))
    section = solids.rounded_rect(band_t, band_w, band_t * 0.45).translate((band_r, 0))
    band = section.revolve(solids.SEG_BIG // 2, 180).rotate((90, 0, 0))  # upper half circle
    # The band's ends sit just above the cups' centres, buried inside the cups.
    band = band.translate((0, 0, cup_z + cup_r * 0.3))
    cushion_r = band_r - band_t / 2 - 0.004
    cushion = (
        solids.rounded_rect(0.01, band_w * 0.8, 0.004)
        .translate((cushion_r, 0))
        .revolve(solids.SEG_BIG // 4, 70)
        .rotate((0, 0, 55))
        .rotate((90, 0, 0))
        .translate((0, 0, cup_z + cup_r * 0.3))
    )
    return solids.union([left, right, band, cushion])


def _helmet(rng: np.random.Generator) -> Manifold:
    # Scaled-down bicycle helmet: a thick half-ellipsoid shell with vent slots, maybe a visor.
    a = rng.uniform(0.075, 0.085)
    b = a * rng.uniform(0.8, 0.9)
    c = a * rng.uniform(0.85, 1.05)
    wall = rng.uniform(0.012, 0.022)
    shell = solids.dome_shell(a, b, c, wall)
    # Front-to-back slots through the top, spread across the width.
    n_vents = int(rng.integers(3, 6))
    slot = solids.rounded_rect(a * rng.uniform(0.6, 0.9), 0.009, 0.004).extrude(c)
    spacing = 1.1 * b / (n_vents - 1)
    slots = [
        slot.translate((0, (k - (n_vents - 1) / 2) * spacing, c * 0.55)) for k in range(n_vents)
    ]
    shell = shell - solids.union(slots)
    if rng.random() < 0.5:
        visor_len = rng.uniform(0.015, 0.025)
        visor = solids.half_ellipse_brim(a + visor_len, b * 0.85, a - wall, b - wall, 0.005)
        shell = shell + visor.translate((0, 0, 0.002))  # kept off the rim plane, as for caps
    return shell


def _jar(rng: np.random.Generator) -> Manifold:
    radius = rng.uniform(0.035, 0.055)
    body_h = rng.uniform(0.06, 0.12)
    neck_r = radius * rng.uniform(0.78, 0.9)
    neck_h = rng.uniform(0.012, 0.02)
    lid_h = rng.uniform(0.014, 0.025)
    lid_r = neck_r + rng.uniform(0.002, 0.004)
    corner = 0.006
    a = np.linspace(0, np.pi / 2, 6)
    shoulder_s = np.linspace(0, 1, 8)[1:]
    shoulder_h = (radius - neck_r) * 1.2
    profile = [(0.0, 0.0)]
    profile += list(
        zip(radius - corner + corner * np.sin(a), corner - corner * np.cos(a), strict=True)
    )
    profile += [(radius, body_h - shoulder_h)]
    profile += list(
        zip(
            neck_r + (radius - neck_r) * np.cos(np.pi / 2 * shoulder_s),
            body_h - shoulder_h + shoulder_h * np.sin(np.pi / 2 * shoulder_s),
            strict=True,
        )
    )
    top = body_h + neck_h
    profile += [(neck_r, top), (0.0, top)]
    body = solids.revolve(profile)
    # Knurled screw lid: a ridged outline extruded over the top of the neck.
    n_ridges = int(rng.integers(40, 70))
    phi = np.linspace(0, 2 * np.pi, 4 * n_ridges, endpoint=False)
    r = lid_r + 0.0008 * np.cos(n_ridges * phi)
    outline = CrossSection([np.column_stack([r * np.cos(phi), r * np.sin(phi)])])
    lid = outline.extrude(lid_h).translate((0, 0, top - lid_h * 0.6))
    return body + lid


def _knife(rng: np.random.Generator) -> Manifold:
    # Lying flat along x: blade towards +x, handle towards -x.
    total = rng.uniform(0.17, 0.195)
    handle_len = total * rng.uniform(0.38, 0.45)
    blade_len = total - handle_len
    blade_w = rng.uniform(0.025, 0.045)
    blade_t = rng.uniform(0.0018, 0.003)
    handle_w = rng.uniform(0.018, 0.024)
    handle_t = rng.uniform(0.013, 0.019)
    tip_y = blade_w * rng.uniform(0.1, 0.35)  # the tip sits near the spine
    x = np.linspace(0, blade_len, 24)
    edge = -blade_w / 2 + (blade_w / 2 + tip_y) * (x / blade_len) ** 3
    drop = np.clip((x - 0.6 * blade_len) / (0.4 * blade_len), 0, None) ** 2
    spine = blade_w / 2 - (blade_w / 2 - tip_y) * drop
    outline = np.vstack([np.column_stack([x, edge]), np.column_stack([x[::-1], spine[::-1]])[1:]])
    blade = (
        CrossSection([outline])
        .extrude(blade_t)
        .translate((-0.003, 0, handle_t / 2 - blade_t / 2))  # tang sinks into the handle
    )
    handle = (
        solids.rounded_rect(handle_len, handle_w, handle_w * 0.45)
        .extrude(handle_t)
        .translate((-handle_len / 2, 0, 0))
    )
    bolster = solids.slab(0.008, blade_w * 0.9, handle_t * 0.9, 0.002, handle_t * 0.05)
    return solids.union([blade, handle, bolster.translate((0.002, 0, 0))])


def _laptop(rng: np.random.Generator) -> Manifold:
    # Scaled-down laptop with its lid opened past vertical.
    width = rng.uniform(0.16, 0.19)
    depth = rng.uniform(0.105, 0.125)
    base_t = rng.uniform(0.008, 0.012)
    lid_t = rng.uniform(0.004, 0.007)
    lid_d = depth * rng.uniform(0.93, 0.98)
    corner = rng.uniform(0.004, 0.008)
    opening = rng.uniform(95, 120)  # degrees between the base and the lid
    base = solids.slab(width, depth, base_t, corner)
    keys = solids.slab(width * 0.85, depth * 0.42, 0.002, 0.001, base_t - 0.001).translate(
        (0, depth * 0.18, 0)
    )
    pad = solids.slab(width * 0.3, depth * 0.25, 0.002, 0.002, base_t - 0.001).translate(
        (0, -depth * 0.27, 0)
    )
    base = base - keys - pad
    # The lid is modelled closed, screen face down, about its hinge axis (the x axis), then
    # opened. The axis runs through the lid's mid-thickness, so no lid face passes exactly
    # through an edge of the base (that would leave sliver triangles).
    lid = solids.slab(width, lid_d, lid_t, corner, -lid_t / 2).translate((0, -lid_d / 2, 0))
    screen = solids.slab(width * 0.9, lid_d * 0.86, 0.002, 0.001, -lid_t / 2 - 0.001)
    lid = (lid - screen.translate((0, -lid_d * 0.52, 0))).rotate((-opening, 0, 0))
    hinge_at = (0, depth / 2 - 0.004, base_t + lid_t / 2)
    hinge = Manifold.cylinder(
        width * 0.8, max(base_t, lid_t) * 0.6, -1, solids.SEG_SMALL, center=True
    ).rotate((0, 90, 0))
    return solids.union([base, lid.translate(hinge_at), hinge.translate(hinge_at)])


def _mug(rng: np.random.Generator) -> Manifold:
    radius = rng.uniform(0.036, 0.046)
    height = rng.uniform(0.08, 0.11)
    wall = rng.uniform(0.004, 0.006)
    floor = rng.uniform(0.006, 0.010)
    foot_r = radius * (1 - rng.uniform(0.0, 0.08))  # slightly conical mugs
    bevel = 0.003

    def outer_r(z: float) -> float:
        return foot_r + (radius - foot_r) * z / height

    body = solids.revolve(
        [
            (0.0, 0.0),
            (foot_r - bevel, 0.0),
            (outer_r(bevel), bevel),
            (radius, height),
            (0.0, height),
        ]
    )
    cavity = solids.revolve(
        [
            (0.0, floor),
            (outer_r(floor) - wall, floor),
            (radius - wall, height),
            (radius - wall, height + 0.01),
            (0.0, height + 0.01),
        ]
    )
    # D-shaped handle: a 200-degree tube arc whose ends are buried in the wall; anything that
    # pokes into the cup is cut away with the cavity below.
    z_low = height * rng.uniform(0.12, 0.2)
    z_high = height * rng.uniform(0.8, 0.88)
    half_span = (z_high - z_low) / 2
    # Scaling the arc to this reach also thickens the tube along x, by at most ~1.6x here.
    reach = rng.uniform(0.028, 0.038)
    handle = (
        solids.ring_arc(half_span, rng.uniform(0.005, 0.007), 200)
        .scale((reach / half_span, 1, 1))
        .translate((radius - wall, 0, (z_low + z_high) / 2))
    )
    return (body + handle) - cavity


def _remote(rng: np.random.Generator) -> Manifold:
    length = rng.uniform(0.14, 0.19)
    width = rng.uniform(0.04, 0.055)
    thick = rng.uniform(0.015, 0.022)
    narrow = rng.uniform(0.8, 1.0)  # the end held in the hand is often narrower
    r = thick * 0.3  # edge rounding; leaves a flat top for the buttons
    ball = Manifold.sphere(r, solids.SEG_SMALL)
    body = Manifold.batch_hull(
        [
            ball.translate((sx * (length / 2 - r), sy * (w / 2 - r), z))
            for sx, w in ((1, width), (-1, width * narrow))
            for sy in (1, -1)
            for z in (r, thick - r)
        ]
    )

    def button(radius: float, x: float, y: float, height: float = 0.0025) -> Manifold:
        """A round button on the flat top (z = thick), sunk 1 mm into the body."""
        return solids.cylinder(radius, height + 0.001, thick - 0.001, segments=16).translate(
            (x, y, 0)
        )

    # Power at the +x end, then a d-pad with a centre button, then a 3-column number grid.
    power_x = length / 2 - 0.015
    pad_x = power_x - 0.022
    parts = [
        body,
        button(0.005, power_x, width * 0.2),
        button(0.012, pad_x, 0, height=0.0015),
        button(0.005, pad_x, 0, height=0.003),
    ]
    pitch = rng.uniform(0.011, 0.014)
    for i in range(int(rng.integers(3, 5))):
        for j in (-1, 0, 1):
            parts.append(button(0.0035, pad_x - 0.022 - i * pitch, j * width * narrow * 0.2))
    return solids.union(parts)


_BUILDERS: dict[str, Callable[[np.random.Generator], Manifold]] = {
    "bag": _bag,
    "bottle": _bottle,
    "bowl": _bowl,
    "camera": _camera,
    "can": _can,
    "cap": _cap,
    "keyboard": _keyboard,
    "earphone": _earphone,
    "helmet": _helmet,
    "jar": _jar,
    "knife": _knife,
    "laptop": _laptop,
    "mug": _mug,
    "remote": _remote,
}

CATEGORIES: tuple[str, ...] = tuple(_BUILDERS)
"""The 14 object categories of the paper, in the paper's order."""


def make_shape(category: str, rng: np.random.Generator) -> trimesh.Trimesh:
    """A random watertight instance of ``category`` in metres, bottom centre at the origin.

    Proportions are drawn from ``rng`` only; the same generator state gives identical vertices.
    The result fits 25 cm tall and 20 cm wide in x and y (see :func:`models.shapes.fits_extent`).

    Raises:
        ShapeError: ``category`` is not one of :data:`CATEGORIES`.
    """
    try:
        builder = _BUILDERS[category]
    except KeyError:
        raise ShapeError(
            f"unknown shape category {category!r}; expected one of {', '.join(CATEGORIES)}"
        ) from None
    mesh = solids.to_trimesh(builder(rng))
    # Manifold's outputs are closed by construction; this guards against a builder whose parts
    # do not overlap (two bodies) or degenerate to nothing.
    if not (mesh.is_volume and mesh.body_count == 1):
        raise RuntimeError(f"shape builder for {category!r} produced an invalid solid")
    return place_on_table(mesh)


BOX_CATEGORY = "box"
"""The box family (cereal, sugar, tea boxes...), used by the ``box`` prior."""

ALL_CATEGORIES: tuple[str, ...] = (*CATEGORIES, BOX_CATEGORY)
"""Category index = position here (the 14 paper categories, then the box family)."""


def make_box_shape(rng: np.random.Generator) -> trimesh.Trimesh:
    """A random box-like product (cuboid, rounded or tapered, sometimes with a lid), watertight.

    Metres, bottom centre at the origin, z up; fits 22 cm tall and 20 cm wide like the library.
    """
    width = rng.uniform(0.04, 0.19)
    depth = rng.uniform(0.03, min(0.15, width))
    height = rng.uniform(0.04, 0.22)
    radius = rng.uniform(0.0005, 0.2 * min(width, depth)) if rng.random() < 0.5 else 0.0005
    section = CrossSection.square((width - 2 * radius, depth - 2 * radius), center=True).offset(
        radius, JoinType.Round, circular_segments=16
    )
    taper = rng.uniform(0.75, 0.95) if rng.random() < 0.2 else 1.0
    body = section.extrude(height, scale_top=(taper, taper))
    if rng.random() < 0.25:  # a lid slightly wider than the box
        lid_height = rng.uniform(0.01, 0.3 * height)
        lip = rng.uniform(0.002, 0.006)
        lid = CrossSection.square((width * taper + 2 * lip, depth * taper + 2 * lip), center=True)
        body = body + lid.extrude(lid_height).translate((0, 0, height - lid_height))
    return place_on_table(solids.to_trimesh(body))


def procedural_shape(category: str, rng: np.random.Generator) -> trimesh.Trimesh:
    """A random shape of one of :data:`ALL_CATEGORIES` (table frame, metres)."""
    if category == BOX_CATEGORY:
        return make_box_shape(rng)
    return make_shape(category, rng)


def object_mesh(spec: str | Path, rng: np.random.Generator, **load_kwargs) -> trimesh.Trimesh:
    """The object mesh for ``spec``: a category name or a mesh file path.

    A name in :data:`CATEGORIES` gives a random instance drawn from ``rng`` (``load_kwargs`` do
    not apply to it and are ignored). Anything with a mesh suffix, or that exists on disk, is
    loaded with :func:`load_mesh_file` and ``load_kwargs`` (``up_axis``, ``scale``,
    ``fit_max_extent_m``).

    Raises:
        ShapeError: ``spec`` is neither a category nor a loadable mesh file.
    """
    if isinstance(spec, str) and spec in _BUILDERS:
        return make_shape(spec, rng)
    path = Path(spec)
    if path.suffix.lower() in MESH_SUFFIXES or path.exists():
        return load_mesh_file(path, **load_kwargs)
    raise ShapeError(
        f"unknown object {str(spec)!r}: not a category ({', '.join(CATEGORIES)}) "
        f"and not a mesh file ({', '.join(MESH_SUFFIXES)})"
    )
