"""The virtual camera and the ShapePrior: crops, frames, named weights, RGB-D, decode."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from drivers.config import CameraConfig
from models.camera import CameraIntrinsics
from models.geometry import VoxelGrid, axes_facing_camera
from models.prior.dataset import registered_grid
from models.prior.shape_prior import (
    DEFAULT_WEIGHTS_DIR,
    PriorNotFoundError,
    ShapePrior,
    available_priors,
)
from models.prior.training import WeightsError, save_weights
from models.prior.virtual_camera import crop_image, grid_crop, sensor_normals_camera
from models.procedural import make_shape
from models.render import Scene, apply_kinect_depth_noise, render

FULL = CameraIntrinsics.kinect_v2_colour(0.5)


@pytest.fixture(scope="module")
def bench_frame():
    rng = np.random.default_rng(0)
    scene = Scene.bench(make_shape("mug", rng), (0.75, 0.35, 0.25))
    pose = CameraConfig().pose_world_camera()
    return scene, pose, render(scene, FULL, pose)


def test_crop_of_full_frame_matches_render_at_virtual_camera(bench_frame) -> None:
    """Training renders through the virtual camera; inference crops the full frame: same pixels."""
    scene, pose, full = bench_frame
    grid = VoxelGrid(64, 0.26, axes_world=axes_facing_camera(pose[:3, 3]))
    crop = grid_crop(FULL, pose, grid, 128)
    direct = render(scene, crop.intrinsics, pose)
    cropped = crop_image(full.silhouette.astype(np.uint8) * 255, crop) > 127
    both, either = cropped & direct.silhouette, cropped | direct.silhouette
    assert both.sum() / either.sum() > 0.97
    depth = crop_image(full.depth_m, crop, nearest=True)
    assert np.median(np.abs(depth[both] - direct.depth_m[both])) < 2e-3
    colour = crop_image(full.colour_rgb, crop)
    assert colour.dtype == np.uint8 and colour.shape == (128, 128, 3)
    assert np.abs(colour.astype(float) - direct.colour_rgb).mean() < 3.0
    # Nearness round trip, and no return stays no return.
    assert np.allclose(crop.depth_m(crop.nearness(direct.depth_m)), direct.depth_m, atol=1e-5)


def test_training_grid_is_the_controller_grid(bench_frame) -> None:
    from controller.config import VoxelGridConfig
    from models.prior.dataset import ViewRecipe

    _, pose, _ = bench_frame
    assert registered_grid(ViewRecipe(), pose) == VoxelGridConfig().grid(tuple(pose[:3, 3]))


def test_untrained_prior_predicts_in_the_grid_frame(bench_frame) -> None:
    _, pose, full = bench_frame
    prior = ShapePrior.untrained("cpu")
    grid = VoxelGrid(64, 0.26, axes_world=axes_facing_camera(pose[:3, 3]))
    rgb = prior.predict(full.colour_rgb, FULL, pose, grid)
    rgbd = prior.predict(full.colour_rgb, FULL, pose, grid, depth_m=full.depth_m)
    for prediction in (rgb, rgbd):
        assert prediction.probabilities.shape == (64, 64, 64)
        assert prediction.latent.shape == (200,)
        assert prediction.silhouette.shape == (128, 128)
        assert prediction.normals_camera.shape == (128, 128, 3)
    latent = rgb.latent.clone().requires_grad_(True)
    decoded = prior.decode(latent)
    assert decoded.shape == (64, 64, 64)
    decoded.sum().backward()
    assert latent.grad is not None
    with pytest.raises(ValueError, match="64\\^3"):
        prior.predict(full.colour_rgb, FULL, pose, VoxelGrid(32, 0.26))


def test_named_priors_load_and_unknown_names_list_the_available(tmp_path: Path) -> None:
    torch.manual_seed(0)
    reference = ShapePrior.untrained("cpu")
    save_weights(reference.sketch_net, "sketch", "cpu", tmp_path / "s.pt")
    save_weights(reference.shape_net, "shape", "cpu", tmp_path / "b.pt")
    entry = {
        "preset": "cpu",
        "sketch_weights": "s.pt",
        "shape_weights": "b.pt",
        "grid_extent_m": 0.26,
    }
    (tmp_path / "priors.json").write_text(json.dumps({"priors": [{"name": "box", **entry}]}))
    prior = ShapePrior.load("box", weights_dir=tmp_path)
    latent = torch.randn(2, 200)
    with torch.no_grad():
        assert torch.allclose(prior.decode(latent), reference.decode(latent), atol=2e-2)
    with pytest.raises(PriorNotFoundError, match=r"available: box \(cpu\)"):
        ShapePrior.load("mugs", weights_dir=tmp_path)
    with pytest.raises(PriorNotFoundError, match="preset 'paper'"):
        ShapePrior.load("box", preset="paper", weights_dir=tmp_path)


def _tiny_weights_folder(folder: Path) -> Path:
    """A weights folder of one untrained prior, 'general'."""
    folder.mkdir(parents=True, exist_ok=True)
    prior = ShapePrior.untrained("cpu")
    save_weights(prior.sketch_net, "sketch", "cpu", folder / "sketch.pt")
    save_weights(prior.shape_net, "shape", "cpu", folder / "shape.pt")
    entry = {"preset": "cpu", "sketch_weights": "sketch.pt", "shape_weights": "shape.pt"}
    (folder / "priors.json").write_text(
        json.dumps({"priors": [{"name": "general", "grid_extent_m": 0.26, **entry}]})
    )
    return folder


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        ("truncate", "not valid ShapeNet weights"),
        ("swap", "not valid ShapeNet weights"),  # the sketch net's weights in the shape file
        ("delete", "missing"),
    ],
)
def test_corrupt_weights_are_refused_naming_the_file(
    tmp_path: Path, damage: str, message: str
) -> None:
    folder = _tiny_weights_folder(tmp_path / "weights")
    shape = folder / "shape.pt"
    if damage == "truncate":
        shape.write_bytes(shape.read_bytes()[:5000])
    elif damage == "swap":
        shape.write_bytes((folder / "sketch.pt").read_bytes())
    else:
        shape.unlink()
    with pytest.raises(WeightsError) as error:
        ShapePrior.load("general", weights_dir=folder)
    assert str(error.value).startswith(f"{shape}: {message}")


def test_a_corrupt_priors_index_is_refused_naming_it(tmp_path: Path) -> None:
    folder = _tiny_weights_folder(tmp_path / "weights")
    (folder / "priors.json").write_text('{"priors": [{"name": ')
    with pytest.raises(WeightsError, match=r"priors\.json: not a valid priors index"):
        ShapePrior.load("general", weights_dir=folder)


def test_the_service_refuses_corrupt_weights_at_start_up(tmp_path: Path) -> None:
    """`touchshape explore` with a corrupt shape-net file: one line naming it, exit 2, before
    any session."""
    folder = _tiny_weights_folder(tmp_path / "weights")
    (folder / "shape.pt").write_bytes(b"not a torch file")
    config = tmp_path / "config.toml"
    config.write_text(
        f'[models]\nweights_dir = "{folder}"\n[logging]\ndir = "{tmp_path / "logs"}"\n'
    )
    touchshape = Path(sys.executable).with_name("touchshape")
    run = subprocess.run(
        [str(touchshape), "explore", "--config", str(config), "--touches", "1"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 2, run.stdout + run.stderr
    errors = run.stderr.strip().splitlines()
    assert len(errors) == 1, run.stderr
    assert errors[0].startswith(f"touchshape: error: {folder / 'shape.pt'}: not valid ShapeNet")
    assert not list((tmp_path / "logs").glob("*/summary.json"))


def test_shipped_priors_are_listed() -> None:
    priors = available_priors()
    assert {"general", "box"} <= set(priors)
    for specs in priors.values():
        for spec in specs:
            assert (DEFAULT_WEIGHTS_DIR / spec.shape_weights).name.endswith(".pt")


@pytest.mark.skipif(
    not (DEFAULT_WEIGHTS_DIR / "general_shape_cpu.pt").exists(), reason="weights not trained yet"
)
def test_shipped_general_prior_sees_the_mug(bench_frame) -> None:
    _, pose, full = bench_frame
    prior = ShapePrior.load("general")
    grid = VoxelGrid(64, 0.26, axes_world=axes_facing_camera(pose[:3, 3]))
    prediction = prior.predict(full.colour_rgb, FULL, pose, grid)
    occupied = prediction.probabilities > 0.5
    assert 0 < occupied.mean() < 0.2
    assert occupied[:, :, :2].any()  # stands on the table (k = 0 is the bottom layer)


def test_eval_prior_command_on_a_user_mesh_file(tmp_path: Path) -> None:
    from controller.cli.main import main

    torch.manual_seed(0)
    untrained = ShapePrior.untrained("cpu")
    save_weights(untrained.sketch_net, "sketch", "cpu", tmp_path / "s.pt")
    save_weights(untrained.shape_net, "shape", "cpu", tmp_path / "b.pt")
    entry = {
        "name": "general",
        "preset": "cpu",
        "sketch_weights": "s.pt",
        "shape_weights": "b.pt",
        "grid_extent_m": 0.26,
    }
    (tmp_path / "priors.json").write_text(json.dumps({"priors": [entry]}))
    mesh_file = tmp_path / "carton.stl"
    trimesh.creation.box(extents=(0.08, 0.05, 0.12)).export(mesh_file)
    out = tmp_path / "eval.json"
    argv = [
        "eval",
        "prior",
        "--weights-dir",
        str(tmp_path),
        "--objects",
        str(mesh_file),
        "--views",
        "1",
        "--input",
        "rgbd",
        "--json",
        str(out),
    ]
    assert main(argv) == 0
    result = json.loads(out.read_text())
    assert result["objects"][0]["name"] == "carton"
    assert {"iou", "chamfer_mm"} <= set(result["objects"][0]) and "iou" in result["mean"]
    row = result["objects"][0]
    assert row["priors_chosen"] == ["general"] and len(row["extent_error_xyz"]) == 3
    assert {"fscore_2mm", "fscore_5mm", "size_error"} <= set(row)
    assert "size_error_median" in result["mean"]
    assert row["views"] == [
        {
            "prior": "general",
            "iou": round(row["iou"], 4),
            "chamfer_mm": row["views"][0]["chamfer_mm"],
        }
    ]


def test_object_frame_prior_decodes_in_the_grid_fitted_to_the_object(bench_frame) -> None:
    """RGB-D finds the silhouette from depth, whatever the nets' weights: the fitted grid holds
    the mug and is smaller than the registered 26 cm cube."""
    scene, pose, full = bench_frame
    prior = ShapePrior.untrained("cpu")
    prior.frame = "object"
    grid = VoxelGrid(64, 0.26, axes_world=axes_facing_camera(pose[:3, 3]))
    prediction = prior.predict(full.colour_rgb, FULL, pose, grid, depth_m=full.depth_m)
    fitted = prediction.grid
    mug = scene.objects[0].mesh
    assert fitted.extent_m < 0.26 and fitted.extent_m > float(np.max(mug.extents))
    inside = fitted.world_to_voxel(mug.sample(2000, seed=0))
    assert np.mean(np.all((inside >= 0) & (inside <= 64), axis=1)) > 0.97
    assert prediction.probabilities.shape == (64, 64, 64)


def test_sensor_normals_are_the_surface_normals_away_from_depth_edges(bench_frame) -> None:
    """The normals RGB-D inference takes from the Kinect's depth follow the surface (the
    renderer's normals) and are left out where the depth jumps (the rim, the mug against the
    table) or where nothing returned."""
    scene, pose, _ = bench_frame
    grid = VoxelGrid(64, 0.26, axes_world=axes_facing_camera(pose[:3, 3]))
    crop = grid_crop(FULL, pose, grid, 128)
    clean = render(scene, crop.intrinsics, pose)
    rng = np.random.default_rng(1)
    sensor = apply_kinect_depth_noise(
        clean.depth_m, clean.normals_camera, rng, intrinsics=crop.intrinsics
    )
    normals, known = sensor_normals_camera(sensor, crop)
    on_object = known & clean.silhouette
    assert on_object.sum() > 0.4 * clean.silhouette.sum()
    cosine = np.sum(normals[on_object] * clean.normals_camera[on_object], axis=-1)
    assert np.median(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))) < 15.0
    assert not known[sensor == 0].any()
    # A jump of 2 cm to a row or column neighbour is an edge (a slope seen at the Kinect's
    # steepest incidence, 80 degrees, rises 1.4 cm a crop pixel).
    padded = np.pad(sensor, 1)
    jump = np.max(
        [
            np.abs(padded[1 + dv : 129 + dv, 1 + du : 129 + du] - sensor)
            for dv, du in ((0, 1), (0, -1), (1, 0), (-1, 0))
        ],
        axis=0,
    )
    edge = (sensor > 0) & (jump > 0.02) & (jump < sensor)
    assert edge.sum() > 10 and not known[edge].any()


def test_rgbd_inference_gives_the_shape_net_what_the_sensor_measured(bench_frame) -> None:
    """With depth, the shape net's input is masked by the outline seen in depth and carries
    the depth's normals wherever they are known (PriorPrediction.normals_camera is that input)."""
    _, pose, full = bench_frame
    prior = ShapePrior.untrained("cpu")
    grid = VoxelGrid(64, 0.26, axes_world=axes_facing_camera(pose[:3, 3]))
    prediction = prior.predict(full.colour_rgb, FULL, pose, grid, depth_m=full.depth_m)
    sensor = crop_image(full.depth_m, prediction.crop, nearest=True)
    normals, known = sensor_normals_camera(sensor, prediction.crop)
    measured = known & prediction.seen_silhouette
    assert measured.sum() > 100
    assert np.allclose(prediction.normals_camera[measured], normals[measured], atol=1e-6)
    assert not prediction.normals_camera[~prediction.seen_silhouette].any()
