"""Object meshes in the table frame: mesh-file loading, placement, size check, voxelisation.

Every mesh of the project's objects is in metres in the *table frame*: z is up, the object stands
on the table plane z = 0 (its lowest point is at z = 0) and the centre of its axis-aligned
bounding box in x, y is at (0, 0) ("bottom centre at the origin"). Procedural shapes are in
:mod:`models.procedural`.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import trimesh

from models.geometry import VoxelGrid

__all__ = [
    "MESH_SUFFIXES",
    "ShapeError",
    "check_explorable",
    "fits_extent",
    "load_mesh_file",
    "place_on_table",
    "voxelize",
]

log = logging.getLogger(__name__)

MESH_SUFFIXES: tuple[str, ...] = (".obj", ".stl", ".ply", ".glb", ".gltf", ".off")
"""File suffixes :func:`load_mesh_file` accepts (case-insensitive)."""


class ShapeError(ValueError):
    """An unknown category name, or a mesh file that is missing, unreadable, corrupt or empty."""


def place_on_table(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Translate in place so the lowest point is at z = 0 and the x-y bbox centre is at 0."""
    lo, hi = mesh.bounds
    # Assigned directly: apply_translation skips offsets below 1e-8 m as "identity", which
    # would leave the lowest point a few nanometres off the table.
    mesh.vertices = mesh.vertices - [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]]
    return mesh


# Rotations taking the named file axis onto +z (proper rotations, exact integer entries).
_UP_ROTATIONS: dict[str, np.ndarray] = {
    "z": np.eye(3),
    "-z": np.diag([1.0, -1.0, -1.0]),
    "y": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),
    "-y": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
    "x": np.array([[0.0, 0, -1], [0, 1, 0], [1, 0, 0]]),
    "-x": np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]),
}


def load_mesh_file(
    path: str | Path,
    *,
    up_axis: str = "z",
    scale: float = 1.0,
    fit_max_extent_m: float | None = None,
) -> trimesh.Trimesh:
    """Load a triangle mesh file (OBJ, STL, PLY, GLB, GLTF, OFF) into the table frame.

    A multi-part file (a scene) is flattened into one mesh with its node transforms applied.
    The file's ``up_axis`` ("x", "y", "z", "-x", "-y" or "-z"; ShapeNet uses "y") is rotated
    onto +z. The mesh is then multiplied by ``scale`` (file units -> metres), or, if
    ``fit_max_extent_m`` is given, scaled uniformly so its largest extent is that many metres
    (``scale`` must then be left at 1). Finally it is placed bottom centre at the origin.

    Meshes that are not watertight are accepted: holes are filled and winding made consistent
    where trimesh can (``mesh.metadata["repaired"]`` then says what was done), otherwise the
    mesh is returned as it is (:func:`check_explorable` refuses it for the bench).

    Raises:
        ShapeError: the file is missing, has an unsupported suffix, cannot be parsed (the
            message says why, e.g. a header that does not match the data), or contains no
            triangles.
        ValueError: bad ``up_axis``, ``scale`` or ``fit_max_extent_m``.
    """
    path = Path(path)
    rotation = _UP_ROTATIONS.get(up_axis.strip().lower())
    if rotation is None:
        raise ValueError(f"up_axis must be one of {', '.join(_UP_ROTATIONS)}, got {up_axis!r}")
    if not (np.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a positive number, got {scale!r}")
    if fit_max_extent_m is not None:
        if not (np.isfinite(fit_max_extent_m) and fit_max_extent_m > 0):
            raise ValueError(f"fit_max_extent_m must be positive, got {fit_max_extent_m!r}")
        if scale != 1.0:
            raise ValueError("give either scale or fit_max_extent_m, not both")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise ShapeError(
            f"unsupported mesh file type {path.suffix!r} for {path}; "
            f"expected one of {', '.join(MESH_SUFFIXES)}"
        )
    if not path.is_file():
        raise ShapeError(f"mesh file not found: {path}")
    try:
        # to_mesh bakes node transforms in and keeps only triangle geometry (a scene may also
        # hold point clouds or paths).
        mesh = trimesh.load_scene(path).to_mesh()
    except Exception as exc:  # trimesh's parsers raise many unrelated types on corrupt input
        raise ShapeError(f"cannot read mesh file {path}: {_read_failure(exc)}") from exc
    if len(mesh.faces) == 0:
        raise ShapeError(f"mesh file {path} contains no triangles (empty, truncated or corrupt)")
    if not np.isfinite(mesh.vertices).all():
        raise ShapeError(f"mesh file {path} has non-finite vertex coordinates")

    # Files with texture coordinates or per-corner normals (e.g. ShapeNet OBJs) are loaded with
    # vertices split along UV / normal seams, which would look like holes.
    mesh.merge_vertices(merge_tex=True, merge_norm=True)
    if not mesh.is_volume:
        was_watertight = mesh.is_watertight
        trimesh.repair.fill_holes(mesh)
        trimesh.repair.fix_normals(mesh)
        mesh.metadata["repaired"] = (
            "its faces were turned consistently" if was_watertight else "its holes were filled"
        )

    transform = np.eye(4)
    transform[:3, :3] = rotation
    mesh.apply_transform(transform)
    if fit_max_extent_m is not None:
        largest = float(mesh.extents.max())
        if largest <= 0:
            raise ShapeError(f"mesh file {path} has zero size; cannot fit it to an extent")
        scale = fit_max_extent_m / largest
    mesh.apply_scale(scale)
    return place_on_table(mesh)


def _read_failure(error: Exception) -> str:
    """Why a parser failed, in words: a missing key means the header promised a field (e.g. a
    PLY vertex property 'x') that the data does not have."""
    if isinstance(error, KeyError):
        return f"the header does not match the data (no field {error.args[0]!r})"
    reason = " ".join(str(error).split()) or "no reason given"
    return f"{type(error).__name__}: {reason}"


def check_explorable(
    mesh: trimesh.Trimesh,
    source: str,
    *,
    min_extent_m: float,
    max_extent_m: float | None = None,
) -> None:
    """Refuse an object the bench cannot explore, with one line naming ``source`` (the file or
    category) and the reason: larger than ``max_extent_m`` on any side (the volume the shape
    is perceived in), with a largest side under ``min_extent_m`` (too small to touch), or not
    a closed solid (its inside is undefined: the gel, the voxels and the scores need one).
    A mesh whose holes :func:`load_mesh_file` filled is accepted with a warning."""
    extents = mesh.extents
    size_m = " x ".join(f"{e:.3f}" for e in extents)
    if max_extent_m is not None and extents.max() > max_extent_m:
        raise ShapeError(
            f"object {source} is too large for the workspace: {size_m} m, at most "
            f"{max_extent_m:.3f} m on each side fits"
        )
    if extents.max() < min_extent_m:
        size_mm = " x ".join(f"{e * 1e3:.3g}" for e in extents)
        raise ShapeError(
            f"object {source} is too small to touch: {size_mm} mm, its largest side must be "
            f"at least {min_extent_m * 1e3:.0f} mm"
        )
    if not mesh.is_volume:
        open_edges = len(trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1))
        raise ShapeError(
            f"object {source} is not a closed solid ({open_edges} open edges) and its holes "
            "could not be filled"
        )
    if mesh.metadata.get("repaired"):
        log.warning("object %s was not a closed solid: %s", source, mesh.metadata["repaired"])


def fits_extent(
    mesh: trimesh.Trimesh, max_height_m: float = 0.25, max_width_m: float = 0.20
) -> bool:
    """Whether the mesh's bounding box is at most ``max_height_m`` in z and ``max_width_m`` in
    each of x and y (metres)."""
    ex, ey, ez = mesh.extents
    return bool(ez <= max_height_m and ex <= max_width_m and ey <= max_width_m)


def voxelize(mesh_world: trimesh.Trimesh, grid: VoxelGrid) -> np.ndarray:
    """Occupancy (N, N, N) bool, indexed [i, j, k], of each voxel centre inside ``mesh_world``.

    Watertight meshes use trimesh's ray-based inside test. Other meshes (user files with holes)
    use a majority vote of ray parity along +x, +y and +z: one hole flips at most the rays
    through it, which the other two directions outvote.
    """
    n = grid.resolution
    centres = grid.voxel_centres_world().reshape(-1, 3)
    low, high = mesh_world.bounds
    pad = grid.voxel_size_m
    candidates = np.flatnonzero(np.all((centres >= low - pad) & (centres <= high + pad), axis=1))
    inside = np.zeros(n**3, dtype=bool)
    if len(candidates):
        points = centres[candidates]
        if mesh_world.is_watertight:
            inside[candidates] = mesh_world.contains(points)
        else:
            inside[candidates] = _parity_vote(mesh_world, points)
    return inside.reshape(n, n, n)


def _parity_vote(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    votes = np.zeros(len(points), dtype=int)
    for axis in range(3):
        direction = np.zeros(3)
        direction[axis] = 1.0
        directions = np.broadcast_to(direction, points.shape)
        _, ray_index, _ = mesh.ray.intersects_location(points, directions, multiple_hits=True)
        crossings = np.bincount(ray_index, minlength=len(points))
        votes += crossings % 2
    return votes >= 2
