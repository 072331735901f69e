"""Dataset builder: voxel ground truth of known meshes, deterministic and resumable shards."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from models.geometry import VoxelGrid
from models.prior.dataset import (
    EVAL_SEED_START,
    BuildSpec,
    SketchVoxelDataset,
    ViewRecipe,
    build_dataset,
    plan_shards,
    split_by_shape,
)
from models.procedural import make_box_shape
from models.shapes import voxelize

TINY = ViewRecipe(image_size=64, voxel_resolution=16)


def test_voxelize_box_matches_voxel_centres() -> None:
    grid = VoxelGrid(16, 0.16)  # 1 cm voxels, paper axes
    box = trimesh.creation.box(extents=(0.055, 0.075, 0.047))
    box.apply_translation((0.0, 0.0, 0.0235))  # bottom centre on the object point
    occupancy = voxelize(box, grid)
    # Centres at +-0.5, 1.5, 2.5 cm are inside |x| < 2.75 cm: 6 x 8 voxels, 5 layers (z < 4.7 cm).
    assert occupancy.sum() == 6 * 8 * 5
    assert occupancy[:, :, :5].sum() == occupancy.sum()
    # a_x = (-1, 0, 0): voxel i grows toward -x; the box is centred, so i = 5..10.
    assert np.flatnonzero(occupancy.any(axis=(1, 2))).tolist() == list(range(5, 11))


def test_voxelize_sphere_volume() -> None:
    grid = VoxelGrid(32, 0.16)
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.06)
    sphere.apply_translation((0.0, 0.0, 0.07))
    volume = voxelize(sphere, grid).sum() * grid.voxel_size_m**3
    assert volume == pytest.approx(4 / 3 * np.pi * 0.06**3, rel=0.03)


def test_voxelize_open_mesh_by_parity_vote() -> None:
    grid = VoxelGrid(16, 0.16)
    box = trimesh.creation.box(extents=(0.055, 0.075, 0.047))
    box.apply_translation((0.0, 0.0, 0.0235))
    closed = voxelize(box, grid)
    open_box = box.copy()
    open_box.update_faces(box.face_normals[:, 0] > -0.5)  # drop the -x side: a hole
    assert not open_box.is_watertight
    assert np.array_equal(voxelize(open_box, grid), closed)


def test_box_family_is_watertight_and_fits(rng: np.random.Generator) -> None:
    for _ in range(10):
        mesh = make_box_shape(rng)
        assert mesh.is_watertight
        assert mesh.bounds[0, 2] == pytest.approx(0.0, abs=1e-9)
        assert mesh.extents[2] <= 0.25 and max(mesh.extents[:2]) <= 0.2


def _spec(out: Path, **kwargs) -> BuildSpec:
    base = dict(
        out_dir=str(out),
        categories=("mug", "box"),
        shapes_per_category=2,
        views=2,
        shapes_per_shard=1,
        recipe=TINY,
    )
    return BuildSpec(**{**base, **kwargs})


def test_shards_are_deterministic_and_resumable(tmp_path: Path) -> None:
    first = build_dataset(_spec(tmp_path / "a"), workers=1, progress=False)
    assert first["complete"] and len(first["shards"]) == 4
    build_dataset(_spec(tmp_path / "b"), workers=1, progress=False)
    for shard in first["shards"]:
        a = np.load(tmp_path / "a" / shard["file"])
        b = np.load(tmp_path / "b" / shard["file"])
        assert all(np.array_equal(a[key], b[key]) for key in a.files)
    # Resume: a missing shard is rebuilt, identical; finished ones are not touched.
    missing = tmp_path / "a" / first["shards"][2]["file"]
    kept = tmp_path / "a" / first["shards"][0]["file"]
    reference = np.load(tmp_path / "b" / missing.name)["voxels"]
    kept_mtime = kept.stat().st_mtime_ns
    missing.unlink()
    build_dataset(_spec(tmp_path / "a"), workers=1, progress=False)
    assert np.array_equal(np.load(missing)["voxels"], reference)
    assert kept.stat().st_mtime_ns == kept_mtime

    dataset = SketchVoxelDataset(tmp_path / "a")
    assert len(dataset) == 8
    item = dataset[0]
    assert item["rgb"].shape == (3, 64, 64) and item["rgb"].dtype == torch.uint8
    assert item["voxels"].shape == (16, 16, 16)
    assert item["normals"].shape == (3, 64, 64)
    # Depth and normals are zero off the silhouette, and the object is seen and voxelised.
    assert float((item["nearness"] * (1 - item["silhouette"])).abs().max()) == 0.0
    assert float(item["silhouette"].sum()) > 0 and float(item["voxels"].sum()) > 0
    train, val = split_by_shape(dataset, 0.25)
    names = dataset.shape_names()
    assert not set(names[train]) & set(names[val])


def test_other_recipe_in_same_folder_is_refused(tmp_path: Path) -> None:
    build_dataset(
        _spec(tmp_path, categories=("box",), shapes_per_category=1), workers=1, progress=False
    )
    with pytest.raises(ValueError, match="another recipe"):
        build_dataset(
            _spec(tmp_path, categories=("box",), shapes_per_category=1, views=3),
            workers=1,
            progress=False,
        )


def test_training_seeds_never_reach_the_held_out_range(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="held-out"):
        plan_shards(_spec(tmp_path, seed=EVAL_SEED_START - 1))


def test_shapenet_style_folder(tmp_path: Path) -> None:
    source = tmp_path / "ShapeNetCore"
    for synset, model in (("03797390", "m1"), ("02876657", "b1")):
        folder = source / synset / model / "models"
        folder.mkdir(parents=True)
        mesh = trimesh.creation.cylinder(radius=0.3, height=0.8)  # unitless, axis along z ...
        mesh.apply_transform(trimesh.transformations.rotation_matrix(-np.pi / 2, (1, 0, 0)))
        mesh.export(folder / "model_normalized.obj")  # ... now along y: ShapeNet's up
    manifest = build_dataset(
        _spec(tmp_path / "out", source=str(source), shapes_per_category=1),
        workers=1,
        progress=False,
    )
    assert sorted(manifest["categories"]) == ["bottle", "mug"]
    dataset = SketchVoxelDataset(tmp_path / "out")
    voxels = dataset[0]["voxels"].numpy()
    # Upright: the tall cylinder occupies more layers (k, up) than columns (i).
    layers = np.flatnonzero(voxels.any(axis=(0, 1)))
    columns = np.flatnonzero(voxels.any(axis=(1, 2)))
    assert len(layers) > len(columns) and layers[0] == 0
    recipe = json.loads((tmp_path / "out" / "manifest.json").read_text())["recipe"]
    assert recipe["source"] == str(source)


def test_object_frame_views_fill_their_grid_and_carry_search_crops(tmp_path: Path) -> None:
    spec = _spec(tmp_path, categories=("fruit", "can"), shapes_per_category=2)
    manifest = build_dataset(spec, workers=1, progress=False)
    shard = np.load(tmp_path / manifest["shards"][0]["file"])
    # The fitted grid follows the object's size; the fixed frame's is always 0.26 m.
    assert len(set(np.round(shard["grid_extent_m"], 4))) > 1
    dataset = SketchVoxelDataset(tmp_path, search_crops=True)
    assert len(dataset) == 2 * dataset.views
    fitted, searched = dataset[0], dataset[dataset.views]
    # The object fills more of the fitted crop than of the search crop, which has no voxels.
    assert float(fitted["silhouette"].mean()) > float(searched["silhouette"].mean()) > 0
    assert float(searched["voxels"].sum()) == 0 and float(fitted["voxels"].sum()) > 0
    names = dataset.shape_names()
    assert len(names) == len(dataset) and names[0] == names[dataset.views]


def test_fixed_frame_data_has_no_search_crops(tmp_path: Path) -> None:
    fixed = dataclasses.replace(TINY, frame="fixed")
    build_dataset(_spec(tmp_path, categories=("can",), recipe=fixed), workers=1, progress=False)
    assert np.allclose(np.load(tmp_path / "shard_00000.npz")["grid_extent_m"], fixed.grid_extent_m)
    with pytest.raises(ValueError, match="no search crops"):
        SketchVoxelDataset(tmp_path, search_crops=True)


def test_folders_train_together_and_a_new_one_keeps_the_old_split(tmp_path: Path) -> None:
    build_dataset(
        _spec(tmp_path / "a", categories=("box", "can"), shapes_per_category=4),
        workers=1,
        progress=False,
    )
    build_dataset(
        _spec(tmp_path / "b", categories=("creature",), shapes_per_category=4),
        workers=1,
        progress=False,
    )
    alone = SketchVoxelDataset(tmp_path / "a")
    together = SketchVoxelDataset([tmp_path / "a", tmp_path / "b"])
    assert together.categories == ["box", "can", "creature"]
    assert len(together) == len(alone) + len(SketchVoxelDataset(tmp_path / "b"))
    assert int(together[len(alone)]["category"]) == 2
    train_alone, val_alone = split_by_shape(alone, 0.25)
    train, val = split_by_shape(together, 0.25)
    # The first folder's views keep their split; the new folder has validation shapes of its own.
    assert [i for i in val if i < len(alone)] == val_alone
    assert [i for i in train if i < len(alone)] == train_alone
    assert any(i >= len(alone) for i in val)
    with pytest.raises(ValueError, match="different recipes"):
        build_dataset(
            _spec(
                tmp_path / "c", categories=("can",), recipe=dataclasses.replace(TINY, image_size=96)
            ),
            workers=1,
            progress=False,
        )
        SketchVoxelDataset([tmp_path / "a", tmp_path / "c"])
