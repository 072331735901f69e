"""The estimate a session starts from: space seen empty stays empty, the depth is fused in, and
the symmetry completion never puts points where the camera saw free space."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from drivers.config import CameraConfig
from models.camera import CameraIntrinsics
from models.geometry import VoxelGrid, axes_facing_camera
from models.metrics import distance_to_mesh
from models.object_bound import object_depth_points
from models.prior.carving import SEEN_EMPTY_PROBABILITY, CameraView, seen_empty_voxels
from models.prior.shape_prior import ShapePrior, available_priors
from models.prior.virtual_camera import grid_crop
from models.procedural import make_shape
from models.render import Scene, apply_kinect_depth_noise, make_table, render
from models.symmetry import SYMMETRY_SOURCE, complete_by_symmetry
from models.touch.observations import camera_observations
from models.vision import VisionSettings, estimate_from_frame, resolve_input

FULL = CameraIntrinsics.kinect_v2_colour(0.5)
POSE = CameraConfig().pose_world_camera()
GRID = VoxelGrid(64, 0.26, axes_world=axes_facing_camera(POSE[:3, 3]))
ALBEDO = (0.75, 0.35, 0.25)


def _frame(mesh: trimesh.Trimesh | None, seed: int = 0):
    """A bench frame of ``mesh`` (None: the empty table) with Kinect depth noise."""
    rng = np.random.default_rng(seed)
    scene = (
        Scene.bench(mesh, ALBEDO) if mesh is not None else Scene([], table=make_table((1.2, 0.8)))
    )
    frame = render(scene, FULL, POSE, rng=rng)
    depth = apply_kinect_depth_noise(frame.depth_m, frame.normals_camera, rng, intrinsics=FULL)
    return frame, depth


@pytest.fixture(scope="module")
def mug():
    return make_shape("mug", np.random.default_rng(0))


def test_input_auto_is_rgbd_where_the_camera_gives_depth() -> None:
    assert resolve_input("auto", None) == "rgb"
    assert resolve_input("auto", np.zeros((4, 4))) == "rgb"
    assert resolve_input("auto", np.full((4, 4), 0.7)) == "rgbd"
    assert resolve_input("rgb", np.full((4, 4), 0.7)) == "rgb"


def test_voxels_off_the_silhouette_and_in_front_of_the_depth_are_seen_empty() -> None:
    """A 6 cm cube on the table: voxels outside its silhouette's rays and in front of its
    measured faces are empty; its inside and the space behind it are not."""
    box = trimesh.creation.box((0.06, 0.06, 0.06))
    box.apply_translation((0.0, 0.0, 0.03))
    crop = grid_crop(FULL, POSE, GRID, 128)
    seen = render(Scene.bench(box, ALBEDO), crop.intrinsics, POSE)
    centres = GRID.voxel_centres_world()
    inside = box.contains(centres.reshape(-1, 3)).reshape(centres.shape[:-1])
    silhouette_only = seen_empty_voxels(GRID, crop, POSE, seen.silhouette)
    with_depth = seen_empty_voxels(GRID, crop, POSE, seen.silhouette, seen.depth_m)
    assert not (silhouette_only & inside).any() and not (with_depth & inside).any()
    assert silhouette_only.mean() > 0.8
    assert with_depth.sum() > silhouette_only.sum()
    # Straight behind the cube, hidden from the camera: never carved.
    behind = np.array([[0.045, 0.0, 0.02]])
    view = CameraView.from_image(crop.intrinsics, POSE, silhouette=seen.silhouette)
    assert not view.empty(behind).any()


@pytest.mark.parametrize("name", sorted(available_priors()))
def test_the_calibrated_priors_leave_an_empty_scene_empty(name: str) -> None:
    """The empty table seen with depth: nothing is predicted, whatever the calibration lifts.
    (From colour alone the sketch nets see an object on an empty table: they never saw one in
    training; docs/prior.md.)"""
    frame, sensor = _frame(None)
    prediction = ShapePrior.load(name).predict(frame.colour_rgb, FULL, POSE, GRID, depth_m=sensor)
    assert prediction.probabilities.max() <= SEEN_EMPTY_PROBABILITY


def test_an_empty_silhouette_carves_the_whole_grid() -> None:
    crop = grid_crop(FULL, POSE, GRID, 128)
    assert seen_empty_voxels(GRID, crop, POSE, np.zeros((128, 128), bool)).all()


@pytest.mark.parametrize("name", sorted(available_priors()))
def test_the_grid_corners_stay_empty_around_an_object(name: str, mug) -> None:
    frame, _ = _frame(mug)
    prediction = ShapePrior.load(name).predict(frame.colour_rgb, FULL, POSE, GRID)
    p = prediction.probabilities
    corners = p[np.ix_([0, -1], [0, -1], [0, -1])]
    assert corners.max() < 0.5
    assert (p > 0.5).any()  # the mug itself is there


def test_the_fused_depth_estimate_passes_within_2mm_of_the_depth_points(mug) -> None:
    frame, depth = _frame(mug)
    priors = {name: ShapePrior.load(name) for name in sorted(available_priors())}
    estimate = estimate_from_frame(
        priors, frame.colour_rgb, FULL, POSE, GRID, depth_m=depth, input_mode="auto"
    )
    assert estimate.input == "rgbd" and estimate.fused is not None
    points = object_depth_points(depth, FULL, POSE, estimate.grid)
    distance = np.abs(estimate.fused.sdf(points))
    assert np.median(distance) < 0.002 and np.percentile(distance, 90) < 0.002
    # Without depth the estimate is the prior's alone.
    rgb = estimate_from_frame(priors, frame.colour_rgb, FULL, POSE, GRID, input_mode="rgb")
    assert rgb.fused is None and rgb.input == "rgb"


def test_mirrored_points_never_enter_space_seen_free(mug) -> None:
    """On a can (rotation-symmetric) and a mug (mirror-symmetric body), the completion finds a
    symmetry whose points complete the far side near the true surface, and not one of them
    lies where the camera saw empty space."""
    can = trimesh.creation.cylinder(radius=0.035, height=0.11, sections=64)
    can.apply_translation((0.01, -0.01, 0.055))
    for mesh in (can, mug):
        _, depth = _frame(mesh)
        points = object_depth_points(depth, FULL, POSE, GRID)
        seen = camera_observations(points, POSE[:3, 3])
        view = CameraView.from_image(FULL, POSE, depth_m=depth)
        fit = complete_by_symmetry(seen, view)
        assert fit is not None
        completed = fit.observations.surface_points_world
        assert len(completed) > 20
        assert (fit.observations.surface_source == SYMMETRY_SOURCE).all()
        assert not view.empty(completed).any()
        assert view.hidden(completed).all()
        assert np.median(distance_to_mesh(completed, mesh.subdivide())) < 0.006


def test_symmetry_completion_can_be_switched_off(mug) -> None:
    frame, depth = _frame(mug)
    prior = {"general": ShapePrior.load("general")}
    off = estimate_from_frame(
        prior,
        frame.colour_rgb,
        FULL,
        POSE,
        GRID,
        depth_m=depth,
        settings=VisionSettings(symmetry=False),
    )
    assert off.symmetry is None
    assert not (off.camera_observations.surface_source == SYMMETRY_SOURCE).any()


def _animal(yaw_deg: float) -> trimesh.Trimesh:
    """A mirror-symmetric four-legged animal, 20 cm long: a body, legs and a head, with its
    mid-plane at ``yaw_deg`` about the vertical."""
    body = trimesh.creation.icosphere(3, 1.0)
    body.apply_scale((0.08, 0.035, 0.035))
    body.apply_translation((0.0, 0.0, 0.09))
    parts = [body]
    for x in (-0.05, 0.05):
        for y in (-0.022, 0.022):
            leg = trimesh.creation.cylinder(radius=0.01, height=0.075, sections=24)
            leg.apply_translation((x, y, 0.0375))
            parts.append(leg)
    head = trimesh.creation.icosphere(3, 0.028)
    head.apply_translation((0.105, 0.0, 0.14))
    neck = trimesh.creation.cylinder(radius=0.016, segment=((0.06, 0.0, 0.1), (0.1, 0.0, 0.135)))
    tail = trimesh.creation.cylinder(radius=0.006, segment=((-0.07, 0.0, 0.1), (-0.11, 0.0, 0.06)))
    parts += [head, neck, tail]
    animal = trimesh.util.concatenate(parts)
    animal.apply_transform(trimesh.transformations.rotation_matrix(np.radians(yaw_deg), (0, 0, 1)))
    return animal


@pytest.mark.parametrize("yaw_deg", [22.5, 52.5, 67.5])
def test_an_elongated_animal_is_completed_by_its_mid_plane(yaw_deg: float) -> None:
    """With its mid-plane between two of the coarse search's angles (the worst case, 7.5
    degrees from both), the plane is found and its copies fill the far flank. (At 37.5 degrees
    its thin legs put more than the allowed 8 % of every candidate's copies in seen-empty
    space, and none is used.)"""
    animal = _animal(yaw_deg)
    _, depth = _frame(animal)
    points = object_depth_points(depth, FULL, POSE, GRID)
    view = CameraView.from_image(FULL, POSE, depth_m=depth)
    fit = complete_by_symmetry(camera_observations(points, POSE[:3, 3]), view)
    assert fit is not None and fit.kind == "plane"
    true_normal = np.array([-np.sin(np.radians(yaw_deg)), np.cos(np.radians(yaw_deg)), 0.0])
    assert abs(fit.direction_world @ true_normal) > np.cos(np.radians(5.0))
    completed = fit.observations.surface_points_world
    assert len(completed) > 20 and not view.empty(completed).any()
    assert np.median(distance_to_mesh(completed, animal)) < 0.006
