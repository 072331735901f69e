"""prior = "auto": the prior whose shape explains the seen silhouette is chosen; sizes are
measured per grid axis."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from models.camera import CameraIntrinsics, look_at_pose
from models.geometry import VoxelGrid, axes_facing_camera
from models.prior.auto import choose_prior, silhouette_agreement
from models.prior.evaluation import extent_errors
from models.prior.networks import ShapeNet
from models.prior.shape_prior import PriorPrediction, ShapePrior
from models.prior.virtual_camera import grid_crop
from models.procedural import make_shape
from models.render import Scene, SceneObject, render
from models.shapes import voxelize

POSE = look_at_pose((-0.62, 0.0, 0.4572), (0.0, 0.0, 0.1))
GRID = VoxelGrid(64, 0.26, axes_world=axes_facing_camera(POSE[:3, 3]))
CROP = grid_crop(CameraIntrinsics.kinect_v2_colour(0.5), POSE, GRID, 128)


def _box(size: tuple[float, float, float], x: float = 0.0) -> trimesh.Trimesh:
    box = trimesh.creation.box(size)
    box.apply_translation((x, 0.0, size[2] / 2))
    return box


def _prediction(mesh: trimesh.Trimesh, seen: np.ndarray, name: str) -> PriorPrediction:
    """What a prior that decoded ``mesh`` would return, the sketch net having seen ``seen``."""
    return PriorPrediction(
        probabilities=voxelize(mesh, GRID).astype(np.float32),
        latent=torch.zeros(200),
        depth_m=np.zeros((128, 128), np.float32),
        normals_camera=np.zeros((128, 128, 3), np.float32),
        silhouette=seen.astype(np.float32),
        crop=CROP,
        grid=GRID,
        prior=name,
    )


@pytest.fixture(scope="module")
def seen() -> np.ndarray:
    truth = _box((0.06, 0.08, 0.14))
    return render(Scene(objects=[SceneObject(truth)]), CROP.intrinsics, POSE).silhouette


def test_the_right_shape_agrees_with_the_silhouette(seen: np.ndarray) -> None:
    right = silhouette_agreement(_prediction(_box((0.06, 0.08, 0.14)), seen, "right"), POSE)
    flat = silhouette_agreement(_prediction(_box((0.12, 0.12, 0.04)), seen, "flat"), POSE)
    assert right > 0.8 and flat < 0.5 * right


class _FixedPrior:
    """Stands in for a ShapePrior: returns a fixed prediction."""

    def __init__(self, prediction: PriorPrediction) -> None:
        self.prediction = prediction

    def predict(self, *args, **kwargs) -> PriorPrediction:
        return self.prediction


def test_auto_chooses_the_prior_that_explains_the_image(seen: np.ndarray) -> None:
    priors = {
        "flat": _FixedPrior(_prediction(_box((0.12, 0.12, 0.04)), seen, "flat")),
        "right": _FixedPrior(_prediction(_box((0.06, 0.08, 0.14)), seen, "right")),
    }
    image = np.zeros((540, 960, 3), np.uint8)
    chosen, scores = choose_prior(priors, image, CROP.intrinsics, POSE, GRID)  # type: ignore[arg-type]
    assert chosen.prior == "right" and scores["right"] > scores["flat"]
    with pytest.raises(ValueError, match="no priors"):
        choose_prior({}, image, CROP.intrinsics, POSE, GRID)


def test_extent_errors_per_grid_axis() -> None:
    box = _box((0.10, 0.06, 0.12))
    errors = extent_errors(voxelize(box, GRID).astype(np.float32), GRID, box)
    # Within a voxel (4 mm) on every axis: the grid's axes here are the world's up to sign.
    assert np.all(np.abs(errors) * np.array([0.10, 0.06, 0.12]) <= GRID.voxel_size_m + 1e-9)
    assert np.all(np.isnan(extent_errors(np.zeros((64, 64, 64)), GRID, box)))


def test_priors_sharing_a_sketch_net_run_it_once_per_crop() -> None:
    torch.manual_seed(0)
    general = ShapePrior.untrained("cpu")
    box = ShapePrior(
        general.sketch_net, ShapeNet(general.preset), name="box", sketch_key=general.sketch_key
    )
    priors = {"general": general, "box": box}
    rng = np.random.default_rng(0)
    scene = Scene.bench(make_shape("can", rng), (0.75, 0.35, 0.25))
    intrinsics = CameraIntrinsics.kinect_v2_colour(0.5)
    image = render(scene, intrinsics, POSE).colour_rgb
    passes: list[int] = []
    general.sketch_net.register_forward_hook(lambda *_: passes.append(1))
    alone = {name: prior.predict(image, intrinsics, POSE, GRID) for name, prior in priors.items()}
    assert len(passes) == 2

    passes.clear()
    chosen, scores = choose_prior(priors, image, intrinsics, POSE, GRID)

    assert len(passes) == 1  # both priors see the same crop through the same net
    assert set(scores) == {"general", "box"}
    np.testing.assert_array_equal(
        chosen.probabilities, alone[chosen.prior].probabilities
    )  # sharing changes nothing
