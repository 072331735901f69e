"""Tests for models.render: rendered geometry against closed-form ray intersections."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from models.camera import CameraIntrinsics, look_at_pose
from models.render import (
    DirectionalLight,
    Lighting,
    Scene,
    SceneObject,
    apply_kinect_depth_noise,
    make_table,
    render,
)

# A 320x240 camera with a 60 deg horizontal field of view keeps each render to a few ms.
INTRINSICS = CameraIntrinsics(320, 240, 277.0, 277.0, 159.5, 119.5)

SPHERE_RADIUS_M = 0.05
SPHERE_CENTRE = np.array([0.03, -0.02, 0.3])
_ICOSPHERE = trimesh.creation.icosphere(subdivisions=5, radius=SPHERE_RADIUS_M)
# How far the flat facets sink inside the true sphere (its vertices lie on it): the radius minus
# the smallest centre-to-facet-plane distance: 14 um here (2.8e-4 r).
TESSELLATION_SAG_M = SPHERE_RADIUS_M - float(
    np.min(np.einsum("ij,ij->i", _ICOSPHERE.face_normals, _ICOSPHERE.triangles[:, 0]))
)


def camera_rays_world(intrinsics: CameraIntrinsics, pose: np.ndarray) -> np.ndarray:
    """(H, W, 3) world-frame ray directions scaled to unit z in the camera frame.

    With that scaling the ray parameter t of a hit is directly its z-depth.
    """
    u, v = np.meshgrid(np.arange(intrinsics.width), np.arange(intrinsics.height))
    rays = np.stack(
        [
            (u - intrinsics.cx) / intrinsics.fx,
            (v - intrinsics.cy) / intrinsics.fy,
            np.ones(u.shape),
        ],
        axis=-1,
    )
    return rays @ pose[:3, :3].T


def project(intrinsics: CameraIntrinsics, pose: np.ndarray, point_world) -> tuple[int, int]:
    """(row, col) of the pixel that sees a world point."""
    p = pose[:3, :3].T @ (np.asarray(point_world) - pose[:3, 3])
    return (
        round(intrinsics.fy * p[1] / p[2] + intrinsics.cy),
        round(intrinsics.fx * p[0] / p[2] + intrinsics.cx),
    )


def sphere_scene(*, with_table: bool = False) -> Scene:
    mesh = _ICOSPHERE.copy()
    mesh.apply_translation(SPHERE_CENTRE)
    return Scene([SceneObject(mesh, (0.8, 0.2, 0.2))], make_table() if with_table else None)


@pytest.fixture(scope="module")
def sphere_render():
    """The sphere seen obliquely from 0.45 m, and the analytic per-pixel ray-sphere solution."""
    pose = look_at_pose((-0.3, -0.25, 0.55), SPHERE_CENTRE)
    out = render(sphere_scene(), INTRINSICS, pose)
    d = camera_rays_world(INTRINSICS, pose)
    oc = pose[:3, 3] - SPHERE_CENTRE
    a = np.sum(d * d, axis=-1)
    b = 2.0 * d @ oc
    c = oc @ oc - SPHERE_RADIUS_M**2
    disc = b * b - 4 * a * c
    depth = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), 0.0)
    # Perpendicular distance from the sphere centre to each pixel's ray.
    d_unit = d / np.sqrt(a)[..., None]
    along = -(d_unit @ oc)
    miss_distance = np.sqrt(np.maximum(oc @ oc - along**2, 0.0))
    return out, pose, depth, miss_distance, along


def test_sphere_depth_matches_analytic(sphere_render):
    out, _, depth, miss_distance, _ = sphere_render
    inner = miss_distance < 0.9 * SPHERE_RADIUS_M  # incidence below ~64 deg
    assert inner.sum() > 2000
    error = np.abs(out.depth_m[inner] - depth[inner])
    # A flat facet lies at most the sag inside the sphere, so along a ray at incidence theta the
    # depth error is at most sag / cos(theta) < 2.3 sag = 33 um here (float32 output adds < 1 um).
    assert 1e-6 < TESSELLATION_SAG_M < 2e-5
    assert error.max() < 2.3 * TESSELLATION_SAG_M + 1e-6
    both = out.hit_mask & (depth > 0)
    # Towards the rim the facets' sag is seen edge-on; still far below a millimetre.
    assert np.abs(out.depth_m[both] - depth[both]).max() < 1e-3


def test_sphere_silhouette_is_projected_disk(sphere_render):
    out, _, _, miss_distance, along = sphere_render
    analytic = miss_distance < SPHERE_RADIUS_M
    assert out.silhouette.sum() > 2000
    mismatch = out.silhouette != analytic
    # One pixel's footprint at the sphere plus the tessellation sag bounds the disagreement.
    pixel_m = along / INTRINSICS.fx
    rim_band = np.abs(miss_distance - SPHERE_RADIUS_M) < pixel_m + TESSELLATION_SAG_M
    assert not np.any(mismatch & ~rim_band)
    assert np.array_equal(out.silhouette, out.hit_mask)  # no table in this scene


def test_sphere_normals_are_radial(sphere_render):
    out, pose, _, miss_distance, _ = sphere_render
    inner = miss_distance < 0.95 * SPHERE_RADIUS_M
    u, v = np.meshgrid(np.arange(INTRINSICS.width), np.arange(INTRINSICS.height))
    rays = np.stack([(u - INTRINSICS.cx) / INTRINSICS.fx, (v - INTRINSICS.cy) / INTRINSICS.fy], -1)
    points = np.concatenate([rays, np.ones((*rays.shape[:2], 1))], -1) * out.depth_m[..., None]
    centre_camera = pose[:3, :3].T @ (SPHERE_CENTRE - pose[:3, 3])
    radial = (points - centre_camera)[inner]
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    normals = out.normals_camera[inner]
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    angle = np.degrees(np.arccos(np.clip(np.sum(normals * radial, axis=1), -1.0, 1.0)))
    # Vertex-normal interpolation is far better than the ~1.2 deg of a flat facet.
    assert np.median(angle) < 0.1
    assert angle.max() < 0.5
    assert np.all(out.normals_camera[~out.hit_mask] == 0.0)


@pytest.mark.parametrize(
    ("axis", "sign"), [(2, 1.0), (0, 1.0), (1, -1.0)], ids=["top", "+x side", "-y side"]
)
def test_box_face_depth_matches_plane(axis: int, sign: float):
    half = np.array([0.05, 0.04, 0.03])
    centre = np.array([0.0, 0.0, 0.03])
    box = trimesh.creation.box(extents=2 * half)
    box.apply_translation(centre)
    pose = look_at_pose((0.3, -0.25, 0.35), centre)
    out = render(Scene([SceneObject(box, (0.3, 0.5, 0.8))]), INTRINSICS, pose)

    d = camera_rays_world(INTRINSICS, pose)
    plane = centre[axis] + sign * half[axis]
    t = (plane - pose[axis, 3]) / d[..., axis]
    hit = pose[:3, 3] + t[..., None] * d
    others = [i for i in range(3) if i != axis]
    # Face interior only, 2 mm clear of its edges; the face is convex and faces the camera.
    inside = np.all(np.abs(hit[..., others] - centre[others]) < half[others] - 0.002, axis=-1)
    assert inside.sum() > 300
    np.testing.assert_allclose(out.depth_m[inside], t[inside], atol=1e-6)
    normal = np.zeros(3)
    normal[axis] = sign
    expected_normal = pose[:3, :3].T @ normal
    np.testing.assert_allclose(
        out.normals_camera[inside], np.tile(expected_normal, (inside.sum(), 1)), atol=1e-6
    )


def test_table_only_depth_is_plane_intersection():
    scene = Scene(objects=[], table=make_table((1.2, 0.8), thickness_m=0.02))
    pose = look_at_pose((-0.62, 0.1, 0.4572), (0.2, 0.0, 0.0))
    out = render(scene, INTRINSICS, pose)
    assert not out.silhouette.any()

    eye = pose[:3, 3]
    d = camera_rays_world(INTRINSICS, pose)

    def slab_entry(inflate: float) -> np.ndarray:
        """Entry t of each ray into the table box grown by ``inflate`` (inf where missed)."""
        lo = np.array([-0.6, -0.4, -0.02]) - inflate
        hi = np.array([0.6, 0.4, 0.0]) + inflate
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - eye) / d, (hi - eye) / d
        enter = np.minimum(t1, t2).max(axis=-1)
        leave = np.maximum(t1, t2).min(axis=-1)
        return np.where((enter <= leave) & (leave > 0), enter, np.inf)

    exact, shrunk, grown = slab_entry(0.0), slab_entry(-0.001), slab_entry(0.001)
    surely_hit = np.isfinite(shrunk)
    surely_missed = ~np.isfinite(grown)
    assert surely_hit.sum() > 10_000 and surely_missed.sum() > 1000
    assert out.hit_mask[surely_hit].all()
    assert not out.hit_mask[surely_missed].any()
    np.testing.assert_allclose(out.depth_m[surely_hit], exact[surely_hit], atol=2e-6)
    assert np.all(out.depth_m[surely_missed] == 0.0)
    assert np.all(out.colour_rgb[surely_missed] == 255)  # white background


def test_object_shadow_darkens_table():
    """A light from -y at 45 deg elevation throws the sphere's shadow towards +y."""
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=0.05)
    mesh.apply_translation((0.0, 0.0, 0.05))
    albedo = (0.6, 0.6, 0.6)
    scene = Scene.bench(mesh, (0.8, 0.2, 0.2), table_albedo=albedo)
    lighting = Lighting(
        ambient_rgb=(0.3, 0.3, 0.3),
        lights=(DirectionalLight((0.0, -1.0, 1.0), (0.8, 0.8, 0.8)),),
    )
    pose = look_at_pose((-0.62, 0.0, 0.4572), (0.0, 0.0, 0.0))
    out = render(scene, INTRINSICS, pose, lighting=lighting)
    # Shadow of the sphere on z=0: an ellipse centred at y=0.05 reaching y=0.12.
    shadowed = project(INTRINSICS, pose, (0.0, 0.1, 0.0))
    lit = project(INTRINSICS, pose, (0.0, -0.1, 0.0))
    assert out.hit_mask[shadowed] and not out.silhouette[shadowed]
    assert out.hit_mask[lit] and not out.silhouette[lit]
    expected_lit = 255 * 0.6 * (0.3 + 0.8 * math.cos(math.radians(45)))
    np.testing.assert_allclose(out.colour_rgb[lit], expected_lit, atol=1.0)
    np.testing.assert_allclose(out.colour_rgb[shadowed], 255 * 0.6 * 0.3, atol=1.0)


def test_transparent_objects_return_no_depth():
    scene = sphere_scene(with_table=True)
    pose = look_at_pose((-0.2, -0.3, 0.8), SPHERE_CENTRE)
    opaque = render(scene, INTRINSICS, pose)
    glass = render(scene, INTRINSICS, pose, transparent_objects=True)
    assert opaque.silhouette.sum() > 1000
    np.testing.assert_array_equal(glass.silhouette, opaque.silhouette)
    np.testing.assert_array_equal(glass.hit_mask, opaque.hit_mask)
    assert np.all(glass.depth_m[glass.silhouette] == 0.0)
    # The table keeps its depth, also where the sphere hovers over it and would shadow it.
    np.testing.assert_array_equal(
        glass.depth_m[~glass.silhouette], opaque.depth_m[~glass.silhouette]
    )
    # The object still shows, faintly: neither its opaque shading nor the table behind it.
    sphere_colour = glass.colour_rgb[glass.silhouette].astype(float).mean(axis=0)
    assert np.abs(sphere_colour - opaque.colour_rgb[opaque.silhouette].mean(axis=0)).max() > 20
    table_only = render(Scene([], make_table()), INTRINSICS, pose)
    behind = table_only.colour_rgb[glass.silhouette].astype(float).mean(axis=0)
    assert np.abs(sphere_colour - behind).max() > 10


def test_backgrounds_differ_and_are_deterministic():
    # Looking straight up from above the table: nothing in view.
    pose = look_at_pose((0.0, 0.0, 0.5), (0.0, 0.0, 1.5), up_world=(1.0, 0.0, 0.0))
    scene = sphere_scene(with_table=True)
    white = render(scene, INTRINSICS, pose).colour_rgb
    assert np.all(white == 255)
    images = {}
    for kind in ("gradient", "texture"):
        first = render(scene, INTRINSICS, pose, background=kind, rng=np.random.default_rng(7))
        again = render(scene, INTRINSICS, pose, background=kind, rng=np.random.default_rng(7))
        other = render(scene, INTRINSICS, pose, background=kind, rng=np.random.default_rng(8))
        assert not first.hit_mask.any()
        np.testing.assert_array_equal(first.colour_rgb, again.colour_rgb)
        assert np.abs(first.colour_rgb.astype(int) - other.colour_rgb).mean() > 5
        assert first.colour_rgb.std() > 3  # not flat
        images[kind] = first.colour_rgb.astype(int)
    assert np.abs(images["gradient"] - white).mean() > 5
    assert np.abs(images["texture"] - white).mean() > 5
    assert np.abs(images["gradient"] - images["texture"]).mean() > 5
    # Texture is busier than the smooth gradient.
    roughness = {k: np.abs(np.diff(im, axis=1)).mean() for k, im in images.items()}
    assert roughness["texture"] > 2 * roughness["gradient"]

    given = np.random.default_rng(0).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    np.testing.assert_array_equal(
        render(scene, INTRINSICS, pose, background=given).colour_rgb, given
    )
    with pytest.raises(ValueError, match="rng"):
        render(scene, INTRINSICS, pose, background="texture")


def test_random_lighting_is_seeded_and_coloured():
    a = Lighting.random(np.random.default_rng(3))
    assert a == Lighting.random(np.random.default_rng(3))
    assert 1 <= len(a.lights) <= 2
    for light in a.lights:
        assert light.direction_world[2] > 0.3  # from above the table
    colours = [Lighting.random(np.random.default_rng(s)).ambient_rgb for s in range(10)]
    assert max(np.ptp(c) for c in colours) > 0.05  # tinted, not grey


def test_intersector_is_built_once():
    scene = sphere_scene(with_table=True)
    scene.build()
    built = scene._geometry
    pose = look_at_pose((-0.5, 0.0, 0.5), (0.0, 0.0, 0.0))
    render(scene, INTRINSICS, pose)
    render(scene, INTRINSICS, pose)
    assert scene._geometry is built


def test_texture_modulates_albedo():
    checker = np.zeros((2, 2, 3))
    checker[0, 0] = checker[1, 1] = 1.0
    table = make_table(texture=checker)
    pose = look_at_pose((0.0, 0.0, 0.5), (0.0, 0.0, 0.0), up_world=(1.0, 0.0, 0.0))
    out = render(Scene([], table), INTRINSICS, pose, lighting=Lighting((1.0, 1.0, 1.0), ()))
    values = np.unique(out.colour_rgb[out.hit_mask][:, 0])
    # Dark and albedo-bright squares only (and nothing in between: nearest-texel sampling).
    assert set(values.tolist()) == {0, round(255 * 0.62)}


def test_intrinsics_and_look_at():
    colour = CameraIntrinsics.kinect_v2_colour(0.5)
    assert (colour.width, colour.height, colour.cx, colour.cy) == (960, 540, 479.5, 269.5)
    assert colour.fx == pytest.approx(540.685)
    np.testing.assert_allclose(colour.matrix, [[540.685, 0, 479.5], [0, 540.685, 269.5], [0, 0, 1]])
    assert CameraIntrinsics.kinect_v2_depth().width == 512

    pose = look_at_pose((-0.62, 0.0, 0.4572), (0.0, 0.0, 0.0))
    rotation = pose[:3, :3]
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    forward = -pose[:3, 3] / np.linalg.norm(pose[:3, 3])
    np.testing.assert_allclose(rotation[:, 2], forward)
    assert rotation[2, 0] == pytest.approx(0.0)  # image x stays horizontal
    assert rotation[2, 1] < 0.0  # image y points down in the world
    assert project(INTRINSICS, pose, (0.0, 0.0, 0.0)) == (120, 160)
    with pytest.raises(ValueError, match="parallel"):
        look_at_pose((0.0, 0.0, 1.0), (0.0, 0.0, 0.0))


# --- Kinect v2 depth noise --------------------------------------------------------------------


def frontal_plane(depth_m: float, shape=(200, 200)) -> tuple[np.ndarray, np.ndarray]:
    depth = np.full(shape, depth_m, dtype=np.float32)
    normals = np.zeros((*shape, 3), dtype=np.float32)
    normals[..., 2] = -1.0
    return depth, normals


def test_noise_is_zero_mean_with_kinect_sigma_at_0_6_m(rng):
    depth, normals = frontal_plane(0.6)
    noisy = apply_kinect_depth_noise(depth, normals, rng)
    assert noisy.dtype == np.float32 and np.all(noisy > 0)
    error = noisy.astype(np.float64) - 0.6
    expected_sigma = 0.0015 - 0.0005 * 0.6 + 0.0003 * 0.36  # 1.31 mm, face-on
    assert error.std() == pytest.approx(expected_sigma, rel=0.03)
    assert 0.001 < error.std() < 0.002  # Kinect v2 axial noise at close range is 1-2 mm
    assert abs(error.mean()) < 4 * expected_sigma / math.sqrt(error.size)


def test_noise_grows_with_incidence_and_drops_out_at_grazing(rng):
    depth, _ = frontal_plane(0.6)
    for degrees in (75.0, 85.0):
        theta = math.radians(degrees)
        normals = np.zeros((*depth.shape, 3))
        normals[..., 1] = math.sin(theta)
        normals[..., 2] = -math.cos(theta)
        noisy = apply_kinect_depth_noise(depth, normals, rng)
        if degrees > 80.0:  # beyond max_incidence_deg
            assert np.all(noisy == 0.0)
            continue
        assert np.all(noisy > 0.0)
        # The angle term adds 0.1 mm * 0.6^1.5 * 25 = 1.16 mm to the face-on 1.31 mm.
        expected = 0.0013080 + 0.0001 * 0.6**1.5 * theta**2 / (math.pi / 2 - theta) ** 2
        assert np.std(noisy - 0.6) == pytest.approx(expected, rel=0.03)


def test_noise_keeps_zeros_and_removes_flying_pixels(rng):
    depth, normals = frontal_plane(0.6, shape=(50, 50))
    depth[:, 25:] = 0.9  # a 30 cm depth step between columns 24 and 25
    depth[10:20, 5:10] = 0.0  # no return
    depth[40:, 40:] = 5.0  # beyond the 4.5 m range
    noisy = apply_kinect_depth_noise(depth, normals, rng)
    assert np.all(noisy[10:20, 5:10] == 0.0)
    assert np.all(noisy[40:, 40:] == 0.0)
    assert np.all(noisy[:, 24:26] == 0.0)  # both sides of the edge
    assert np.all(noisy[:, :4] > 0.0) and np.all(noisy[:38, 27:38] > 0.0)
    # A no-return hole is no depth edge: its rim survives.
    assert np.all(noisy[9, 5:10] > 0.0)


def test_noise_uses_true_viewing_rays_with_intrinsics(rng):
    """A table seen straight down: the incidence angle is the off-axis angle of each pixel."""
    pose = look_at_pose((0.0, 0.0, 0.6), (0.0, 0.0, 0.0), up_world=(1.0, 0.0, 0.0))
    out = render(Scene([], make_table()), INTRINSICS, pose)
    assert np.allclose(out.depth_m, 0.6, atol=1e-6)
    noisy = apply_kinect_depth_noise(
        out.depth_m, out.normals_camera, rng, intrinsics=INTRINSICS, max_incidence_deg=20.0
    )
    assert noisy[120, 160] > 0.0
    assert noisy[120, 0] == 0.0  # the middle of the left edge is atan(160 / 277) = 30 deg off axis
    without = apply_kinect_depth_noise(out.depth_m, out.normals_camera, rng, max_incidence_deg=20.0)
    assert np.all(without > 0)  # the optical-axis approximation sees every pixel face-on
