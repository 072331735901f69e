"""Solid modelling on manifold3d: the building blocks of the procedural shapes.

Every operation returns a closed, consistently wound (outward-facing) 2-manifold, so solids built
from these parts are watertight by construction. manifold3d also provides 2-D cross-sections
without shapely, which trimesh's polygon extrusion would need and which is not a dependency of
this project. Lengths are metres, z is up.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import trimesh
from manifold3d import CrossSection, JoinType, Manifold, OpType

# Circle resolutions (segments per full turn). Chosen so the biggest category stays well below
# ~20k faces: ray casting for rendering and tactile simulation scales with face count.
SEG_BIG = 64
SEG_SMALL = 24


def union(parts: Sequence[Manifold]) -> Manifold:
    return Manifold.batch_boolean(list(parts), OpType.Add)


def revolve(profile: Sequence[tuple[float, float]], segments: int = SEG_BIG) -> Manifold:
    """Solid of revolution about z of a closed (radius, z) profile given counter-clockwise."""
    return CrossSection([np.asarray(profile, dtype=float)]).revolve(segments)


def rounded_rect(size_x: float, size_y: float, radius: float) -> CrossSection:
    """Rectangle centred on the origin with circular corners of ``radius``."""
    core = CrossSection.square((size_x - 2 * radius, size_y - 2 * radius), center=True)
    return core.offset(radius, JoinType.Round, circular_segments=SEG_SMALL)


def slab(size_x: float, size_y: float, height: float, radius: float, z0: float = 0.0) -> Manifold:
    """Box with rounded vertical edges, centred in x, y, spanning z0 .. z0 + height."""
    return rounded_rect(size_x, size_y, radius).extrude(height).translate((0, 0, z0))


def cylinder(radius: float, height: float, z0: float = 0.0, segments: int = SEG_SMALL) -> Manifold:
    """Cylinder about the z axis spanning z0 .. z0 + height."""
    return Manifold.cylinder(height, radius, radius, segments).translate((0, 0, z0))


def ellipsoid(a: float, b: float, c: float, segments: int = SEG_BIG) -> Manifold:
    return Manifold.sphere(1.0, segments).scale((a, b, c))


def ring_arc(major: float, minor: float, degrees: float) -> Manifold:
    """Arc of a torus tube in the x-z plane, centred on the origin, symmetric about +x.

    The tube (circular section of radius ``minor``) follows a circle of radius ``major`` from
    -degrees/2 to +degrees/2 measured from +x towards +z.
    """
    section = CrossSection.circle(minor, 16).translate((major, 0))
    arc_segments = max(8, round(SEG_BIG * degrees / 360))
    arc = section.revolve(arc_segments, degrees)  # in the x-y plane, from +x towards +y
    return arc.rotate((0, 0, -degrees / 2)).rotate((90, 0, 0))


def half_ellipse_brim(
    outer_a: float, outer_b: float, inner_a: float, inner_b: float, thickness: float
) -> Manifold:
    """Flat brim/visor on z = 0 .. thickness: the front (x >= 0) half of an ellipse minus an
    inner ellipse, so it joins the rim of a dome without closing the dome's opening."""
    t = np.linspace(-np.pi / 2, np.pi / 2, 33)
    half = CrossSection([np.column_stack([outer_a * np.cos(t), outer_b * np.sin(t)])])
    u = np.linspace(0, 2 * np.pi, SEG_BIG, endpoint=False)
    hole = CrossSection([np.column_stack([inner_a * np.cos(u), inner_b * np.sin(u)])])
    return (half - hole).extrude(thickness)


def dome_shell(a: float, b: float, c: float, wall: float) -> Manifold:
    """Upper half of an ellipsoidal shell (semi-axes a, b, c; open at z = 0)."""
    outer = ellipsoid(a, b, c)
    inner = ellipsoid(a - wall, b - wall, c - wall)
    return (outer - inner).trim_by_plane((0, 0, 1), 0.0)


def to_trimesh(solid: Manifold) -> trimesh.Trimesh:
    mesh_data = solid.to_mesh64()
    # Manifold already shares vertices between faces. trimesh's processing would merge vertices
    # by rounding, which can collapse the sub-micron sliver triangles booleans leave behind and
    # break the manifold, so the mesh is taken as it is.
    return trimesh.Trimesh(
        vertices=np.asarray(mesh_data.vert_properties)[:, :3],
        faces=np.asarray(mesh_data.tri_verts),
        process=False,
    )
