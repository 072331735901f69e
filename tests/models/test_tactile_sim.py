"""GelSight simulation: ray-cast indentation vs analytic caps, elastomer, force, real optics."""

from __future__ import annotations

import math
from importlib.resources import files

import numpy as np
import pytest
import trimesh
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from models.tactile.sim import GelPadSpec, GelSightSimulator, sphere_cap_indentation_mm

SPEC = GelPadSpec()
PX_MM = SPEC.mm_per_px
# A pad pointing down at the table, yawed and away from the world origin, so that the tests
# exercise the pad -> world transform and the pixel <-> pad-frame convention.
POSE_WORLD_PAD = np.eye(4)
POSE_WORLD_PAD[:3, :3] = Rotation.from_euler("xz", [180, 30], degrees=True).as_matrix()
POSE_WORLD_PAD[:3, 3] = [0.42, -0.17, 0.15]
# Contact point on the pad (mm), off-centre, and its pixel (x=col, y=row).
CONTACT_PAD_MM = (1.2, -0.7)
CONTACT_PX = (CONTACT_PAD_MM[0] / PX_MM + 319.5, CONTACT_PAD_MM[1] / PX_MM + 239.5)


@pytest.fixture(scope="module")
def sim() -> GelSightSimulator:
    return GelSightSimulator()


def pad_to_world(points_pad_mm: ArrayLike, pose: np.ndarray = POSE_WORLD_PAD) -> np.ndarray:
    return (np.asarray(points_pad_mm, dtype=float) * 1e-3) @ pose[:3, :3].T + pose[:3, 3]


def sphere_pressed(radius_mm: float, depth_mm: float) -> trimesh.Trimesh:
    """Icosphere pressed ``depth_mm`` past the gel plane at CONTACT_PAD_MM."""
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=radius_mm * 1e-3)
    mesh.apply_translation(pad_to_world([*CONTACT_PAD_MM, radius_mm - depth_mm]))
    return mesh


def box_pressed(depth_mm: float, edge_x_mm: float = 15.0) -> trimesh.Trimesh:
    """30x30x10 mm box, its face ``depth_mm`` past the gel plane and its +x edge at pad x =
    ``edge_x_mm`` (by default beyond the pad, so the face covers all of it)."""
    mesh = trimesh.creation.box(extents=[0.03, 0.03, 0.01])
    transform = POSE_WORLD_PAD.copy()
    transform[:3, 3] = pad_to_world([edge_x_mm - 15.0, 0.0, 5.0 - depth_mm])
    mesh.apply_transform(transform)
    return mesh


def analytic_contact_radius_px(radius_mm: float, depth_mm: float) -> float:
    return math.sqrt(2 * radius_mm * depth_mm - depth_mm**2) / PX_MM


# --- spec ----------------------------------------------------------------------------------------


def test_spec_square_pixels_and_validation() -> None:
    assert SPEC.mm_per_px == pytest.approx(19.0 / 640)
    assert SPEC.shape == (480, 640)
    with pytest.raises(ValueError):
        GelPadSpec(max_indentation_mm=2.5)
    with pytest.raises(ValueError):
        GelPadSpec(height_mm=19.0)


def test_sphere_cap_helper() -> None:
    cap = sphere_cap_indentation_mm(SPEC, (300.0, 200.0), 2.0, 0.5)
    assert cap.dtype == np.float32 and cap.shape == SPEC.shape
    assert cap[200, 300] == pytest.approx(0.5)
    area_radius_px = math.sqrt(np.count_nonzero(cap) / math.pi)
    assert area_radius_px == pytest.approx(analytic_contact_radius_px(2.0, 0.5), abs=0.5)


# --- geometry ------------------------------------------------------------------------------------


@pytest.mark.parametrize("radius_mm", [2.0, 6.0])
def test_ray_cast_sphere_matches_analytic_cap(sim: GelSightSimulator, radius_mm: float) -> None:
    geometric = sim.geometric_indentation_mm(sphere_pressed(radius_mm, 0.5), POSE_WORLD_PAD)
    analytic = sphere_cap_indentation_mm(SPEC, CONTACT_PX, radius_mm, 0.5)
    assert geometric.dtype == np.float32 and geometric.shape == SPEC.shape

    contact = analytic > 0
    rmse = float(np.sqrt(np.mean((geometric[contact] - analytic[contact]) ** 2)))
    assert rmse < 0.01  # measured 0.0009 (R=2) and 0.0014 mm (R=6): icosphere facets
    assert not geometric[~contact].any()
    area_radius_px = math.sqrt(np.count_nonzero(geometric) / math.pi)
    assert abs(area_radius_px - analytic_contact_radius_px(radius_mm, 0.5)) < 2.0


def test_elastic_surface_keeps_peak_and_adds_skirt(sim: GelSightSimulator) -> None:
    geometric = sim.geometric_indentation_mm(sphere_pressed(2.0, 0.5), POSE_WORLD_PAD)
    surface = sim.elastic_deformation_mm(geometric)
    np.testing.assert_array_equal(
        sim.indentation_mm(sphere_pressed(2.0, 0.5), POSE_WORLD_PAD), surface
    )

    # The rigid ball sets the deepest point: the peak is the geometric one (within 1 % of 0.5).
    assert surface.max() == geometric.max()
    assert surface.max() == pytest.approx(0.5, rel=0.01)
    # The gel never passes through the object, and inside the contact it sits on the ball
    # except for a rim where it has already lifted off (Hertz-like; measured <= 0.22 d).
    assert np.all(surface >= geometric)
    contact = geometric > 0
    assert (surface - geometric)[contact].max() < 0.25 * 0.5
    rows, cols = np.indices(SPEC.shape)
    rho_mm = np.hypot(cols - CONTACT_PX[0], rows - CONTACT_PX[1]) * PX_MM
    a_mm = analytic_contact_radius_px(2.0, 0.5) * PX_MM
    # (Up to the icosphere's facet creases, which the smoothing rounds by < 1 um.)
    core = rho_mm < 0.6 * a_mm
    np.testing.assert_allclose(surface[core], geometric[core], atol=1e-3)
    # Outside the contact the gel sinks in a skirt that decays within ~2 sigma.
    assert surface[(rho_mm > a_mm + 0.1) & (rho_mm < a_mm + 0.3)].min() > 0.02
    assert surface[rho_mm > a_mm + 1.0].max() < 0.02 * 0.5


def test_flat_face_over_whole_pad_is_uniform(sim: GelSightSimulator) -> None:
    geometric = sim.geometric_indentation_mm(box_pressed(0.3), POSE_WORLD_PAD)
    np.testing.assert_allclose(geometric, 0.3, atol=1e-4)
    surface = sim.elastic_deformation_mm(geometric)
    np.testing.assert_allclose(surface, 0.3, atol=1e-4)
    # Winkler: E * d / h * area = 0.3 MPa * 0.3 / 2 * (19 x 14.25 mm^2) = 12.2 N.
    area_mm2 = SPEC.image_width_px * SPEC.image_height_px * PX_MM**2
    expected_n = SPEC.youngs_modulus_mpa * 0.3 / SPEC.gel_thickness_mm * area_mm2
    assert sim.contact_force_n(surface) == pytest.approx(expected_n, rel=1e-3)
    assert not sim.bottomed_out(surface)


def test_box_edge_is_pixel_exact(sim: GelSightSimulator) -> None:
    # The box's side wall crosses the pad: rays near it are refined to one per pixel.
    edge_x_mm = 0.31
    geometric = sim.geometric_indentation_mm(box_pressed(0.3, edge_x_mm), POSE_WORLD_PAD)
    x_mm, _ = SPEC.pixel_to_pad_mm(*np.indices(SPEC.shape))
    np.testing.assert_array_equal(geometric > 0, x_mm < edge_x_mm)
    np.testing.assert_allclose(geometric[x_mm < edge_x_mm], 0.3, atol=1e-4)


def test_object_not_touching_gives_zero(sim: GelSightSimulator) -> None:
    indentation = sim.indentation_mm(sphere_pressed(2.0, -0.2), POSE_WORLD_PAD)
    assert not indentation.any()
    assert sim.contact_force_n(indentation) == 0.0


def test_pad_facing_away_gives_zero(sim: GelSightSimulator) -> None:
    # Turned 180 deg about its x axis and moved back 3.5 mm, the pad looks away from the ball,
    # which is now 3 mm behind the gel plane (behind the 2 mm gel and its backing).
    facing_away = POSE_WORLD_PAD.copy()
    flip = Rotation.from_euler("x", 180, degrees=True).as_matrix()
    facing_away[:3, :3] = POSE_WORLD_PAD[:3, :3] @ flip
    facing_away[:3, 3] = pad_to_world([0.0, 0.0, -3.5])
    ball = sphere_pressed(2.0, 0.5)
    assert sim.indentation_mm(ball, POSE_WORLD_PAD).any()
    indentation = sim.indentation_mm(ball, facing_away)
    assert not indentation.any()
    assert sim.contact_force_n(indentation) == 0.0


def test_bottoming_out_on_the_backing(sim: GelSightSimulator) -> None:
    assert not sim.bottomed_out(sim.indentation_mm(sphere_pressed(6.0, 1.4), POSE_WORLD_PAD))
    # 1.8 mm: past the 1.5 mm limit but the rays still start outside the ball.
    deep = sim.indentation_mm(sphere_pressed(6.0, 1.8), POSE_WORLD_PAD)
    assert deep.max() == pytest.approx(SPEC.max_indentation_mm)
    assert sim.bottomed_out(deep)
    # 2.5 mm: the ball reaches through the backing, so rays start inside it.
    through = sim.geometric_indentation_mm(sphere_pressed(6.0, 2.5), POSE_WORLD_PAD)
    assert np.isfinite(through).all()
    assert through.max() == pytest.approx(SPEC.max_indentation_mm)
    assert sim.bottomed_out(through)
    plateau = through == through.max()
    assert math.sqrt(np.count_nonzero(plateau) / math.pi) == pytest.approx(
        analytic_contact_radius_px(6.0, 2.5 - SPEC.max_indentation_mm), abs=2.0
    )


def test_force_monotonic_and_in_range(sim: GelSightSimulator) -> None:
    depths = [0.1, 0.2, 0.4, 0.7, 1.0, 1.3]
    forces = [
        sim.contact_force_n(sim.indentation_mm(sphere_pressed(6.0, d), POSE_WORLD_PAD))
        for d in depths
    ]
    assert np.all(np.diff(forces) > 0)
    ball_n = sim.contact_force_n(sim.indentation_mm(sphere_pressed(2.0, 0.5), POSE_WORLD_PAD))
    assert 0.1 < ball_n < 1.0  # measured 0.29 N
    flat_n = sim.contact_force_n(sim.indentation_mm(box_pressed(0.5), POSE_WORLD_PAD))
    assert 10.0 < flat_n < 50.0  # measured 20.3 N


# --- optics --------------------------------------------------------------------------------------


def test_no_contact_renders_background_plus_noise(sim: GelSightSimulator) -> None:
    image = sim.render_bgr(np.zeros(SPEC.shape, np.float32), np.random.default_rng(0))
    assert image.dtype == np.uint8 and image.shape == (480, 640, 3)
    residual = image.astype(float) - sim.background_bgr()
    assert abs(residual.mean()) < 0.05
    assert residual.std() == pytest.approx(SPEC.noise_sigma, rel=0.1)
    # A uniformly pressed (flat) gel looks like the untouched one.
    flat = sim.render_bgr(np.full(SPEC.shape, 0.3, np.float32), np.random.default_rng(0))
    np.testing.assert_array_equal(flat, image)


def test_render_deterministic_and_contact_visible(sim: GelSightSimulator) -> None:
    indentation = sim.elastic_deformation_mm(sphere_cap_indentation_mm(SPEC, CONTACT_PX, 2.0, 0.5))
    first = sim.render_bgr(indentation, np.random.default_rng(7))
    np.testing.assert_array_equal(first, sim.render_bgr(indentation, np.random.default_rng(7)))
    assert not np.array_equal(first, sim.render_bgr(indentation, np.random.default_rng(8)))

    change = np.abs(first.astype(float) - sim.background_bgr()).mean(axis=2)
    rows, cols = np.indices(SPEC.shape)
    rho_px = np.hypot(cols - CONTACT_PX[0], rows - CONTACT_PX[1])
    contact_px = analytic_contact_radius_px(2.0, 0.5)
    assert change[rho_px < contact_px].mean() > 8.0
    assert change[rho_px > contact_px + 60].mean() < 1.5 * SPEC.noise_sigma


@pytest.mark.parametrize("press", [0, 10, 20, 40])
def test_render_matches_real_ball_press(sim: GelSightSimulator, press: int) -> None:
    """A 2 mm ball rendered where Taxim's dataPack annotates a real press looks like it.

    Depth from the annotated radius r: R - sqrt(R^2 - r^2). Measured mean absolute error inside
    the circle vs the real frame's own change from f0: 4.2/25.8, 7.4/23.7, 4.8/25.4, 7.1/23.9.
    """
    data_pack = files("taxim") / "calib" / "gelsight" / "dataPack.npz"
    with data_pack.open("rb") as file, np.load(file) as pack:
        real = pack["imgs"][press].astype(float)
        centre = tuple(pack["touch_center"][press])
        radius_px = float(pack["touch_radius"][press])
    ball_mm = 2.0
    depth = ball_mm - math.sqrt(ball_mm**2 - (radius_px * PX_MM) ** 2)
    indentation = sim.elastic_deformation_mm(
        sphere_cap_indentation_mm(SPEC, centre, ball_mm, depth)
    )
    rendered = sim.render_bgr(indentation, np.random.default_rng(press)).astype(float)

    rows, cols = np.indices(SPEC.shape)
    inside = np.hypot(cols - centre[0], rows - centre[1]) < radius_px
    real_signal = np.abs(real - sim.background_bgr())[inside].mean()
    error = np.abs(rendered - real)[inside].mean()
    assert real_signal > 15.0
    assert error < 0.5 * real_signal
