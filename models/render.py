"""The project's one renderer: an Embree ray caster for the simulated Kinect v2 and training data.

Frames and units: the world frame is z-up in metres with the table top in the plane z = 0. The
camera frame is OpenCV's (x right, y down, z forward) and ``pose_world_camera`` is the 4x4
homogeneous transform taking camera-frame points to the world frame. Pixel centres sit at integer
pixel coordinates (OpenCV convention), so the centre of a W-pixel-wide image is at u = (W - 1) / 2.

One primary ray per pixel centre is cast through the pinhole model against a single BVH holding
every scene element (built once per :class:`Scene`, then reused for every frame). Hits are shaded
Lambertian with ambient light plus directional lights, each with a shadow ray, so objects cast
shadows on the table. Alongside colour the renderer returns ground-truth z-depth, camera-frame
normals and the object silhouette; :func:`apply_kinect_depth_noise` turns the depth into a
plausible Kinect v2 time-of-flight measurement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Literal

import numpy as np
import trimesh
from scipy import ndimage
from trimesh.ray.ray_pyembree import RayMeshIntersector

from models.camera import CameraIntrinsics

# A shadow ray starts this far off the surface along its normal so that it cannot re-hit the
# triangle it leaves: Embree works in float32, and 0.1 mm is far above its rounding error at
# table scale yet far below anything the 1-2 mm depth noise of the Kinect could resolve.
_SHADOW_RAY_OFFSET_M = 1e-4

# Corner normals deviating more than this from their face normal mark a crease (the edges of a
# box): such corners shade flat instead of being smoothed across the edge.
_CREASE_ANGLE_DEG = 30.0

# How much of a transparent object's own shading shows over what lies behind it.
_GLASS_OPACITY = 0.3

_TABLE_ALBEDO = (0.62, 0.55, 0.47)

BackgroundSpec = Literal["white", "gradient", "texture"] | np.ndarray


@dataclass
class SceneObject:
    """One scene element: a world-frame triangle mesh and its surface appearance.

    ``albedo_rgb`` is the diffuse reflectance in 0..1. ``texture``, an (H, W, 3) float image in
    0..1, multiplies the albedo; it is projected triplanarly in world coordinates with one copy of
    the image covering ``texture_tile_m`` metres. ``is_object`` marks elements that count towards
    the silhouette (the table does not).
    """

    mesh: trimesh.Trimesh
    albedo_rgb: tuple[float, float, float] = (0.7, 0.7, 0.7)
    texture: np.ndarray | None = None
    is_object: bool = True
    texture_tile_m: float = 0.1


def make_table(
    size_m: tuple[float, float] = (1.2, 0.8),
    centre_xy_m: tuple[float, float] = (0.0, 0.0),
    *,
    thickness_m: float = 0.02,
    albedo_rgb: tuple[float, float, float] = _TABLE_ALBEDO,
    texture: np.ndarray | None = None,
) -> SceneObject:
    """The table: a thin box of ``size_m`` (x, y) centred at ``centre_xy_m`` with its top at z=0."""
    box = trimesh.creation.box(extents=(size_m[0], size_m[1], thickness_m))
    box.apply_translation((centre_xy_m[0], centre_xy_m[1], -0.5 * thickness_m))
    return SceneObject(mesh=box, albedo_rgb=albedo_rgb, texture=texture, is_object=False)


@dataclass
class _Hits:
    """First hits of a batch of rays (M hits), all world frame."""

    ray: np.ndarray  # (M,) index of the ray that hit
    location: np.ndarray  # (M, 3) hit point, metres
    element: np.ndarray  # (M,) index into Scene.elements
    geometric_normal: np.ndarray  # (M, 3) unit face normal, turned towards the ray origin
    shading_normal: np.ndarray  # (M, 3) unit interpolated normal, same side as geometric_normal


class _Geometry:
    """Some scene elements concatenated into one mesh with a built Embree BVH."""

    def __init__(self, meshes: list[trimesh.Trimesh], element_ids: list[int]) -> None:
        offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        combined = trimesh.Trimesh(
            vertices=np.concatenate([m.vertices for m in meshes]),
            faces=np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)]),
            # Processing could merge or drop faces and break the face -> element mapping.
            process=False,
        )
        self.face_element = np.repeat(element_ids, [len(m.faces) for m in meshes])
        self.triangles = combined.triangles
        self.face_normals = combined.face_normals
        self.corner_normals = np.concatenate([_corner_normals(m) for m in meshes])
        # Faces whose corner normals all equal the face normal (the table, box sides) shade flat,
        # which spares them the barycentric interpolation: most pixels usually see the table.
        self.curved_face = np.any(self.corner_normals != self.face_normals[:, None, :], axis=(1, 2))
        self.intersector = RayMeshIntersector(combined)
        # One throwaway query builds the BVH now, so that no frame pays for it.
        self.intersector.intersects_any(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))

    def first_hits(self, origins: np.ndarray, directions: np.ndarray) -> _Hits:
        """First hit of each ray (origins and unit directions (N, 3), world frame)."""
        tri, ray, location = self.intersector.intersects_id(
            origins, directions, multiple_hits=False, return_locations=True
        )
        geometric = self.face_normals[tri]
        flip = np.where(np.einsum("ij,ij->i", geometric, directions[ray]) > 0.0, -1.0, 1.0)[:, None]
        shading = geometric.copy()
        curved = self.curved_face[tri]
        barycentric = trimesh.triangles.points_to_barycentric(
            self.triangles[tri[curved]], location[curved]
        )
        smooth = np.einsum("ij,ijk->ik", barycentric, self.corner_normals[tri[curved]])
        shading[curved] = smooth / np.linalg.norm(smooth, axis=1, keepdims=True)
        return _Hits(ray, location, self.face_element[tri], geometric * flip, shading * flip)


def _corner_normals(mesh: trimesh.Trimesh) -> np.ndarray:
    """(F, 3, 3) per-corner normals: smooth vertex normals except at creases, where flat."""
    face_normals = mesh.face_normals
    corners = mesh.vertex_normals[mesh.faces]
    smooth = np.einsum("fcj,fj->fc", corners, face_normals) >= math.cos(
        math.radians(_CREASE_ANGLE_DEG)
    )
    return np.where(smooth[..., None], corners, face_normals[:, None, :])


@dataclass
class Scene:
    """Scene elements in the world frame: the objects and an optional table.

    The ray-casting BVH is built on first use (or by :meth:`build`) and cached, so a scene must
    not be changed once rendered; make a new one for a new object pose.
    """

    objects: list[SceneObject]
    table: SceneObject | None = None

    @classmethod
    def bench(
        cls,
        object_mesh: trimesh.Trimesh,
        albedo_rgb: tuple[float, float, float],
        table_size_m: tuple[float, float] = (1.2, 0.8),
        table_albedo: tuple[float, float, float] = _TABLE_ALBEDO,
    ) -> Scene:
        """One object (already placed in the world frame) on a table centred at the origin."""
        return cls(
            objects=[SceneObject(mesh=object_mesh, albedo_rgb=albedo_rgb)],
            table=make_table(table_size_m, albedo_rgb=table_albedo),
        )

    @property
    def elements(self) -> list[SceneObject]:
        """All elements, objects first then the table; hit element ids index this list."""
        return [*self.objects, *([self.table] if self.table is not None else [])]

    def build(self) -> None:
        """Build the ray-casting structures now rather than during the first render."""
        _ = self._geometry

    @cached_property
    def _geometry(self) -> _Geometry:
        elements = self.elements
        if not elements:
            raise ValueError("cannot render an empty scene")
        return _Geometry([e.mesh for e in elements], list(range(len(elements))))

    @cached_property
    def _see_through_geometry(self) -> _Geometry | None:
        """Only the non-object elements: what a ray passing through transparent objects can hit."""
        ids = [i for i, e in enumerate(self.elements) if not e.is_object]
        if not ids:
            return None
        return _Geometry([self.elements[i].mesh for i in ids], ids)


@dataclass(frozen=True)
class DirectionalLight:
    """A light at infinity: ``direction_world`` points from the scene towards the light.

    ``colour_rgb`` is the irradiance on a surface facing the light, relative to the one that shows
    a surface at exactly its albedo.
    """

    direction_world: tuple[float, float, float]
    colour_rgb: tuple[float, float, float]


@dataclass(frozen=True)
class Lighting:
    """Ambient light (reaches every surface, unshadowed) plus directional lights."""

    ambient_rgb: tuple[float, float, float]
    lights: tuple[DirectionalLight, ...]

    @classmethod
    def default(cls) -> Lighting:
        """Neutral white light: ambient plus a key light above and behind a camera on -x."""
        return cls(
            ambient_rgb=(0.35, 0.35, 0.35),
            lights=(DirectionalLight((-0.5, 0.35, 1.0), (0.7, 0.7, 0.7)),),
        )

    @classmethod
    def random(cls, rng: np.random.Generator) -> Lighting:
        """Random coloured illumination for data augmentation: one or two lights, 20-80 deg up."""
        count = int(rng.integers(1, 3))
        ambient = rng.uniform(0.15, 0.4) * _random_tint(rng)
        lights = []
        for _ in range(count):
            azimuth = rng.uniform(0.0, 2.0 * math.pi)
            elevation = math.radians(rng.uniform(20.0, 80.0))
            direction = (
                math.cos(elevation) * math.cos(azimuth),
                math.cos(elevation) * math.sin(azimuth),
                math.sin(elevation),
            )
            colour = rng.uniform(0.5, 0.9) / count * _random_tint(rng)
            lights.append(DirectionalLight(direction, tuple(colour.tolist())))
        return cls(ambient_rgb=tuple(ambient.tolist()), lights=tuple(lights))


def _random_tint(rng: np.random.Generator) -> np.ndarray:
    """A random RGB tint with mean 1 and saturation up to about 50 %."""
    tint = 1.0 + rng.uniform(0.0, 0.5) * rng.uniform(-1.0, 1.0, 3)
    return tint / tint.mean()


_DEFAULT_LIGHTING = Lighting.default()


@dataclass
class RenderOutput:
    """One rendered frame; H x W is the intrinsics' image size.

    ``depth_m`` is z-depth along the optical axis (not range along the ray), 0 where no return.
    ``normals_camera`` are unit normals in the camera frame turned towards the camera, 0 where no
    hit. ``silhouette`` marks pixels whose first hit is an ``is_object`` element and ``hit_mask``
    pixels that hit anything.
    """

    colour_rgb: np.ndarray  # (H, W, 3) uint8
    depth_m: np.ndarray  # (H, W) float32
    normals_camera: np.ndarray  # (H, W, 3) float32
    silhouette: np.ndarray  # (H, W) bool
    hit_mask: np.ndarray  # (H, W) bool


def render(
    scene: Scene,
    intrinsics: CameraIntrinsics,
    pose_world_camera: np.ndarray,
    *,
    lighting: Lighting = _DEFAULT_LIGHTING,
    background: BackgroundSpec = "white",
    rng: np.random.Generator | None = None,
    transparent_objects: bool = False,
) -> RenderOutput:
    """Ray-cast one frame of ``scene`` seen by a pinhole camera at ``pose_world_camera``.

    ``background`` fills pixels that hit nothing: "white", "gradient" (a smooth lit gradient
    between random colours), "texture" (random sinusoids and blobs) or an (H, W, 3) uint8 image.
    The random backgrounds are drawn from ``rng``, which they require.

    With ``transparent_objects`` the objects model glass that a time-of-flight camera cannot see:
    they return no depth (0 in ``depth_m``) and show only faintly over what lies behind them in
    the colour image, while normals, silhouette and hit mask still describe the object itself.
    """
    height, width = intrinsics.height, intrinsics.width
    rotation = np.asarray(pose_world_camera, dtype=np.float64)[:3, :3]
    eye = np.asarray(pose_world_camera, dtype=np.float64)[:3, 3]
    directions = _pixel_rays(intrinsics) @ rotation.T  # unit length: rotation keeps norms
    origins = np.broadcast_to(eye, directions.shape)

    elements = scene.elements
    is_object = np.array([e.is_object for e in elements])
    hits = scene._geometry.first_hits(origins, directions)
    on_object = is_object[hits.element]

    colour = _background(background, intrinsics, rng).reshape(-1, 3)
    background_colour = colour[hits.ray]
    # Glass lets the light through, so transparent objects cast no shadows either.
    occluders = scene._see_through_geometry if transparent_objects else scene._geometry
    colour[hits.ray] = _shade(scene, hits, lighting, occluders)
    depth = np.zeros(height * width)
    depth[hits.ray] = (hits.location - eye) @ rotation[:, 2]

    if transparent_objects and on_object.any():
        glass_rays = hits.ray[on_object]
        depth[glass_rays] = 0.0
        behind = background_colour[on_object]
        see_through = scene._see_through_geometry
        if see_through is not None:
            far = see_through.first_hits(origins[glass_rays], directions[glass_rays])
            behind[far.ray] = _shade(scene, far, lighting, occluders)
        colour[glass_rays] = _GLASS_OPACITY * colour[glass_rays] + (1 - _GLASS_OPACITY) * behind

    normals = np.zeros((height * width, 3))
    normals[hits.ray] = hits.shading_normal @ rotation  # world -> camera: R^T n, row-vector form
    silhouette = np.zeros(height * width, dtype=bool)
    silhouette[hits.ray[on_object]] = True
    hit_mask = np.zeros(height * width, dtype=bool)
    hit_mask[hits.ray] = True

    colour_rgb = np.clip(colour * 255.0 + 0.5, 0.0, 255.0).astype(np.uint8)
    return RenderOutput(
        colour_rgb=colour_rgb.reshape(height, width, 3),
        depth_m=depth.astype(np.float32).reshape(height, width),
        normals_camera=normals.astype(np.float32).reshape(height, width, 3),
        silhouette=silhouette.reshape(height, width),
        hit_mask=hit_mask.reshape(height, width),
    )


@lru_cache(maxsize=8)
def _pixel_rays(intrinsics: CameraIntrinsics) -> np.ndarray:
    """(H*W, 3) unit camera-frame rays through the pixel centres, row-major. Read-only."""
    u, v = np.meshgrid(np.arange(intrinsics.width), np.arange(intrinsics.height))
    rays = np.stack(
        [
            (u.ravel() - intrinsics.cx) / intrinsics.fx,
            (v.ravel() - intrinsics.cy) / intrinsics.fy,
            np.ones(u.size),
        ],
        axis=1,
    )
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    rays.flags.writeable = False  # shared between calls through the cache
    return rays


def _shade(
    scene: Scene, hits: _Hits, lighting: Lighting, occluders: _Geometry | None
) -> np.ndarray:
    """(M, 3) Lambertian colour (0..1, may exceed 1) of hit points, shadowed by ``occluders``."""
    elements = scene.elements
    albedo = np.array([e.albedo_rgb for e in elements], dtype=np.float64)[hits.element]
    for index, element in enumerate(elements):
        if element.texture is None:
            continue
        mine = hits.element == index
        albedo[mine] *= _triplanar(
            element.texture,
            hits.location[mine],
            hits.geometric_normal[mine],
            element.texture_tile_m,
        )

    irradiance = np.tile(np.asarray(lighting.ambient_rgb, dtype=np.float64), (len(hits.ray), 1))
    shadow_origins = hits.location + _SHADOW_RAY_OFFSET_M * hits.geometric_normal
    for light in lighting.lights:
        towards = np.asarray(light.direction_world, dtype=np.float64)
        towards /= np.linalg.norm(towards)
        cosine = np.clip(hits.shading_normal @ towards, 0.0, None)
        # Only surfaces facing the light can be lit; only those need a shadow ray.
        lit = np.flatnonzero((hits.geometric_normal @ towards > 0.0) & (cosine > 0.0))
        if occluders is not None:
            blocked = occluders.intersector.intersects_any(
                shadow_origins[lit], np.broadcast_to(towards, (len(lit), 3))
            )
            lit = lit[~blocked]
        irradiance[lit] += cosine[lit, None] * np.asarray(light.colour_rgb)
    return albedo * irradiance


def _triplanar(
    texture: np.ndarray, points: np.ndarray, normals: np.ndarray, tile_m: float
) -> np.ndarray:
    """Sample ``texture`` (H, W, 3) at world ``points`` by triplanar projection (nearest texel).

    Each axis-aligned projection is weighted by the normal's component along that axis (to the
    fourth power, to keep the blend zones narrow), so no surface gets a stretched projection.
    """
    texture = np.asarray(texture, dtype=np.float64)
    rows, cols = texture.shape[:2]
    weights = np.abs(normals) ** 4
    weights /= weights.sum(axis=1, keepdims=True)
    sampled = np.zeros((len(points), 3))
    for axis, (a, b) in enumerate(((1, 2), (0, 2), (0, 1))):
        col = np.floor(points[:, a] / tile_m * cols).astype(np.int64) % cols
        row = np.floor(points[:, b] / tile_m * rows).astype(np.int64) % rows
        sampled += weights[:, axis, None] * texture[row, col]
    return sampled


def _background(
    background: BackgroundSpec, intrinsics: CameraIntrinsics, rng: np.random.Generator | None
) -> np.ndarray:
    """(H, W, 3) float64 background image in 0..1 (a fresh, writable array)."""
    shape = (intrinsics.height, intrinsics.width, 3)
    if isinstance(background, np.ndarray):
        if background.shape != shape or background.dtype != np.uint8:
            raise ValueError(f"background image must be uint8 of shape {shape}")
        return background.astype(np.float64) / 255.0
    if background == "white":
        return np.ones(shape)
    if rng is None:
        raise ValueError(f"background={background!r} is random: pass rng")
    if background == "gradient":
        return _gradient_background(intrinsics.width, intrinsics.height, rng)
    if background == "texture":
        return _texture_background(intrinsics.width, intrinsics.height, rng)
    raise ValueError(f"unknown background {background!r}")


def _gradient_background(width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    """A linear blend between two random colours, brightened around a random light spot."""
    start, end = rng.uniform(0.1, 0.95, (2, 3))
    angle = rng.uniform(0.0, 2.0 * math.pi)
    spot_x, spot_y = rng.uniform(0.0, 1.0, 2)
    # Coordinates in units of the longer image side, so the look does not depend on resolution.
    scale = max(width, height)
    x = np.arange(width)[None, :] / scale
    y = np.arange(height)[:, None] / scale
    ramp = math.cos(angle) * x + math.sin(angle) * y
    ramp = (ramp - ramp.min()) / max(float(np.ptp(ramp)), 1e-12)
    spot_distance2 = (x - spot_x * width / scale) ** 2 + (y - spot_y * height / scale) ** 2
    light = 0.7 + 0.3 * np.exp(-spot_distance2 / 0.18)
    return (start + ramp[..., None] * (end - start)) * light[..., None]


def _texture_background(width: int, height: int, rng: np.random.Generator) -> np.ndarray:
    """Random clutter: a palette of three random colours indexed by sinusoids and blobs."""
    scale = max(width, height)
    x = np.arange(width) / scale
    y = np.arange(height) / scale
    # sin(a x + b y + p) = sin(a x + p) cos(b y) + cos(a x + p) sin(b y): two outer products per
    # wave instead of a sine over every pixel keeps the random textures cheap at full resolution.
    stripes = np.zeros((height, width))
    for _ in range(6):
        frequency = 2.0 * math.pi * rng.uniform(2.0, 25.0)
        angle = rng.uniform(0.0, math.pi)
        phase_x = frequency * math.cos(angle) * x + rng.uniform(0.0, 2.0 * math.pi)
        phase_y = frequency * math.sin(angle) * y
        stripes += rng.uniform(0.3, 1.0) * (
            np.outer(np.cos(phase_y), np.sin(phase_x)) + np.outer(np.sin(phase_y), np.cos(phase_x))
        )
    blobs = np.zeros((height, width))
    for _ in range(8):  # Gaussian blobs are separable too.
        centre_x, centre_y = rng.uniform(0.0, 1.0, 2) * (width / scale, height / scale)
        sigma = rng.uniform(0.03, 0.2)
        blobs += rng.choice((-1.0, 1.0)) * np.outer(
            np.exp(-((y - centre_y) ** 2) / (2 * sigma**2)),
            np.exp(-((x - centre_x) ** 2) / (2 * sigma**2)),
        )
    palette = rng.uniform(0.05, 1.0, (3, 3))
    mix_stripes = (stripes - stripes.min()) / max(float(np.ptp(stripes)), 1e-12)
    mix_blobs = 1.0 / (1.0 + np.exp(-4.0 * blobs))
    base = palette[0] + mix_stripes[..., None] * (palette[1] - palette[0])
    return base + mix_blobs[..., None] * (palette[2] - base)


def apply_kinect_depth_noise(
    depth_m: np.ndarray,
    normals_camera: np.ndarray,
    rng: np.random.Generator,
    *,
    intrinsics: CameraIntrinsics | None = None,
    sigma_base_m: float = 0.0015,
    sigma_linear: float = -0.0005,
    sigma_quadratic_per_m: float = 0.0003,
    sigma_incidence_per_sqrt_m: float = 0.0001,
    max_incidence_deg: float = 80.0,
    range_m: tuple[float, float] = (0.5, 4.5),
    flying_pixel_threshold_m: float = 0.03,
) -> np.ndarray:
    """A Kinect v2 (time-of-flight) measurement of a noise-free z-depth image.

    Inputs are a rendered ``depth_m`` (H, W) in metres, 0 = no return, and ``normals_camera``
    (H, W, 3). The incidence angle theta is between the normal and the pixel's viewing ray; pass
    ``intrinsics`` for exact rays, otherwise the optical axis stands in for every pixel (good to a
    few degrees near the image centre only). Returns float32 depth with 0 = no return:

    * Axial noise: zero-mean Gaussian with standard deviation, z in metres,
      ``sigma(z, theta) = s0 + s1 z + s2 z^2 + s3 z^1.5 theta^2 / (pi/2 - theta)^2``
      (defaults s0..s3 = 1.5 mm, -0.5 mm/m, 0.3 mm/m^2, 0.1 mm/m^1.5). This is the form and fit of
      Fankhauser et al., "Kinect v2 for Mobile Robot Navigation: Evaluation and Modeling", ICAR
      2015, which adapts the angle term of Nguyen, Izadi & Lovell, "Modeling Kinect Sensor Noise
      for Improved 3D Reconstruction and Tracking", 3DIMPVT 2012 (structured-light Kinect v1) to
      the ToF sensor: about 1.3 mm at 0.6 m face-on, rising steeply towards grazing incidence.
      The noise is applied to z rather than along the ray; the difference is below the model's
      accuracy. Lateral noise is not modelled.
    * Dropouts: no return where theta exceeds ``max_incidence_deg`` (too little light comes back)
      or z lies outside the sensor's ``range_m`` (0.5-4.5 m specified for the Kinect v2).
    * Flying pixels: a ToF pixel straddling a depth edge mixes both returns into a depth between
      them; the Kinect v2 driver discards such pixels, so every pixel whose 3x3 neighbourhood of
      returns spans more than ``flying_pixel_threshold_m`` is dropped. Pixels without a return are
      ignored here, so edges against empty space are kept.
    * Zeros (no return) stay zero.
    """
    if not 0.0 < max_incidence_deg < 90.0:
        raise ValueError("max_incidence_deg must lie in (0, 90)")
    depth = np.asarray(depth_m, dtype=np.float64)
    normals = np.asarray(normals_camera, dtype=np.float64)
    if intrinsics is None:
        view = np.array([0.0, 0.0, 1.0])
    else:
        if (intrinsics.height, intrinsics.width) != depth.shape:
            raise ValueError("intrinsics do not match the depth image size")
        view = _pixel_rays(intrinsics).reshape(*depth.shape, 3)
    cos_incidence = np.clip(np.abs(np.sum(normals * view, axis=-1)), 0.0, 1.0)
    incidence = np.arccos(cos_incidence)

    returned = depth > 0.0
    farthest = ndimage.maximum_filter(depth, size=3)  # zeros never win a max over depths
    nearest = ndimage.minimum_filter(np.where(returned, depth, np.inf), size=3)
    valid = (
        returned
        & (incidence <= math.radians(max_incidence_deg))
        & (depth >= range_m[0])
        & (depth <= range_m[1])
        & (farthest - nearest <= flying_pixel_threshold_m)
    )

    # Clamped so that the angle term stays finite on the dropped pixels as well.
    theta = np.minimum(incidence, math.radians(max_incidence_deg))
    sigma = (
        sigma_base_m
        + sigma_linear * depth
        + sigma_quadratic_per_m * depth**2
        + sigma_incidence_per_sqrt_m * depth**1.5 * theta**2 / (0.5 * math.pi - theta) ** 2
    )
    noisy = depth + sigma * rng.standard_normal(depth.shape)
    return np.where(valid, noisy, 0.0).astype(np.float32)
