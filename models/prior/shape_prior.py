"""Named shape priors: image (+ optional depth) -> voxel occupancy in the registered grid.

A prior is a 2.5D sketch net and a shape net of one preset, loaded by name from a weights folder
holding ``priors.json`` (the committed ``models/prior/weights/`` by default). The shape net's
decoder is the learned prior that touch refinement optimises through :meth:`ShapePrior.decode`.

Frames: the prediction is indexed [i, j, k] in a :class:`models.geometry.VoxelGrid` whose axes
face the camera (a_x horizontal toward the camera, a_z up): the grid registered with the camera
(``VoxelGridConfig.grid(camera_position)``, bottom centre on the object point) for a prior of the
fixed frame, or the grid fitted to the object (:mod:`models.prior.frame`) for a prior of the
object frame; ``PriorPrediction.grid`` says which, and ``x_w = R_v (x_v - o_v) + o_w`` places it
in the world.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Protocol

import numpy as np
import torch

from models.camera import CameraIntrinsics
from models.geometry import VoxelGrid
from models.object_bound import object_depth_points
from models.prior.carving import carve, seen_empty_voxels, seen_silhouette
from models.prior.frame import (
    FrameError,
    depth_silhouette,
    fit_object_grid,
    grid_holding_points,
    search_grid,
)
from models.prior.networks import (
    FrozenVoxelDecoder,
    NetworkPreset,
    ShapeNet,
    SketchNet,
    get_preset,
    normalise_rgb,
    shape_input,
)
from models.prior.virtual_camera import GridCrop, crop_image, grid_crop, sensor_normals_camera

log = logging.getLogger(__name__)

DEFAULT_WEIGHTS_DIR = Path(__file__).parent / "weights"
"""The weights shipped with the package (``priors.json`` lists them)."""


class ModelsSettings(Protocol):
    """What :meth:`ShapePrior.from_config` reads (``controller.config.ModelsConfig``)."""

    prior: str
    preset: str
    weights_dir: str
    device: str


class PriorNotFoundError(ValueError):
    """No prior of that name (and preset) in the weights folder."""


@dataclass(frozen=True)
class PriorSpec:
    """One entry of ``priors.json``: file names relative to the weights folder."""

    name: str
    preset: str
    sketch_weights: str
    shape_weights: str
    grid_extent_m: float
    description: str = ""
    frame: Literal["fixed", "object"] = "fixed"
    """"fixed": the prior decodes into the registered grid of ``grid_extent_m``; "object": into
    the grid fitted to the object (:mod:`models.prior.frame`), found in a search crop first."""


def available_priors(weights_dir: str | Path | None = None) -> dict[str, list[PriorSpec]]:
    """Priors in a weights folder by name (one spec per preset trained)."""
    folder = Path(weights_dir) if weights_dir else DEFAULT_WEIGHTS_DIR
    index = folder / "priors.json"
    if not index.exists():
        return {}
    from models.prior.training import WeightsError

    priors: dict[str, list[PriorSpec]] = {}
    try:
        for entry in json.loads(index.read_text(encoding="utf-8"))["priors"]:
            priors.setdefault(entry["name"], []).append(PriorSpec(**entry))
    except (UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError) as error:
        raise WeightsError(f"{index}: not a valid priors index ({error!r})") from None
    return priors


SketchCache = dict[tuple[str, GridCrop], dict[str, torch.Tensor]]
"""Sketch-net outputs on one image by (``ShapePrior.sketch_key``, crop)."""


@dataclass
class PriorPrediction:
    """What a prior sees and predicts for one frame.

    ``probabilities`` (N, N, N) float32 occupancy in ``grid`` indexed [i, j, k]; ``latent`` the
    (200,) code; ``depth_m`` (metres, 0 = background), ``normals_camera`` (camera frame) and
    ``silhouette`` (probability) are the predicted sketches on the crop's pixels (``crop``);
    ``prior`` names the prior that made it. Space the camera saw empty is carved out.
    """

    probabilities: np.ndarray
    latent: torch.Tensor
    depth_m: np.ndarray
    normals_camera: np.ndarray
    silhouette: np.ndarray
    crop: GridCrop
    grid: VoxelGrid
    prior: str
    seen_empty: np.ndarray | None = None
    """(N, N, N) bool: voxels the camera saw empty (:mod:`models.prior.carving`); the
    probabilities are capped there, and so must be any shape decoded from the latent later."""
    seen_silhouette: np.ndarray | None = None
    """(H, W) bool on the crop: where the object was seen (the sketch net's silhouette; with
    depth, the returns above the table), as the carving used it."""


class ShapePrior:
    """A sketch net + shape net pair; :meth:`predict` runs image -> voxels."""

    def __init__(
        self,
        sketch_net: SketchNet,
        shape_net: ShapeNet,
        *,
        name: str = "untrained",
        grid_extent_m: float = 0.26,
        frame: Literal["fixed", "object"] = "fixed",
        device: str | torch.device = "cpu",
        sketch_key: str | None = None,
    ) -> None:
        self.name = name
        self.preset: NetworkPreset = shape_net.preset
        self.grid_extent_m = grid_extent_m
        self.frame = frame
        self.sketch_key = sketch_key or f"sketch-net-{id(sketch_net)}"
        """Names the sketch net's weights: priors with the same key see the same sketches, so
        the automatic choice runs that net once per crop (:class:`SketchCache`)."""
        self.device = torch.device(device)
        self.sketch_net = sketch_net.to(self.device).eval()
        self.shape_net = shape_net.to(self.device).eval()
        self.decoder = FrozenVoxelDecoder(self.shape_net.decoder).to(self.device)
        """The shape net's decoder as inference runs it (:class:`FrozenVoxelDecoder`)."""

    @classmethod
    def load(
        cls,
        name: str = "general",
        *,
        preset: str = "cpu",
        weights_dir: str | Path | None = None,
        device: str = "cpu",
    ) -> ShapePrior:
        """The prior ``name`` of ``preset`` from ``weights_dir`` (default: shipped weights).

        Raises:
            PriorNotFoundError: unknown name or preset; the message lists what is available.
        """
        from models.prior.training import load_weights

        folder = Path(weights_dir) if weights_dir else DEFAULT_WEIGHTS_DIR
        priors = available_priors(folder)
        listing = (
            ", ".join(
                f"{n} ({'/'.join(s.preset for s in specs)})" for n, specs in sorted(priors.items())
            )
            or "none"
        )
        specs = [spec for spec in priors.get(name, []) if spec.preset == preset]
        if not specs:
            raise PriorNotFoundError(
                f"no shape prior {name!r} with preset {preset!r} in {folder}; available: {listing}"
            )
        spec = specs[0]
        network_preset = get_preset(preset)
        sketch, shape = SketchNet(network_preset), ShapeNet(network_preset)
        load_weights(sketch, folder / spec.sketch_weights)
        load_weights(shape, folder / spec.shape_weights)
        return cls(
            sketch,
            shape,
            name=name,
            grid_extent_m=spec.grid_extent_m,
            frame=spec.frame,
            device=device,
            sketch_key=f"{(folder / spec.sketch_weights).resolve()}:{preset}",
        )

    @classmethod
    def from_config(cls, models: ModelsSettings) -> ShapePrior:
        """The prior a config's ``[models]`` section names (``prior``, ``preset``,
        ``weights_dir`` with "" = shipped weights, ``device``)."""
        return cls.load(
            models.prior,
            preset=models.preset,
            weights_dir=models.weights_dir or None,
            device=models.device,
        )

    @classmethod
    def untrained(cls, preset: str = "cpu", *, seed: int = 0) -> ShapePrior:
        """Randomly initialised networks (for timing and tests)."""
        torch.manual_seed(seed)
        network_preset = get_preset(preset)
        return cls(SketchNet(network_preset), ShapeNet(network_preset), name=f"untrained-{preset}")

    def check_grid(self, grid: VoxelGrid) -> None:
        """The grid must have the resolution (and, in the fixed frame, the extent) the prior
        was trained for."""
        if grid.resolution != self.preset.voxel_resolution:
            raise ValueError(
                f"prior {self.name!r} ({self.preset.name} preset) predicts "
                f"{self.preset.voxel_resolution}^3 voxels; the grid has {grid.resolution}^3"
            )
        if self.frame == "fixed" and abs(grid.extent_m - self.grid_extent_m) > 1e-6:
            raise ValueError(
                f"prior {self.name!r} was trained for a {self.grid_extent_m} m grid, "
                f"not {grid.extent_m} m"
            )

    @torch.no_grad()
    def predict(
        self,
        colour_rgb: np.ndarray,
        intrinsics: CameraIntrinsics,
        pose_world_camera: np.ndarray,
        grid: VoxelGrid,
        *,
        depth_m: np.ndarray | None = None,
        sketch_cache: SketchCache | None = None,
    ) -> PriorPrediction:
        """Voxels from a full camera frame: (H, W, 3) uint8 RGB, its pinhole intrinsics and
        ``pose_world_camera``; ``grid`` is the registered voxel grid (in the object frame, its
        axes and object point place the search grid; the prediction's ``grid`` is the fitted
        one). With ``depth_m`` (H, W z-depth metres registered to the colour image, 0 = no
        return; RGB-D mode) the sensor depth replaces the predicted depth wherever it returned
        (and finds the object's silhouette in the object frame). ``sketch_cache`` shares the
        sketch net's outputs on this image between priors (one cache per image)."""
        self.check_grid(grid)
        if self.frame == "object":
            grid = self.object_grid(
                colour_rgb, intrinsics, pose_world_camera, grid, depth_m, sketch_cache
            )
        crop = grid_crop(intrinsics, pose_world_camera, grid, self.preset.image_size)
        sketches = self.sketches(colour_rgb, crop, sketch_cache)
        silhouette = torch.sigmoid(sketches["silhouette_logits"])
        mask = (silhouette > 0.5).float()
        depth = sketches["depth"]
        seen = mask[0, 0].cpu().numpy() > 0
        sensor_m = None
        if depth_m is not None:
            sensor_m = crop_image(depth_m.astype(np.float32), crop, nearest=True)
            sensor_t = torch.from_numpy(crop.nearness(sensor_m))[None, None].to(self.device)
            depth = torch.where(sensor_t > 0, sensor_t, depth)
        seen = seen_silhouette(seen, sensor_m, crop.intrinsics, pose_world_camera, grid)
        normals = sketches["normals"]
        if sensor_m is not None:
            # What the sensor measured replaces what the sketch net guessed: the object's
            # outline in depth and the normals of its depth where known (docs/prior.md).
            mask = torch.from_numpy(seen.astype(np.float32))[None, None].to(self.device)
            measured, known = sensor_normals_camera(sensor_m, crop)
            measured_t = torch.from_numpy(measured).permute(2, 0, 1)[None].to(self.device)
            known_t = torch.from_numpy(known)[None, None].to(self.device)
            normals = torch.where(known_t, measured_t, normals)
        latent = self.shape_net.encode(shape_input(depth, normals, mask))
        probabilities = torch.sigmoid(self.decoder(latent))[0].cpu().numpy()
        seen_empty = seen_empty_voxels(grid, crop, pose_world_camera, seen, sensor_m)
        near = (depth * mask)[0, 0].cpu().numpy()
        return PriorPrediction(
            probabilities=carve(probabilities, seen_empty),
            latent=latent[0].cpu(),
            depth_m=crop.depth_m(near),
            normals_camera=(normals * mask)[0].permute(1, 2, 0).cpu().numpy(),
            silhouette=silhouette[0, 0].cpu().numpy(),
            crop=crop,
            grid=grid,
            prior=self.name,
            seen_empty=seen_empty,
            seen_silhouette=seen,
        )

    def sketches(
        self, colour_rgb: np.ndarray, crop: GridCrop, cache: SketchCache | None = None
    ) -> dict[str, torch.Tensor]:
        """The sketch net's outputs on ``crop`` of the image (from ``cache`` if there)."""
        key = (self.sketch_key, crop)
        if cache is not None and key in cache:
            return cache[key]
        rgb = torch.from_numpy(crop_image(colour_rgb, crop)).permute(2, 0, 1)[None]
        sketches = self.sketch_net(normalise_rgb(rgb.to(self.device)))
        if cache is not None:
            cache[key] = sketches
        return sketches

    def object_grid(
        self,
        colour_rgb: np.ndarray,
        intrinsics: CameraIntrinsics,
        pose_world_camera: np.ndarray,
        registered: VoxelGrid,
        depth_m: np.ndarray | None = None,
        sketch_cache: SketchCache | None = None,
    ) -> VoxelGrid:
        """The grid fitted to the object: its silhouette in the search crop (from the sensor's
        depth with RGB-D, else the sketch net's), then :func:`fit_object_grid`. An image with no
        object in it keeps the search grid."""
        search = search_grid(registered.resolution, registered.axes_world, registered.origin_world)
        crop = grid_crop(intrinsics, pose_world_camera, search, self.preset.image_size)
        if depth_m is not None:
            depth = crop_image(depth_m.astype(np.float32), crop, nearest=True)
            mask = depth_silhouette(depth, crop.intrinsics, pose_world_camera, search)
        else:
            logits = self.sketches(colour_rgb, crop, sketch_cache)["silhouette_logits"]
            mask = (logits[0, 0] > 0).cpu().numpy()
        try:
            grid = fit_object_grid(
                mask, crop.intrinsics, pose_world_camera, search.axes_world, search.resolution
            )
        except FrameError as error:
            log.warning("prior %s: %s; using the search grid", self.name, error)
            return search
        if depth_m is None:
            return grid
        # With depth the object's seen surface is known: the grid holds all of it.
        return grid_holding_points(
            grid, object_depth_points(depth_m, intrinsics, pose_world_camera, search)
        )

    def decode(self, latent: torch.Tensor) -> torch.Tensor:
        """Latent (200,) or (B, 200) -> probabilities (N, N, N) or (B, N, N, N) in the grid
        frame [i, j, k]; differentiable in the latent, not in the network's weights."""
        batch = latent.dim() == 1
        probabilities = torch.sigmoid(self.decoder(latent[None] if batch else latent))
        return probabilities[0] if batch else probabilities
