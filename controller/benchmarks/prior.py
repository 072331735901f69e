"""Benchmark figures of the shape priors: inference latency, training throughput, model sizes.

Measured, printed as JSON and reported in docs/prior.md; never asserted (timings depend on the
machine and its load).
"""

from __future__ import annotations

import os
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import torch

from controller.benchmarks.timing import machine, repeated
from models.geometry import VoxelGrid, axes_facing_camera
from models.prior.auto import AUTO
from models.prior.evaluation import BenchCamera
from models.prior.networks import ShapeNet, SketchNet, get_preset, normalise_rgb, parameter_count
from models.prior.shape_prior import DEFAULT_WEIGHTS_DIR, ShapePrior, available_priors
from models.prior.training import paper_optimizer, shape_loss, sketch_loss
from models.procedural import make_shape
from models.render import Scene, apply_kinect_depth_noise, render
from models.vision import estimate_from_frame


def _training_throughput(preset_name: str, batch: int, steps: int) -> dict[str, float]:
    """Images per second of one optimiser step of each stage on random data."""
    preset = get_preset(preset_name)
    size, n = preset.image_size, preset.voxel_resolution
    torch.manual_seed(0)
    rgb = torch.rand(batch, 3, size, size)
    sketch_batch = {
        "nearness": torch.rand(batch, 1, size, size),
        "normals": torch.rand(batch, 3, size, size),
        "silhouette": (torch.rand(batch, 1, size, size) > 0.5).float(),
    }
    voxels = (torch.rand(batch, n, n, n) > 0.9).float()
    sketch, shape = SketchNet(preset), ShapeNet(preset)
    sketch_opt = paper_optimizer("sketch", sketch, None)
    shape_opt = paper_optimizer("shape", shape, None)

    def sketch_step() -> None:
        sketch_opt.zero_grad()
        sketch_loss(sketch(normalise_rgb(rgb)), sketch_batch)["total"].backward()
        sketch_opt.step()

    def shape_step() -> None:
        shape_opt.zero_grad()
        shape_loss(shape(torch.rand(batch, 4, size, size)), voxels).backward()
        shape_opt.step()

    result = {}
    for stage, step in (("sketch", sketch_step), ("shape", shape_step)):
        median_s = repeated(step, steps).medians()["wall_s"]
        result[f"{stage}_images_per_s"] = round(batch / median_s, 2)
    result["batch"] = batch
    return result


def _latency(function: Callable[[], object], repeats: int) -> dict[str, float]:
    """Wall-clock figures (ms) and the median CPU time, which a loaded machine inflates less."""
    stopwatch = repeated(function, repeats)
    cpu_ms = round(1e3 * stopwatch.medians()["cpu_s"], 3)
    return {**stopwatch.milliseconds(), "cpu_median_ms": cpu_ms, "repeats": repeats}


def committed_prior_latency(
    camera: BenchCamera, *, repeats: int = 10, weights_dir: Path | None = None
) -> dict[str, dict]:
    """Latency of every cpu-preset prior in ``weights_dir`` (default: the shipped ones) and of
    the automatic choice among them, full bench frame -> the estimate a session starts from
    (:func:`models.vision.estimate_from_frame`: with RGB-D the depth fusion and the symmetry
    completion included), on one torch thread (the deployment budget is 0.5 s on one thread):
    ``{name: {"frame", "rgb_to_voxels", "rgbd_to_voxels"}}`` (wall and CPU milliseconds)."""
    rng = np.random.default_rng(0)
    scene = Scene.bench(make_shape("mug", rng), camera.object_albedo_rgb, camera.table_size_m)
    frame = render(scene, camera.intrinsics, camera.pose_world_camera, rng=rng)
    depth = apply_kinect_depth_noise(
        frame.depth_m, frame.normals_camera, rng, intrinsics=camera.intrinsics
    )
    axes = axes_facing_camera(camera.pose_world_camera[:3, 3])
    priors = {
        name: ShapePrior.load(name, preset="cpu", weights_dir=weights_dir)
        for name, specs in available_priors(weights_dir).items()
        if any(spec.preset == "cpu" for spec in specs)
    }
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        figures: dict[str, dict] = {}
        for name in [*priors, AUTO]:
            chosen = priors if name == AUTO else {name: priors[name]}
            if not chosen:
                continue
            first = next(iter(chosen.values()))
            grid = VoxelGrid(
                first.preset.voxel_resolution, first.grid_extent_m, (0.0, 0.0, 0.0), axes
            )
            predict = partial(
                estimate_from_frame,
                chosen,
                frame.colour_rgb,
                camera.intrinsics,
                camera.pose_world_camera,
                grid,
            )
            figures[name] = {
                "frame": "+".join(sorted({p.frame for p in chosen.values()})),
                "rgb_to_voxels": _latency(partial(predict, input_mode="rgb"), repeats),
                "rgbd_to_voxels": _latency(
                    partial(predict, depth_m=depth, input_mode="rgbd"), repeats
                ),
            }
        return figures
    finally:
        torch.set_num_threads(threads)


def benchmark_prior(
    camera: BenchCamera, *, repeats: int = 10, weights_dir: Path | None = None
) -> dict:
    """Latency (full bench frame -> voxels) and sizes for both presets; training throughput;
    the latency of every committed prior and of ``auto`` on one thread."""
    rng = np.random.default_rng(0)
    scene = Scene.bench(make_shape("mug", rng), camera.object_albedo_rgb, camera.table_size_m)
    frame = render(scene, camera.intrinsics, camera.pose_world_camera, rng=rng)
    axes = axes_facing_camera(camera.pose_world_camera[:3, 3])
    figures: dict = {
        "benchmark": "prior",
        # numpy's and scipy's BLAS threads follow OMP_NUM_THREADS, read once at import: run
        # with OMP_NUM_THREADS=1 for the one-thread figures (docs/prior.md, "Benchmarks").
        "machine": machine(
            torch_threads=torch.get_num_threads(),
            torch=torch.__version__,
            omp_num_threads=os.environ.get("OMP_NUM_THREADS"),
        ),
        "frame": [camera.intrinsics.width, camera.intrinsics.height],
        "presets": {},
    }
    for name in ("cpu", "paper"):
        try:
            prior = ShapePrior.load("general", preset=name)
            weights = "trained"
        except ValueError:
            prior = ShapePrior.untrained(name)
            weights = "untrained (random)"
        preset = prior.preset
        grid = VoxelGrid(preset.voxel_resolution, prior.grid_extent_m, (0.0, 0.0, 0.0), axes)
        predict = partial(
            prior.predict, frame.colour_rgb, camera.intrinsics, camera.pose_world_camera, grid
        )
        count = repeats if name == "cpu" else max(2, repeats // 4)
        entry = {
            "weights": weights,
            "image_size": preset.image_size,
            "voxel_resolution": preset.voxel_resolution,
            "sketch_params": parameter_count(prior.sketch_net),
            "shape_params": parameter_count(prior.shape_net),
            "float16_mb": round(
                2 * (parameter_count(prior.sketch_net) + parameter_count(prior.shape_net)) / 1e6, 2
            ),
            "rgb_to_voxels": {**repeated(predict, count).milliseconds(), "repeats": count},
            "rgbd_to_voxels": {
                **repeated(partial(predict, depth_m=frame.depth_m), count).milliseconds(),
                "repeats": count,
            },
        }
        entry["training"] = _training_throughput(
            name, 16 if name == "cpu" else 1, 3 if name == "cpu" else 1
        )
        figures["presets"][name] = entry
    figures["committed_priors_one_thread"] = committed_prior_latency(
        camera, repeats=repeats, weights_dir=weights_dir
    )
    figures["committed_weights_mb"] = round(
        sum(p.stat().st_size for p in (weights_dir or DEFAULT_WEIGHTS_DIR).glob("*.pt")) / 1e6, 2
    )
    return figures
