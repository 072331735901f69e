"""Tests for models.procedural and models.shapes: category meshes and mesh-file loading."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from models.procedural import CATEGORIES, make_shape, object_mesh
from models.shapes import ShapeError, check_explorable, fits_extent, load_mesh_file

SEEDS = (0, 1, 2)


@pytest.fixture(scope="module")
def shapes() -> dict[tuple[str, int], trimesh.Trimesh]:
    """Every category for every seed, built once for the whole module."""
    return {(c, s): make_shape(c, np.random.default_rng(s)) for c in CATEGORIES for s in SEEDS}


def _z_up_to_y_up(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """A copy rotated so that the table frame's +z points along +y, as in ShapeNet files."""
    rotated = mesh.copy()
    rotated.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    return rotated


def test_categories_are_the_papers_fourteen_in_order() -> None:
    assert CATEGORIES == (
        "bag", "bottle", "bowl", "camera", "can", "cap", "keyboard",
        "earphone", "helmet", "jar", "knife", "laptop", "mug", "remote",
    )  # fmt: skip


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("category", CATEGORIES)
def test_shape_is_a_watertight_solid_standing_on_the_table(
    shapes: dict[tuple[str, int], trimesh.Trimesh], category: str, seed: int
) -> None:
    mesh = shapes[category, seed]
    assert mesh.is_watertight
    assert mesh.is_volume  # also: consistent winding, outward normals
    assert mesh.volume > 0
    assert mesh.body_count == 1
    assert len(mesh.faces) <= 20_000
    lo, hi = mesh.bounds
    assert abs(lo[2]) < 1e-6
    np.testing.assert_allclose((lo[:2] + hi[:2]) / 2, 0.0, atol=1e-9)
    assert fits_extent(mesh, max_height_m=0.25, max_width_m=0.20)
    # Real objects, not slivers: every shape is at least 1 cm along its two largest axes.
    assert np.sort(mesh.extents)[1] > 0.01


@pytest.mark.parametrize("category", CATEGORIES)
def test_seeds_give_different_shapes(
    shapes: dict[tuple[str, int], trimesh.Trimesh], category: str
) -> None:
    extents = [shapes[category, s].extents for s in SEEDS]
    for i in range(len(SEEDS)):
        for j in range(i + 1, len(SEEDS)):
            assert not np.allclose(extents[i], extents[j], atol=1e-4)


@pytest.mark.parametrize("category", CATEGORIES)
def test_same_seed_gives_identical_mesh(category: str) -> None:
    # Only the passed generator may be used: numpy's legacy global state must not move.
    state = np.random.get_state()  # noqa: NPY002
    a = make_shape(category, np.random.default_rng(7))
    b = make_shape(category, np.random.default_rng(7))
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    after = np.random.get_state()  # noqa: NPY002
    assert all(np.array_equal(x, y) for x, y in zip(state, after, strict=True))


@pytest.mark.parametrize("seed", SEEDS)
def test_mug_is_hollow_with_a_floor(
    shapes: dict[tuple[str, int], trimesh.Trimesh], seed: int
) -> None:
    mug = shapes["mug", seed]
    assert mug.volume < 0.5 * mug.convex_hull.volume
    # The handle sticks out along +x only, so the y extent is the cup's diameter and the cup's
    # axis sits one radius in from the -x side.
    radius = mug.extents[1] / 2
    axis_x = mug.bounds[0, 0] + radius
    height = mug.extents[2]
    inside_cup, in_floor = mug.contains([[axis_x, 0, 0.6 * height], [axis_x, 0, 0.003]])
    assert not inside_cup
    assert in_floor
    # A ray dropped down the axis meets the floor first, not some lid.
    hits, _, _ = mug.ray.intersects_location([[axis_x, 0, height + 0.05]], [[0, 0, -1]])
    assert hits[:, 2].max() < 0.02


@pytest.mark.parametrize("seed", SEEDS)
def test_bowl_is_hollow_with_a_floor(
    shapes: dict[tuple[str, int], trimesh.Trimesh], seed: int
) -> None:
    bowl = shapes["bowl", seed]
    assert bowl.volume < 0.4 * bowl.convex_hull.volume
    inside_bowl, in_floor = bowl.contains([[0, 0, 0.7 * bowl.extents[2]], [0, 0, 0.002]])
    assert not inside_bowl
    assert in_floor


@pytest.mark.parametrize("suffix", [".stl", ".obj", ".ply", ".glb"])
def test_load_mesh_file_round_trip_with_y_up(tmp_path: Path, suffix: str) -> None:
    shape = make_shape("mug", np.random.default_rng(3))
    stored = _z_up_to_y_up(shape)
    stored.apply_translation([0.3, -0.2, 0.5])  # files need not be centred
    path = tmp_path / f"mug{suffix}"
    stored.export(path)

    loaded = load_mesh_file(path, up_axis="y")

    # Files store float32 coordinates: compare to float32 precision at 0.1 m.
    np.testing.assert_allclose(loaded.extents, shape.extents, atol=1e-6)
    np.testing.assert_allclose(loaded.bounds, shape.bounds, atol=1e-6)
    assert loaded.is_watertight
    assert loaded.volume == pytest.approx(shape.volume, rel=1e-4)


def test_load_mesh_file_applies_scale_and_fit(tmp_path: Path) -> None:
    shape = make_shape("bottle", np.random.default_rng(0))
    path = tmp_path / "bottle_mm.stl"
    shape.copy().apply_scale(1000.0).export(path)  # millimetres, z up

    in_metres = load_mesh_file(path, scale=0.001)
    np.testing.assert_allclose(in_metres.extents, shape.extents, rtol=1e-5)

    fitted = load_mesh_file(path, fit_max_extent_m=0.1)
    assert fitted.extents.max() == pytest.approx(0.1)
    np.testing.assert_allclose(fitted.extents / 0.1, shape.extents / shape.extents.max(), 1e-5)

    with pytest.raises(ValueError, match="not both"):
        load_mesh_file(path, scale=0.001, fit_max_extent_m=0.1)
    with pytest.raises(ValueError, match="up_axis"):
        load_mesh_file(path, up_axis="w")


def test_load_mesh_file_flattens_a_scene_with_its_transforms(tmp_path: Path) -> None:
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box((0.02, 0.02, 0.02)))
    moved = trimesh.transformations.translation_matrix([0.1, 0.0, 0.05])
    scene.add_geometry(trimesh.creation.box((0.02, 0.02, 0.02)), transform=moved)
    path = tmp_path / "two_boxes.glb"
    scene.export(path)

    mesh = load_mesh_file(path)

    np.testing.assert_allclose(mesh.extents, [0.12, 0.02, 0.07], atol=1e-6)
    assert len(mesh.faces) == 24


def test_load_mesh_file_accepts_an_open_mesh(tmp_path: Path) -> None:
    box = trimesh.creation.box((0.05, 0.05, 0.05))
    open_box = trimesh.Trimesh(box.vertices, box.faces[1:])  # one triangle missing
    path = tmp_path / "open_box.ply"
    open_box.export(path)

    mesh = load_mesh_file(path)

    assert mesh.is_watertight  # the single-triangle hole is filled
    np.testing.assert_allclose(mesh.extents, 0.05)


def test_corrupt_or_empty_files_raise_shape_error_naming_the_file(tmp_path: Path) -> None:
    noise = tmp_path / "noise.stl"
    noise.write_bytes(np.random.default_rng(0).bytes(1000))
    empty = tmp_path / "empty.obj"
    empty.write_text("")
    for path in (noise, empty, tmp_path / "missing.ply"):
        with pytest.raises(ShapeError, match=path.name):
            load_mesh_file(path)
    with pytest.raises(ShapeError, match="unsupported"):
        load_mesh_file(tmp_path / "notes.txt")


def test_unknown_category_raises_shape_error_naming_it() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(ShapeError, match="teapot"):
        make_shape("teapot", rng)
    with pytest.raises(ShapeError, match="teapot"):
        object_mesh("teapot", rng)


def test_object_mesh_takes_a_category_or_a_file(tmp_path: Path) -> None:
    from_name = object_mesh("can", np.random.default_rng(5))
    np.testing.assert_array_equal(
        from_name.vertices, make_shape("can", np.random.default_rng(5)).vertices
    )
    path = tmp_path / "can.obj"
    _z_up_to_y_up(from_name).export(path)
    for spec in (path, str(path)):
        from_file = object_mesh(spec, np.random.default_rng(0), up_axis="y")
        np.testing.assert_allclose(from_file.extents, from_name.extents, atol=1e-6)


def test_fits_extent_limits() -> None:
    assert fits_extent(trimesh.creation.box((0.2, 0.2, 0.25)))
    assert not fits_extent(trimesh.creation.box((0.21, 0.1, 0.1)))
    assert not fits_extent(trimesh.creation.box((0.1, 0.21, 0.1)))
    assert not fits_extent(trimesh.creation.box((0.1, 0.1, 0.26)))
    assert fits_extent(trimesh.creation.box((0.1, 0.1, 0.26)), max_height_m=0.3)


def _open_box(size_m: float) -> trimesh.Trimesh:
    """A box without its top (two triangles missing): a hole trimesh can fill."""
    box = trimesh.creation.box((size_m,) * 3)
    return trimesh.Trimesh(box.vertices, box.faces[box.face_normals[:, 2] < 0.9])


def _open_cylinder() -> trimesh.Trimesh:
    """A cup without a lid: a 32-sided hole, which trimesh cannot fill."""
    cylinder = trimesh.creation.cylinder(radius=0.03, height=0.08, sections=32)
    return trimesh.Trimesh(cylinder.vertices, cylinder.faces[cylinder.face_normals[:, 2] < 0.9])


def test_a_file_whose_header_lies_is_refused_in_words(tmp_path: Path) -> None:
    """A PLY header promising vertex properties y and z only: the reason, not KeyError('x')."""
    path = tmp_path / "liar.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float y\nproperty float z\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0\n1 0\n0 1\n3 0 1 2\n"
    )
    with pytest.raises(ShapeError) as refused:
        load_mesh_file(path)
    message = str(refused.value)
    assert message == (
        f"cannot read mesh file {path}: the header does not match the data (no field 'x')"
    )
    truncated = tmp_path / "truncated.ply"
    truncated.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 300\nproperty float x\n"
        b"property float y\nproperty float z\nelement face 1\n"
        b"property list uchar int vertex_indices\nend_header\n\x00\x00"
    )
    with pytest.raises(ShapeError, match=r"^cannot read mesh file .*truncated\.ply: \w+Error: "):
        load_mesh_file(truncated)


@pytest.mark.parametrize(
    ("mesh", "reason"),
    [
        (
            trimesh.creation.box((3.0, 3.0, 3.0)),
            "is too large for the workspace: 3.000 x 3.000 x 3.000 m, at most 0.260 m on each"
            " side fits",
        ),
        (
            trimesh.creation.box((1e-5, 1e-5, 1e-5)),
            "is too small to touch: 0.01 x 0.01 x 0.01 mm, its largest side must be at least 19 mm",
        ),
        (
            trimesh.Trimesh([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0]], [[0, 1, 2]]),
            "is not a closed solid (3 open edges) and its holes could not be filled",
        ),
        (_open_cylinder(), "is not a closed solid (32 open edges)"),
    ],
    ids=["3 m box", "10 um box", "one triangle", "open cylinder"],
)
def test_objects_the_bench_cannot_explore_are_refused_in_one_line(
    tmp_path: Path, mesh: trimesh.Trimesh, reason: str
) -> None:
    path = tmp_path / "object.stl"
    mesh.export(path)
    loaded = load_mesh_file(path)
    with pytest.raises(ShapeError) as refused:
        check_explorable(loaded, str(path), min_extent_m=0.019, max_extent_m=0.26)
    message = str(refused.value)
    assert message.startswith(f"object {path} {reason}") and "\n" not in message


def test_an_object_with_a_hole_that_can_be_filled_is_taken_with_a_warning(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "open_box.stl"
    _open_box(0.06).export(path)
    mesh = load_mesh_file(path)
    with caplog.at_level("WARNING", logger="models.shapes"):
        check_explorable(mesh, str(path), min_extent_m=0.019, max_extent_m=0.26)
    assert mesh.is_volume
    assert [r.getMessage() for r in caplog.records] == [
        f"object {path} was not a closed solid: its holes were filled"
    ]
    closed = tmp_path / "box.stl"
    trimesh.creation.box((0.06, 0.06, 0.06)).export(closed)
    caplog.clear()
    with caplog.at_level("WARNING", logger="models.shapes"):
        check_explorable(load_mesh_file(closed), str(closed), min_extent_m=0.019)
    assert caplog.records == []


def test_every_library_object_is_explorable(shapes: dict[tuple[str, int], trimesh.Trimesh]) -> None:
    """The limits the bench uses (the 19 mm gel pad, the 0.26 m voxel grid) take them all."""
    for (category, _), mesh in shapes.items():
        check_explorable(mesh, category, min_extent_m=0.019, max_extent_m=0.26)
