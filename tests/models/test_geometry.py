"""Geometry round trips and the paper's registrations, with noise where the real world has it."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from models.geometry import (
    VoxelGrid,
    axes_facing_camera,
    frame_from_z_axis,
    invert_transform,
    make_transform,
    matrix_to_ur_pose,
    point_segment_distance,
    points_along_segment,
    radial_angle_about_vertical,
    ray_plane_intersection,
    register_points,
    rotation_angle_between,
    segment_box_clip,
    transform_points,
    ur_pose_to_matrix,
)


def random_transform(rng: np.random.Generator) -> np.ndarray:
    return make_transform(Rotation.random(random_state=rng).as_matrix(), rng.uniform(-1, 1, 3))


def test_transform_inverse_round_trip(rng: np.random.Generator) -> None:
    for _ in range(20):
        transform = random_transform(rng)
        points = rng.uniform(-1, 1, (50, 3))
        back = transform_points(invert_transform(transform), transform_points(transform, points))
        np.testing.assert_allclose(back, points, atol=1e-12)
        np.testing.assert_allclose(transform @ invert_transform(transform), np.eye(4), atol=1e-12)


def test_ur_pose_round_trip(rng: np.random.Generator) -> None:
    for _ in range(50):
        transform = random_transform(rng)
        pose = matrix_to_ur_pose(transform)
        assert np.linalg.norm(pose[3:]) <= np.pi + 1e-9
        np.testing.assert_allclose(ur_pose_to_matrix(pose), transform, atol=1e-10)


def test_ur_pose_known_value() -> None:
    # Rotation of pi about x: the TCP pointing straight down, as on a UR pendant.
    transform = ur_pose_to_matrix([0.1, 0.2, 0.3, np.pi, 0.0, 0.0])
    np.testing.assert_allclose(transform[:3, 2], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(transform[:3, 3], [0.1, 0.2, 0.3])
    with pytest.raises(ValueError, match="6 values"):
        ur_pose_to_matrix([0, 0, 0])


def test_three_point_registration_is_exact(rng: np.random.Generator) -> None:
    # The paper's calibration points (0,0,0), (1,0,0), (0,1,0) in the world.
    pose_robot_world = random_transform(rng)
    points_world = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    points_robot = transform_points(pose_robot_world, points_world)
    registration = register_points(points_world, points_robot)
    np.testing.assert_allclose(registration.transform_to_from, pose_robot_world, atol=1e-10)
    assert registration.max_residual_m < 1e-10


def test_least_squares_registration_under_noise(rng: np.random.Generator) -> None:
    pose_robot_world = random_transform(rng)
    points_world = rng.uniform(-0.3, 0.3, (12, 3))
    noise_m = 0.0005
    points_robot = transform_points(pose_robot_world, points_world) + rng.normal(
        0, noise_m, (12, 3)
    )
    registration = register_points(points_world, points_robot)
    rotation_error = rotation_angle_between(
        registration.transform_to_from[:3, :3], pose_robot_world[:3, :3]
    )
    translation_error = np.linalg.norm(
        registration.transform_to_from[:3, 3] - pose_robot_world[:3, 3]
    )
    assert rotation_error < np.radians(0.3)
    assert translation_error < 3 * noise_m
    # Residuals reflect the noise (3-D noise of sigma s has rms ~ s * sqrt(3) * sqrt((n-2)/n)).
    assert 0.3 * noise_m < registration.rms_residual_m < 2.5 * noise_m
    assert "12 points" in registration.report()


def test_registration_rejects_degenerate_input() -> None:
    with pytest.raises(ValueError, match="at least 3"):
        register_points(np.zeros((2, 3)), np.zeros((2, 3)))
    collinear = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    with pytest.raises(ValueError, match="collinear"):
        register_points(collinear, collinear)


def test_voxel_grid_paper_registration() -> None:
    grid = VoxelGrid(resolution=64, extent_m=0.256, origin_world=(0.1, 0.2, 0.0))
    # The bottom centre o_v lands on the table point o_w.
    np.testing.assert_allclose(grid.voxel_to_world(grid.origin_voxel), [0.1, 0.2, 0.0])
    # x_w = R_v (x_v - o_v) + o_w with R_v = s [a_x a_y a_z] and the paper's a_x = (-1, 0, 0).
    voxel = np.array([40.0, 10.0, 5.0])
    expected = 0.004 * np.array([-(40 - 32), 10 - 32, 5]) + [0.1, 0.2, 0.0]
    np.testing.assert_allclose(grid.voxel_to_world(voxel), expected, atol=1e-12)
    np.testing.assert_allclose(grid.world_to_voxel(expected), voxel, atol=1e-9)
    centres = grid.voxel_centres_world()
    assert centres.shape == (64, 64, 64, 3)
    np.testing.assert_allclose(centres[32, 32, 0], [0.1 - 0.002, 0.2 + 0.002, 0.002], atol=1e-12)


def test_voxel_axes_follow_camera_yaw() -> None:
    # A camera on the -x side looks along +x: the paper's axes.
    axes = axes_facing_camera((-0.6, 0.0, 0.45))
    np.testing.assert_allclose(axes, [[-1, 0, 0], [0, -1, 0], [0, 0, 1]], atol=1e-12)
    axes = np.array(axes_facing_camera((0.0, 0.6, 0.45)))
    np.testing.assert_allclose(axes[0], [0, 1, 0], atol=1e-12)
    assert np.isclose(np.linalg.det(axes), 1.0)
    with pytest.raises(ValueError):
        axes_facing_camera((0.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="orthonormal"):
        VoxelGrid(axes_world=((1, 0, 0), (1, 0, 0), (0, 0, 1)))


def test_ray_and_segment_helpers() -> None:
    assert ray_plane_intersection([0, 0, 1], [0, 0, -1], [0, 0, 0], [0, 0, 1]) == pytest.approx(1)
    assert ray_plane_intersection([0, 0, 1], [0, 0, 1], [0, 0, 0], [0, 0, 1]) is None
    assert ray_plane_intersection([0, 0, 1], [1, 0, 0], [0, 0, 0], [0, 0, 1]) is None
    t0, t1 = segment_box_clip([-2, 0, 0], [2, 0, 0], [-1, -1, -1], [1, 1, 1])
    assert (t0, t1) == (pytest.approx(0.25), pytest.approx(0.75))
    assert segment_box_clip([-2, 2, 0], [2, 2, 0], [-1, -1, -1], [1, 1, 1]) is None
    points = points_along_segment([0, 0, 0], [0.1, 0, 0], 0.03)
    assert len(points) == 5 and np.all(np.diff(points[:, 0]) <= 0.03 + 1e-12)
    assert point_segment_distance([0.5, 1, 0], [0, 0, 0], [1, 0, 0]) == pytest.approx(1)
    assert point_segment_distance([2, 0, 0], [0, 0, 0], [1, 0, 0]) == pytest.approx(1)
    assert radial_angle_about_vertical([1, 0, 0.2], [0, 1, 0.1]) == pytest.approx(np.pi / 2)
    assert radial_angle_about_vertical([1, 0, 0], [-1, 0, 0]) == pytest.approx(np.pi)


def test_frame_from_z_axis(rng: np.random.Generator) -> None:
    for _ in range(20):
        z = rng.normal(size=3)
        frame = frame_from_z_axis(z)
        np.testing.assert_allclose(frame.T @ frame, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(frame), 1.0)
        np.testing.assert_allclose(frame[:, 2], z / np.linalg.norm(z), atol=1e-12)
    np.testing.assert_allclose(frame_from_z_axis([1, 0, 0])[:, 2], [1, 0, 0])
