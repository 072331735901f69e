"""Training data for the shape priors: rendered views of shapes with 2.5D sketches and voxels.

Each view places one shape (:mod:`models.procedural`, or a ShapeNetCore-style mesh) on the bench
table at the object point, yawed at random about the vertical axis, and renders it with the
project's renderer (:func:`models.render.render`) through the *virtual camera* of
:mod:`models.prior.virtual_camera`: the deployment Kinect pose (45.72 cm high, 30 deg tilt,
0.62 m away) with jitter, cropped around the registered voxel grid at the network's resolution.
Backgrounds: 1/3 white, 1/3 lit gradients with random coloured illumination, 1/3 random
textures.
Ground-truth voxels are in the controller's frame: the :class:`models.geometry.VoxelGrid` whose
axes face the (jittered) camera, indexed [i, j, k], occupancy of each voxel centre.

Determinism: shape ``n`` of category ``c`` is drawn from ``default_rng((c, seed + n))`` and its
views from ``default_rng((c, seed + n, 1))``, independent of the worker count or order. Training
data must use shape seeds below :data:`EVAL_SEED_START`; evaluation draws its held-out shapes from
seeds at or above it.

Shards (``shard_XXXXX.npz``, compressed) hold the views of a few shapes of one category;
``manifest.json`` records the recipe and the finished shards. Building again skips finished
shards, so an interrupted build resumes.
"""

from __future__ import annotations

import json
import math
import multiprocessing
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import trimesh

from models.camera import CameraIntrinsics, look_at_pose
from models.families import FAMILIES, SHAPE_GROUPS, SIZE_RANGE_M, make_family_shape
from models.files import write_atomically, write_json_atomically
from models.geometry import VoxelGrid, axes_facing_camera, make_transform, rotation_about_axis
from models.prior.frame import FrameError, fit_object_grid, search_grid
from models.prior.virtual_camera import GridCrop, grid_crop, sensor_normals_camera
from models.procedural import CATEGORIES, procedural_shape
from models.render import (
    Lighting,
    RenderOutput,
    Scene,
    SceneObject,
    apply_kinect_depth_noise,
    make_table,
    render,
)
from models.shapes import load_mesh_file, voxelize

EVAL_SEED_START = 1_000_000
"""Shape seeds >= this are held out for evaluation and never used for training data."""

BACKGROUNDS: tuple[str, ...] = ("white", "gradient", "texture")


# ShapeNetCore synset ids of the paper's 14 categories.
SHAPENET_SYNSETS: dict[str, str] = {
    "02773838": "bag",
    "02876657": "bottle",
    "02880940": "bowl",
    "02942699": "camera",
    "02946921": "can",
    "02954340": "cap",
    "03085013": "keyboard",
    "03261776": "earphone",
    "03513137": "helmet",
    "03593526": "jar",
    "03624134": "knife",
    "03642806": "laptop",
    "03797390": "mug",
    "04074963": "remote",
}


@dataclass(frozen=True)
class ViewRecipe:
    """How views are drawn: the deployment camera and its jitter (metres, degrees)."""

    image_size: int = 128
    voxel_resolution: int = 64
    grid_extent_m: float = 0.26
    camera_height_m: float = 0.4572
    camera_tilt_deg: float = 30.0
    camera_distance_m: float = 0.62
    full_colour_scale: float = 0.5
    """The deployment image: Kinect v2 colour intrinsics at this scale (the bench's default)."""
    height_jitter_m: float = 0.04
    tilt_jitter_deg: float = 4.0
    distance_jitter_m: float = 0.06
    shapenet_size_m: tuple[float, float] = (0.10, 0.20)
    """Largest extent of a ShapeNet model after scaling (the files are normalised, unitless)."""
    frame: Literal["fixed", "object"] = "object"
    """"fixed": the grid_extent_m cube on the object point (the paper's registration);
    "object": the grid fitted to the object's silhouette (:mod:`models.prior.frame`)."""
    frame_jitter: float = 0.05
    """Relative jitter of the fitted frame's edge and centre, for the frame's own errors."""
    category_scale: tuple[float, float] = (0.6, 1.4)
    """The 14 categories are scaled by a factor drawn in this range (within SIZE_RANGE_M)."""


@dataclass(frozen=True)
class BuildSpec:
    """What to build: categories x shapes x views from a source, with a seed."""

    out_dir: str
    source: str = "procedural"
    categories: tuple[str, ...] = CATEGORIES
    shapes_per_category: int = 40
    views: int = 6
    seed: int = 0
    shapes_per_shard: int = 5
    recipe: ViewRecipe = field(default_factory=ViewRecipe)


def shape_rngs(category_index: int, shape_seed: int) -> tuple[np.random.Generator, ...]:
    """(shape rng, view rng) of one shape: the documented per-shape seeding."""
    return (
        np.random.default_rng((category_index, shape_seed)),
        np.random.default_rng((category_index, shape_seed, 1)),
    )


def generated_shape(
    group: str, rng: np.random.Generator, recipe: ViewRecipe | None = None
) -> trimesh.Trimesh:
    """A shape of one of :data:`SHAPE_GROUPS` (table frame, metres). With a ``recipe``, the
    14 categories are scaled by a factor in ``recipe.category_scale`` (drawn after the shape, so
    the shape itself is that of the seed), kept within :data:`models.families.SIZE_RANGE_M`."""
    if group in FAMILIES:
        return make_family_shape(group, rng)
    mesh = procedural_shape(group, rng)
    if recipe is not None and group in CATEGORIES:
        largest = float(np.max(mesh.extents))
        low = max(recipe.category_scale[0], SIZE_RANGE_M[0] / largest)
        high = min(recipe.category_scale[1], SIZE_RANGE_M[1] / largest)
        mesh.apply_scale(float(np.exp(rng.uniform(np.log(low), np.log(high)))))
    return mesh


def shapenet_models(root: Path) -> dict[str, list[Path]]:
    """ShapeNetCore layout ``synset/model/models/model_normalized.obj`` -> {category: [paths]}.

    Known synsets are named after the paper's categories; others keep their synset id.
    """
    found: dict[str, list[Path]] = {}
    for path in sorted(root.glob("*/*/models/model_normalized.obj")):
        synset = path.parents[2].name
        found.setdefault(SHAPENET_SYNSETS.get(synset, synset), []).append(path)
    if not found:
        raise FileNotFoundError(f"no */*/models/model_normalized.obj under {root}")
    return found


# --- one view -------------------------------------------------------------------------------------


def jittered_camera_pose(recipe: ViewRecipe, rng: np.random.Generator) -> np.ndarray:
    """A deployment-like ``pose_world_camera``: height, tilt, distance jittered; looks along +x."""
    height = recipe.camera_height_m + rng.uniform(-1, 1) * recipe.height_jitter_m
    tilt = math.radians(recipe.camera_tilt_deg + rng.uniform(-1, 1) * recipe.tilt_jitter_deg)
    distance = recipe.camera_distance_m + rng.uniform(-1, 1) * recipe.distance_jitter_m
    eye = np.array([-distance, 0.0, height])
    view = np.array([math.cos(tilt), 0.0, -math.sin(tilt)])
    return look_at_pose(eye, eye + view)


def registered_grid(recipe: ViewRecipe, pose_world_camera: np.ndarray) -> VoxelGrid:
    """The paper's fixed grid for this camera: on the object point, axes facing the camera."""
    return VoxelGrid(
        recipe.voxel_resolution, recipe.grid_extent_m, (0.0, 0.0, 0.0), _axes(pose_world_camera)
    )


def view_crop(recipe: ViewRecipe, pose_world_camera: np.ndarray, grid: VoxelGrid) -> GridCrop:
    """The network-resolution virtual camera for a view."""
    full = CameraIntrinsics.kinect_v2_colour(recipe.full_colour_scale)
    return grid_crop(full, pose_world_camera, grid, recipe.image_size)


def random_texture(rng: np.random.Generator, size: int = 32) -> np.ndarray:
    """A random (size, size, 3) texture in 0..1 (printed labels, patterns): blocky palette noise."""
    palette = rng.uniform(0.1, 1.0, (3, 3))
    cells = int(rng.choice((2, 4, 8, 16)))
    index = rng.integers(0, 3, (cells, cells))
    return np.kron(palette[index], np.ones((size // cells, size // cells, 1)))


def render_view(
    mesh: trimesh.Trimesh, recipe: ViewRecipe, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """One training view of ``mesh`` (table frame): arrays as stored in a shard (see module doc)."""
    pose_world_camera = jittered_camera_pose(recipe, rng)
    yaw = rng.uniform(0.0, 2.0 * math.pi)
    mesh_world = mesh.copy()
    mesh_world.apply_transform(make_transform(rotation_about_axis((0, 0, 1), yaw)))
    background = BACKGROUNDS[int(rng.integers(len(BACKGROUNDS)))]
    if background == "gradient" or (background == "texture" and rng.random() < 0.5):
        lighting = Lighting.random(rng)
    else:
        lighting = Lighting.default()
    albedo = tuple(rng.uniform(0.1, 0.95, 3).tolist())
    texture = random_texture(rng) if rng.random() < 1 / 3 else None
    table_albedo = tuple(rng.uniform(0.2, 0.9, 3).tolist())
    table_size = (rng.uniform(0.6, 1.6), rng.uniform(0.5, 1.0))
    table = make_table(
        table_size, (rng.uniform(-0.1, 0.1), rng.uniform(-0.05, 0.05)), albedo_rgb=table_albedo
    )
    scene = Scene(
        objects=[
            SceneObject(
                mesh_world,
                albedo_rgb=albedo,
                texture=texture,
                texture_tile_m=rng.uniform(0.03, 0.15),
            )
        ],
        table=table,
    )

    def render_crop(grid: VoxelGrid) -> tuple[GridCrop, RenderOutput]:
        crop = view_crop(recipe, pose_world_camera, grid)
        out = render(
            scene,
            crop.intrinsics,
            pose_world_camera,
            lighting=lighting,
            background=background,
            rng=rng,
        )
        return crop, out

    view: dict[str, np.ndarray] = {}
    if recipe.frame == "object":
        searched, search_out = render_crop(
            search_grid(recipe.voxel_resolution, _axes(pose_world_camera))
        )
        view |= {f"search_{k}": v for k, v in _sketches(searched, search_out).items()}
        grid = object_grid(recipe, pose_world_camera, searched, search_out.silhouette, rng)
    else:
        grid = registered_grid(recipe, pose_world_camera)
    crop, out = render_crop(grid)
    sensor = apply_kinect_depth_noise(
        out.depth_m, out.normals_camera, rng, intrinsics=crop.intrinsics
    )
    return (
        view
        | _sketches(crop, out)
        | {
            "sensor_nearness": crop.nearness(sensor).astype(np.float16),
            "voxels": np.packbits(voxelize(mesh_world, grid)),
            "grid_extent_m": np.float32(grid.extent_m),
            "grid_origin_world": np.asarray(grid.origin_world, dtype=np.float32),
            "pose_world_camera": pose_world_camera.astype(np.float32),
            "yaw_rad": np.float32(yaw),
            "background": np.int8(BACKGROUNDS.index(background)),
        }
    )


def _sketches(crop: GridCrop, out: RenderOutput) -> dict[str, np.ndarray]:
    """The network's input and the sketch net's targets of one rendered crop, as stored."""
    silhouette = out.silhouette
    return {
        "rgb": out.colour_rgb,
        "nearness": np.where(silhouette, crop.nearness(out.depth_m), 0).astype(np.float16),
        "normals": np.round(out.normals_camera * 127 * silhouette[..., None]).astype(np.int8),
        "silhouette": np.packbits(silhouette),
    }


def _axes(pose_world_camera: np.ndarray) -> tuple[tuple[float, float, float], ...]:
    return axes_facing_camera(pose_world_camera[:3, 3])


def object_grid(
    recipe: ViewRecipe,
    pose_world_camera: np.ndarray,
    searched: GridCrop,
    silhouette: np.ndarray,
    rng: np.random.Generator,
) -> VoxelGrid:
    """The object-fitted grid of a view, jittered by ``recipe.frame_jitter`` so the networks
    learn the frame's errors; the search grid when no object is seen."""
    axes = _axes(pose_world_camera)
    try:
        fitted = fit_object_grid(
            silhouette, searched.intrinsics, pose_world_camera, axes, recipe.voxel_resolution
        )
    except FrameError:
        return search_grid(recipe.voxel_resolution, axes)
    jitter = recipe.frame_jitter
    extent = fitted.extent_m * (1.0 + rng.uniform(-jitter, jitter))
    shift = rng.normal(0.0, 0.5 * jitter * fitted.extent_m, 2)
    axes_array = np.asarray(axes)
    origin = np.asarray(fitted.origin_world) + shift[0] * axes_array[0] + shift[1] * axes_array[1]
    return VoxelGrid(recipe.voxel_resolution, extent, (origin[0], origin[1], 0.0), axes)


# --- shards ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ShardTask:
    """Views of ``len(shape_seeds)`` shapes of one category, written to one shard file."""

    index: int
    category: str
    shape_seeds: tuple[int, ...]
    mesh_paths: tuple[str, ...]
    """ShapeNet files for these shapes, or empty for procedural shapes."""


def shard_path(out_dir: Path, index: int) -> Path:
    return out_dir / f"shard_{index:05d}.npz"


def plan_shards(spec: BuildSpec) -> list[ShardTask]:
    """The deterministic list of shards for a build."""
    if spec.seed < 0 or spec.seed + spec.shapes_per_category > EVAL_SEED_START:
        raise ValueError(
            f"training shape seeds must stay in [0, {EVAL_SEED_START}): seed {spec.seed} + "
            f"{spec.shapes_per_category} shapes crosses into the held-out evaluation seeds"
        )
    tasks: list[ShardTask] = []
    if spec.source == "procedural":
        for category in spec.categories:
            if category not in SHAPE_GROUPS:
                raise ValueError(f"unknown category {category!r}; expected {SHAPE_GROUPS}")
            seeds = [spec.seed + n for n in range(spec.shapes_per_category)]
            for start in range(0, len(seeds), spec.shapes_per_shard):
                chunk = tuple(seeds[start : start + spec.shapes_per_shard])
                tasks.append(ShardTask(len(tasks), category, chunk, ()))
        return tasks
    models = shapenet_models(Path(spec.source))
    for category, paths in models.items():
        order = np.random.default_rng((spec.seed, len(paths))).permutation(len(paths))
        chosen = [paths[i] for i in order[: spec.shapes_per_category]]
        for start in range(0, len(chosen), spec.shapes_per_shard):
            chunk = chosen[start : start + spec.shapes_per_shard]
            seeds = tuple(spec.seed + start + n for n in range(len(chunk)))
            tasks.append(ShardTask(len(tasks), category, seeds, tuple(str(p) for p in chunk)))
    return tasks


def build_shard(spec: BuildSpec, task: ShardTask) -> Path:
    """Render one shard and write it atomically."""
    category_index = SHAPE_GROUPS.index(task.category) if task.category in SHAPE_GROUPS else -1
    rng_key = category_index if category_index >= 0 else sum(task.category.encode())
    views: list[dict[str, np.ndarray]] = []
    names: list[str] = []
    for n, shape_seed in enumerate(task.shape_seeds):
        shape_rng, view_rng = shape_rngs(rng_key, shape_seed)
        if task.mesh_paths:
            size = shape_rng.uniform(*spec.recipe.shapenet_size_m)
            mesh = load_mesh_file(task.mesh_paths[n], up_axis="y", fit_max_extent_m=size)
            names.append(Path(task.mesh_paths[n]).parents[1].name)
        else:
            mesh = generated_shape(task.category, shape_rng, spec.recipe)
            names.append(f"{task.category}_{shape_seed}")
        views.extend(render_view(mesh, spec.recipe, view_rng) for _ in range(spec.views))
    arrays = {key: np.stack([view[key] for view in views]) for key in views[0]}
    arrays["shape_index"] = np.repeat(np.arange(len(names)), spec.views)
    arrays["names"] = np.array(names)
    arrays["category"] = np.array(task.category)
    return write_atomically(
        shard_path(Path(spec.out_dir), task.index),
        lambda temporary: np.savez_compressed(temporary, **arrays),
    )


def _build_shard_star(args: tuple[BuildSpec, ShardTask]) -> int:
    torch.set_num_threads(1)
    build_shard(*args)
    return args[1].index


def manifest_path(out_dir: Path) -> Path:
    return out_dir / "manifest.json"


def build_dataset(spec: BuildSpec, *, workers: int = 2, progress: bool = True) -> dict:
    """Build (or resume) a dataset; returns the manifest also written to ``manifest.json``."""
    from tqdm import tqdm

    out_dir = Path(spec.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    tasks = plan_shards(spec)
    recipe = {**asdict(spec), "categories": list(spec.categories)}
    recipe.pop("out_dir")
    existing = manifest_path(out_dir)
    if existing.exists():
        previous = json.loads(existing.read_text())
        if previous["recipe"] != json.loads(json.dumps(recipe)):
            raise ValueError(f"{out_dir} holds a dataset with another recipe; use a new --out")
    todo = [task for task in tasks if not shard_path(out_dir, task.index).exists()]
    manifest = {
        "format": "touchshape-prior-data/1",
        "recipe": recipe,
        "seeding": "shape n of category c: default_rng((c, seed + n)); its views: "
        "default_rng((c, seed + n, 1)); c = index in SHAPE_GROUPS",
        "eval_seed_start": EVAL_SEED_START,
        "categories": list(dict.fromkeys(task.category for task in tasks)),
        "shards": [
            {
                "file": shard_path(out_dir, t.index).name,
                "category": t.category,
                "shapes": len(t.shape_seeds),
                "views": len(t.shape_seeds) * spec.views,
            }
            for t in tasks
        ],
        "complete": False,
    }
    write_json_atomically(existing, manifest)
    jobs = [(spec, task) for task in todo]
    bar = tqdm(
        total=len(tasks), initial=len(tasks) - len(todo), desc="shards", disable=not progress
    )
    if workers <= 1:
        for job in jobs:
            _build_shard_star(job)
            bar.update()
    else:
        context = multiprocessing.get_context("spawn")
        with context.Pool(workers) as pool:
            for _ in pool.imap_unordered(_build_shard_star, jobs):
                bar.update()
    bar.close()
    manifest["complete"] = True
    write_json_atomically(existing, manifest)
    return manifest


# --- torch dataset --------------------------------------------------------------------------------


class SketchVoxelDataset(torch.utils.data.Dataset):
    """All views of a built dataset, held in memory as stored (compact), decoded per item.

    Items are dicts of tensors: ``rgb`` uint8 (3, S, S); ``nearness``, ``sensor_nearness``,
    ``silhouette`` float (1, S, S); ``normals`` float (3, S, S); ``voxels`` float (N, N, N);
    ``category`` int (index into :attr:`categories`); ``sensor_normals`` float (3, S, S), the
    normals of the sensor depth as RGB-D inference takes them (0 where unknown; object-frame
    data only, zeros otherwise). With ``search_crops`` (for the sketch
    net), the views' search crops follow as further items: the crops in which the object-fitted
    frame looks for the object, with sketches but no voxels (zeros) and no sensor depth.
    """

    _VIEW_KEYS = ("rgb", "nearness", "sensor_nearness", "normals", "silhouette", "voxels")
    _CROP_KEYS = ("pose_world_camera", "grid_origin_world", "grid_extent_m")
    """Where each view's crop was: enough to rebuild its virtual camera (the sensor normals)."""
    _SEARCH_KEYS = ("search_rgb", "search_nearness", "search_normals", "search_silhouette")

    def __init__(
        self,
        data_dirs: str | Path | Sequence[str | Path],
        *,
        shards: Sequence[str] | None = None,
        search_crops: bool = False,
    ) -> None:
        folders = (
            [Path(data_dirs)] if isinstance(data_dirs, str | Path) else list(map(Path, data_dirs))
        )
        if not folders or (shards is not None and len(folders) > 1):
            raise ValueError("give one dataset folder (with shards) or several (without)")
        manifests = [json.loads(manifest_path(folder).read_text()) for folder in folders]
        recipes = [manifest["recipe"]["recipe"] for manifest in manifests]
        sizes = {(recipe["image_size"], recipe["voxel_resolution"]) for recipe in recipes}
        frames = {recipe.get("frame", "fixed") for recipe in recipes}
        if len(sizes) > 1 or len(frames) > 1:
            raise ValueError(f"{', '.join(map(str, folders))}: datasets of different recipes")
        (self.image_size, self.voxel_resolution), frame = sizes.pop(), frames.pop()
        self.recipe = ViewRecipe(
            **{k: tuple(v) if isinstance(v, list) else v for k, v in recipes[0].items()}
        )
        self.categories: list[str] = list(
            dict.fromkeys(c for manifest in manifests for c in manifest["categories"])
        )
        if search_crops and frame != "object":
            raise ValueError(f"{folders[0]} has no search crops (its views use the fixed frame)")
        keys = self._VIEW_KEYS + self._CROP_KEYS + (self._SEARCH_KEYS if search_crops else ())
        parts: dict[str, list[np.ndarray]] = {}
        for source, (folder, manifest) in enumerate(zip(folders, manifests, strict=True)):
            files = [s["file"] for s in manifest["shards"]] if shards is None else list(shards)
            for name in files:
                with np.load(folder / name) as shard:
                    count = len(shard["rgb"])
                    for key in keys:
                        parts.setdefault(key, []).append(shard[key])
                    category = self.categories.index(str(shard["category"]))
                    parts.setdefault("category", []).append(np.full(count, category))
                    parts.setdefault("name", []).append(shard["names"][shard["shape_index"]])
                    parts.setdefault("source", []).append(np.full(count, source))
        self.arrays = {key: np.concatenate(value) for key, value in parts.items()}
        self.views = len(self.arrays["rgb"])
        self.search_crops = search_crops

    def __len__(self) -> int:
        return self.views * (2 if self.search_crops else 1)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        a = self.arrays
        size, n = self.image_size, self.voxel_resolution
        search = index >= self.views
        view = index - self.views if search else index
        prefix = "search_" if search else ""
        silhouette = np.unpackbits(a[prefix + "silhouette"][view])[: size * size]
        nearness = torch.from_numpy(a[prefix + "nearness"][view].astype(np.float32))[None]
        sensor_normals = torch.zeros((3, size, size))
        if search:
            sensor_nearness = torch.zeros_like(nearness)
            voxels = torch.zeros((n, n, n))
        else:
            sensor = a["sensor_nearness"][view].astype(np.float32)
            sensor_nearness = torch.from_numpy(sensor)[None]
            voxels = torch.from_numpy(
                np.unpackbits(a["voxels"][view])[: n**3].reshape(n, n, n).astype(np.float32)
            )
            if self.recipe.frame == "object":
                crop = self._crop(view)
                normals, _ = sensor_normals_camera(crop.depth_m(sensor), crop)
                sensor_normals = torch.from_numpy(normals).permute(2, 0, 1)
        return {
            "rgb": torch.from_numpy(a[prefix + "rgb"][view]).permute(2, 0, 1).contiguous(),
            "nearness": nearness,
            "sensor_nearness": sensor_nearness,
            "normals": torch.from_numpy(
                a[prefix + "normals"][view].astype(np.float32) / 127.0
            ).permute(2, 0, 1),
            "silhouette": torch.from_numpy(silhouette.reshape(1, size, size).astype(np.float32)),
            "voxels": voxels,
            "category": torch.tensor(int(a["category"][view])),
            "sensor_normals": sensor_normals,
        }

    def _crop(self, view: int) -> GridCrop:
        """A view's virtual camera: its object-fitted grid faces the camera (``_axes``)."""
        pose = self.arrays["pose_world_camera"][view].astype(np.float64)
        origin = self.arrays["grid_origin_world"][view].astype(np.float64)
        grid = VoxelGrid(
            self.voxel_resolution,
            float(self.arrays["grid_extent_m"][view]),
            tuple(float(v) for v in origin),
            _axes(pose),
        )
        return view_crop(self.recipe, pose, grid)

    def shape_names(self) -> np.ndarray:
        """Name of the shape of each item (views of one shape, and their search crops, share
        it)."""
        names = self.arrays["name"]
        return np.concatenate([names, names]) if self.search_crops else names


def split_by_shape(
    dataset: SketchVoxelDataset, val_fraction: float, seed: int = 0
) -> tuple[list[int], list[int]]:
    """Train / validation view indices with whole shapes held out for validation.

    Each dataset folder is split on its own with the same seed, so adding a folder leaves the
    split of the others as it was (a fine-tune on more data validates on the same shapes)."""
    names = dataset.shape_names()
    sources = dataset.arrays["source"]
    sources = np.concatenate([sources, sources]) if dataset.search_crops else sources
    is_val = np.zeros(len(names), dtype=bool)
    for source in np.unique(sources):
        in_source = sources == source
        unique = np.unique(names[in_source])
        rng = np.random.default_rng(seed)
        count = max(1, round(val_fraction * len(unique)))
        val_names = set(rng.choice(unique, count, replace=False))
        is_val |= in_source & np.array([name in val_names for name in names])
    return np.flatnonzero(~is_val).tolist(), np.flatnonzero(is_val).tolist()
