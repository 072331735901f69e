"""The fused shape (models/touch/fused.py): the prior's signed distance, posed and bent through
the tactile measurements by a Gaussian-process correction."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt

from models.geometry import VoxelGrid
from models.metrics import distance_to_mesh
from models.touch.constraints import TouchResult
from models.touch.fused import FusedShape, FusionSettings, _GramFactor
from models.touch.observations import ObservationsError, SurfaceObservations, thin_to_lattice
from models.touch.posed_prior import (
    Pose,
    SignedDistanceGrid,
    _inside_distance,
    fit_pose,
    posed_grid,
)

GRID = VoxelGrid(64, 0.26, (0.0, 0.0, 0.0))
HALF = np.array([0.04, 0.03, 0.05])  # a rounded box 8 x 6 x 10 cm
CENTRE = np.array([0.0, 0.0, 0.05])
NO_SHIFT = np.zeros(3)
NO_POINTS = np.zeros((0, 3))


def box_field(points: np.ndarray, shift: np.ndarray = NO_SHIFT) -> np.ndarray:
    """A rounded box's implicit function (< 0 inside), about metres near its faces."""
    scaled = (points - CENTRE - shift) / HALF
    return ((np.abs(scaled) ** 8).sum(-1) ** 0.125 - 1.0) * HALF.min()


def box_probabilities(shift: np.ndarray = NO_SHIFT) -> np.ndarray:
    centres = GRID.voxel_centres_world()
    return (1.0 / (1.0 + np.exp(box_field(centres, shift) / 0.002))).astype(np.float32)


def patch(centre: np.ndarray, normal: np.ndarray, half_m: float = 0.004, step_m: float = 0.0005):
    """Points of a flat square patch on a plane, with the plane's normal."""
    normal = normal / np.linalg.norm(normal)
    u = np.cross(normal, [0.0, 0.0, 1.0] if abs(normal[2]) < 0.9 else [1.0, 0.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(normal, u)
    steps = np.arange(-half_m, half_m + 1e-9, step_m)
    a, b = np.meshgrid(steps, steps)
    points = centre + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
    return points, np.tile(normal, (len(points), 1))


def observations(points, normals, free=NO_POINTS, source=None) -> SurfaceObservations:
    source = np.zeros(len(points), np.int64) if source is None else np.asarray(source)
    return SurfaceObservations(np.asarray(points), np.asarray(normals), free, source)


@pytest.fixture(scope="module")
def prior() -> np.ndarray:
    return box_probabilities()


def test_prior_distance_is_exact_near_the_surface(prior: np.ndarray) -> None:
    field = SignedDistanceGrid.from_probabilities(prior, GRID)
    face = np.array([[0.04 + d, 0.0, 0.05] for d in (-0.004, -0.001, 0.0, 0.002, 0.006)])
    assert np.allclose(field(face), [-0.004, -0.001, 0.0, 0.002, 0.006], atol=4e-4)


def test_the_distance_at_its_own_voxel_centres_is_the_interpolated_one(prior: np.ndarray) -> None:
    field = SignedDistanceGrid.from_probabilities(prior, GRID)
    interpolated = field(GRID.voxel_centres_world())
    assert np.allclose(field.at_voxel_centres(GRID), interpolated, atol=1e-9)
    moved = posed_grid(GRID, Pose(x_m=0.003, yaw_rad=0.1))
    assert np.allclose(field.at_voxel_centres(moved), field(moved.voxel_centres_world()))


def test_a_face_measured_5mm_out_moves_there(prior: np.ndarray) -> None:
    points, normals = patch(np.array([0.045, 0.0, 0.05]), np.array([1.0, 0.0, 0.0]))
    shape = FusedShape.from_prior(
        prior, GRID, observations(points, normals), FusionSettings(pose_fit=False)
    )
    assert np.median(np.abs(shape.sdf(points))) < 1e-4 and np.abs(shape.sdf(points)).max() < 5e-4
    mesh = shape.mesh()
    # The face at the patch's centre is where the sensor measured it, not where vision put it.
    assert np.median(distance_to_mesh(points, mesh)) < 3e-4
    ray = np.array([[x, 0.0, 0.05] for x in np.arange(0.035, 0.055, 0.0002)])
    crossing = ray[np.argmax(shape.sdf(ray) > 0), 0]
    assert crossing == pytest.approx(0.045, abs=4e-4)


def test_contacts_lie_on_the_fused_surface_with_agreeing_normals(prior: np.ndarray) -> None:
    # Two patches on a tilted face 3 mm inside the prior's corner region and one on top.
    parts = [
        patch(np.array([0.03, 0.02, 0.05]), np.array([1.0, 1.0, 0.0])),
        patch(np.array([0.0, 0.0, 0.098]), np.array([0.0, 0.0, 1.0])),
    ]
    points = np.concatenate([p for p, _ in parts])
    normals = np.concatenate([n for _, n in parts])
    source = np.repeat([0, 1], [len(parts[0][0]), len(parts[1][0])])
    shape = FusedShape.from_prior(
        prior, GRID, observations(points, normals, source=source), FusionSettings(pose_fit=False)
    )
    assert np.median(np.abs(shape.sdf(points))) < 1e-4 and np.abs(shape.sdf(points)).max() < 5e-4
    eps = 1e-4
    gradient = np.stack(
        [
            (shape.sdf(points + eps * e) - shape.sdf(points - eps * e)) / (2 * eps)
            for e in np.eye(3)
        ],
        axis=1,
    )
    gradient /= np.linalg.norm(gradient, axis=1, keepdims=True)
    assert np.median(np.sum(gradient * normals, axis=1)) > 0.95
    assert np.median(distance_to_mesh(points, shape.mesh())) < 3e-4


def test_free_points_stay_outside(prior: np.ndarray) -> None:
    # The sensor swept through the prior's +x face region 3 mm deep without contact, and met
    # the object further in.
    points, normals = patch(np.array([0.036, 0.0, 0.05]), np.array([1.0, 0.0, 0.0]))
    ys, zs = np.meshgrid(np.arange(-0.006, 0.0061, 0.001), np.arange(0.044, 0.0561, 0.001))
    free = np.stack([np.full(ys.size, 0.039), ys.ravel(), zs.ravel()], axis=1)
    assert (box_field(free) < 0).all()  # the prior says inside
    shape = FusedShape.from_prior(
        prior, GRID, observations(points, normals, free), FusionSettings(pose_fit=False)
    )
    assert (shape.sdf(free) > 0).all()
    assert np.abs(shape.sdf(points)).max() < 3e-4


def test_far_from_touches_the_field_is_the_prior(prior: np.ndarray) -> None:
    points, normals = patch(np.array([0.045, 0.0, 0.05]), np.array([1.0, 0.0, 0.0]))
    settings = FusionSettings(pose_fit=False, support_m=0.03)
    shape = FusedShape.from_prior(prior, GRID, observations(points, normals), settings)
    plain = SignedDistanceGrid.from_probabilities(prior, GRID)
    rng = np.random.default_rng(0)
    queries = CENTRE + rng.uniform(-0.06, 0.06, size=(4000, 3))
    far = np.linalg.norm(queries - points.mean(axis=0), axis=1) > 0.03 + 0.006
    assert far.sum() > 1000
    assert np.array_equal(
        shape.sdf(queries[far]), np.maximum(plain(queries[far]), -queries[far, 2])
    )
    assert np.allclose(shape.std(queries[far]), settings.prior_std_m)
    # ... and near them the field changed and is certain.
    assert np.median(shape.std(points)) < 0.25 * settings.prior_std_m


def test_a_10mm_shift_is_recovered_by_the_pose_fit(prior: np.ndarray) -> None:
    shift = np.array([0.010, -0.004, 0.0])
    parts, sources = [], []
    for n, (centre, normal) in enumerate(
        [
            ((0.04, 0.0, 0.05), (1, 0, 0)),
            ((-0.04, 0.01, 0.04), (-1, 0, 0)),
            ((0.0, 0.03, 0.06), (0, 1, 0)),
            ((0.01, -0.03, 0.05), (0, -1, 0)),
            ((0.0, 0.0, 0.1), (0, 0, 1)),
        ]
    ):
        points, normals = patch(np.asarray(centre, float) + shift, np.asarray(normal, float))
        parts.append((points, normals))
        sources += [n] * len(points)
    obs = observations(
        np.concatenate([p for p, _ in parts]), np.concatenate([n for _, n in parts]), source=sources
    )
    field = SignedDistanceGrid.from_probabilities(prior, GRID)
    pose = fit_pose(field, GRID, obs)
    assert pose.x_m == pytest.approx(0.010, abs=0.001)
    assert pose.y_m == pytest.approx(-0.004, abs=0.001)
    assert abs(np.degrees(pose.yaw_rad)) < 2.0 and abs(pose.log_scale) < 0.02
    moved = field.moved_to(posed_grid(GRID, pose))
    assert np.abs(moved(obs.surface_points_world)).max() < 1e-3


def test_the_surface_is_closed_outward_and_cut_by_the_table(prior: np.ndarray) -> None:
    mesh = FusedShape.from_prior(prior, GRID).mesh()
    assert mesh.is_watertight and mesh.volume > 0
    assert mesh.bounds[0, 2] >= -1e-9
    assert mesh.volume == pytest.approx(0.08 * 0.06 * 0.10, rel=0.12)


def test_observations_from_a_touch_and_back_from_disk(tmp_path) -> None:
    contacts, _ = patch(np.array([0.04, 0.0, 0.05]), np.array([1.0, 0.0, 0.0]), step_m=0.0002)
    direction = np.array([-1.0, 0.0, 0.0])
    touch = TouchResult.from_contact(contacts, direction, np.array([0.08, 0.0, 0.05]))
    obs = SurfaceObservations.from_touch(touch, source=3)
    assert 40 < len(obs.surface_points_world) < len(contacts)
    assert np.allclose(obs.surface_normals_world, [1.0, 0.0, 0.0], atol=1e-6)
    assert (obs.free_points_world[:, 0] > 0.04).all()  # in front of the contact
    assert (obs.surface_source == 3).all()
    path = obs.save(tmp_path / "observations.npz")
    back = SurfaceObservations.load(path)
    assert np.allclose(back.surface_points_world, obs.surface_points_world, atol=1e-7)
    path.write_bytes(b"not a zip")
    with pytest.raises(ObservationsError, match=r"observations\.npz"):
        SurfaceObservations.load(path)
    with pytest.raises(ValueError, match="NaN"):
        SurfaceObservations(contacts * np.nan, contacts, np.zeros((0, 3)), np.zeros(len(contacts)))


def test_extending_the_kernel_factor_by_free_points_equals_factoring_them_all() -> None:
    """A round of free points extends the Cholesky factor by their rows: the same factor, and
    the same weights, as factoring the grown kernel matrix."""
    rng = np.random.default_rng(0)
    settings = FusionSettings()
    points, free = rng.uniform(-0.03, 0.03, (60, 3)), rng.uniform(-0.03, 0.03, (15, 3))
    noise = np.full(60, settings.surface_noise_m)
    free_noise = np.full(15, settings.free_noise_m)
    extended = _GramFactor.of(points, noise, settings).extended(free, free_noise, settings)
    direct = _GramFactor.of(
        np.concatenate([points, free]), np.concatenate([noise, free_noise]), settings
    )
    np.testing.assert_allclose(np.tril(extended.lower), np.tril(direct.lower), atol=1e-12)
    residuals = rng.normal(0.0, 0.002, 75)
    np.testing.assert_allclose(extended.solve(residuals), direct.solve(residuals), rtol=1e-8)


def test_the_inside_distance_on_the_objects_box_equals_the_whole_grids() -> None:
    """The prior's inside distances are computed on the inside voxels' box grown by one: the
    same numbers as the whole grid's transform, also where the object meets the grid's faces."""
    rng = np.random.default_rng(0)
    for trial in range(60):
        inside = np.zeros((24, 24, 24), dtype=bool)
        low = rng.integers(0, 12, 3)
        high = low + rng.integers(1, 13, 3)
        inside[tuple(slice(lo, hi) for lo, hi in zip(low, high, strict=True))] = True
        inside &= rng.random(inside.shape) < 0.9  # holes: outside voxels inside the box
        if trial % 3 == 0:
            inside[:, :, :2] = True  # on the grid's face
        if not inside.any() or inside.all():
            continue
        np.testing.assert_array_equal(_inside_distance(inside), distance_transform_edt(inside))


def test_thinning_keeps_the_first_point_of_every_cell() -> None:
    rng = np.random.default_rng(1)
    points = rng.normal(0.0, 0.02, (500, 3)) + np.array([0.3, -0.2, 0.1])
    spacing = 0.004
    keep = thin_to_lattice(points, spacing)
    cells = [tuple(c) for c in np.floor(points / spacing).astype(int)]
    first = {}
    for index, cell in enumerate(cells):
        first.setdefault(cell, index)
    np.testing.assert_array_equal(keep, sorted(first.values()))
