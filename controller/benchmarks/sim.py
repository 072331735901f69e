"""Benchmarks that print JSON: measured here, reported in docs/benchmarks.md, never asserted."""

from __future__ import annotations

import os
import platform
import resource
import statistics
import time
import tracemalloc
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.fft
from numpy.typing import NDArray

from controller.config import Config
from controller.motion.planner import pad_pose_facing
from drivers.sim.gelsight import gel_pad_spec
from drivers.sim.world import SimWorld
from models.camera import CameraIntrinsics
from models.render import apply_kinect_depth_noise, render
from models.tactile.lut import (
    GelSightCalibration,
    calibrate_datapack,
    default_datapack_path,
    load_datapack,
    tile_grid,
)
from models.tactile.reconstruction import PoissonSolver, TactileReconstructor, contact_mask
from models.tactile.sim import GelSightSimulator


def _timed_ms(function: Callable[[], Any], frames: int) -> dict[str, float]:
    """Median and spread of ``frames`` calls after one warm-up call, in milliseconds."""
    function()
    samples = []
    for _ in range(frames):
        start = time.perf_counter()
        function()
        samples.append((time.perf_counter() - start) * 1e3)
    return {
        "median_ms": round(statistics.median(samples), 3),
        "min_ms": round(min(samples), 3),
        "max_ms": round(max(samples), 3),
        "frames": frames,
    }


def benchmark_sim(config: Config, *, frames: int = 20) -> dict[str, Any]:
    """Per-frame times of the bench: Kinect render (+ depth noise) and GelSight simulation."""
    world = SimWorld.from_config(config.sim, config.robot.arm, config.gripper, config.sensor)
    camera = config.cameras.rgbd
    intrinsics = CameraIntrinsics.kinect_v2_colour(camera.colour_scale)
    pose_world_camera = camera.pose_world_camera()
    rng = np.random.default_rng(0)

    start = time.perf_counter()
    world.scene.build()
    bvh_build_ms = (time.perf_counter() - start) * 1e3

    def render_frame() -> None:
        output = render(world.scene, intrinsics, pose_world_camera, rng=rng)
        apply_kinect_depth_noise(output.depth_m, output.normals_camera, rng, intrinsics=intrinsics)

    gel = GelSightSimulator(gel_pad_spec(config.sensor))
    toward_camera = -pose_world_camera[:3, 2]
    height_m = float(world.object_mesh_world.bounds[1, 2]) / 2
    point, normal = world.surface_point_toward(toward_camera, height_m)
    pose_world_pad = pad_pose_facing(point, normal, -0.0005)  # pressed 0.5 mm into the surface
    indentation = gel.indentation_mm(world.scene_mesh_world, pose_world_pad)

    return {
        "benchmark": "sim",
        "object": config.sim.object,
        "object_faces": len(world.object_mesh_world.faces),
        "machine": {
            "cpu_count": os.cpu_count(),
            "processor": platform.processor() or platform.machine(),
            "python": platform.python_version(),
        },
        "kinect_render": {
            "resolution": [intrinsics.width, intrinsics.height],
            "bvh_build_ms": round(bvh_build_ms, 3),
            **_timed_ms(render_frame, frames),
        },
        "gelsight_indentation": {
            "resolution": [gel.spec.image_width_px, gel.spec.image_height_px],
            "contact_px": int(np.count_nonzero(indentation)),
            **_timed_ms(lambda: gel.indentation_mm(world.scene_mesh_world, pose_world_pad), frames),
        },
        "gelsight_render": _timed_ms(lambda: gel.render_bgr(indentation, rng), frames),
    }


class _StraightforwardGelSight:
    """The benchmark's baseline, not a library path: the same table and the same results, done
    the textbook way - a float64 per-pixel colour lookup and the classic DST-I Poisson solver on
    the (H-2)x(W-2) interior with zero height on the image border (as GelSight's own
    fast_poisson does it), with the eigenvalues recomputed per frame."""

    def __init__(self, calibration: GelSightCalibration, reference_bgr: NDArray[np.uint8]) -> None:
        self.calibration = calibration
        self.reference = reference_bgr
        self.tiles = tile_grid(calibration.image_shape, calibration.tile_px)[0]

    def __call__(
        self, image_bgr: NDArray[np.uint8]
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        calibration = self.calibration
        step = calibration.colour_step
        half = calibration.colour_limit // step
        levels = 2 * half + 1
        change = image_bgr.astype(np.float64) - self.reference.astype(np.float64)
        level = np.clip(np.floor(change / step + 0.5), -half, half).astype(np.int64) + half
        colour = (level[..., 0] * levels + level[..., 1]) * levels + level[..., 2]
        index = self.tiles * levels**3 + colour
        grad_x = calibration.table_gx[index].astype(np.float64)
        grad_y = calibration.table_gy[index].astype(np.float64)

        grad_xx = np.zeros_like(grad_x)
        grad_yy = np.zeros_like(grad_y)
        grad_xx[:, 1:] = grad_x[:, 1:] - grad_x[:, :-1]
        grad_yy[1:, :] = grad_y[1:, :] - grad_y[:-1, :]
        divergence = (grad_xx + grad_yy)[1:-1, 1:-1]
        transformed = scipy.fft.dst(scipy.fft.dst(divergence, type=1, axis=0), type=1, axis=1)
        rows, cols = divergence.shape
        x, y = np.meshgrid(np.arange(1, cols + 1), np.arange(1, rows + 1))
        eigen = (2 * np.cos(np.pi * x / (cols + 1)) - 2) + (2 * np.cos(np.pi * y / (rows + 1)) - 2)
        interior = scipy.fft.idst(
            scipy.fft.idst(transformed / eigen, type=1, axis=0), type=1, axis=1
        )
        height = np.zeros(calibration.image_shape)
        height[1:-1, 1:-1] = interior * calibration.mm_per_px
        height = np.maximum(height, 0.0)
        return height, contact_mask(height)


def _peak_traced_mb(function: Callable[[], Any]) -> float:
    """Peak of the Python/numpy memory allocated while ``function`` runs, MiB (tracemalloc)."""
    tracemalloc.start()
    try:
        function()
        return tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


def benchmark_gelsight(*, frames: int = 200) -> dict[str, Any]:
    """Full GelSight reconstruction (lookup + Poisson + contact mask) of 640x480 frames.

    Calibrated on the even-indexed real presses of taxim's dataPack and run on the odd ones,
    cycled to ``frames``; the library and the straightforward baseline alternate frame by
    frame in one process so that load from other jobs hits both alike. fps = 1000 / median ms.
    Both run on one thread (numpy elementwise code and scipy.fft with workers=1).
    """
    if frames < 1:
        raise ValueError("frames must be >= 1")
    pack = load_datapack(default_datapack_path())
    calibration = calibrate_datapack(pack, range(0, len(pack.images_bgr), 2))
    images = pack.images_bgr[1::2]
    tables_mb = (calibration.table_gx.nbytes + calibration.table_gy.nbytes) / 2**20
    reconstructor = TactileReconstructor(calibration, pack.reference_bgr)
    straightforward = _StraightforwardGelSight(calibration, pack.reference_bgr)
    solver = PoissonSolver(calibration.image_shape, calibration.mm_per_px)

    fast_ms, plain_ms, lookup_ms, poisson_ms, differences = [], [], [], [], []
    # Thread CPU time beside wall time: on a shared machine it leaves out the time this thread
    # waited for a core, which the wall-clock figures (the ones that count) include.
    fast_cpu_ms, plain_cpu_ms = [], []
    reconstructor.reconstruct(images[0])  # warm-up: first-touch page faults, FFT plans
    straightforward(images[0])
    for frame in range(frames):
        image = images[frame % len(images)]
        start, start_cpu = time.perf_counter(), time.thread_time()
        result = reconstructor.reconstruct(image)
        fast_ms.append((time.perf_counter() - start) * 1e3)
        fast_cpu_ms.append((time.thread_time() - start_cpu) * 1e3)
        start, start_cpu = time.perf_counter(), time.thread_time()
        plain_height, _ = straightforward(image)
        plain_ms.append((time.perf_counter() - start) * 1e3)
        plain_cpu_ms.append((time.thread_time() - start_cpu) * 1e3)
        differences.append(float(np.abs(result.height_mm - plain_height).max()))
    for frame in range(frames):
        image = images[frame % len(images)]
        start = time.perf_counter()
        gradients = reconstructor.gradients(image)
        lookup_ms.append((time.perf_counter() - start) * 1e3)
        start = time.perf_counter()
        solver.solve(*gradients)
        poisson_ms.append((time.perf_counter() - start) * 1e3)

    fast, plain = statistics.median(fast_ms), statistics.median(plain_ms)
    return {
        "benchmark": "gelsight",
        "resolution": [calibration.image_shape[1], calibration.image_shape[0]],
        "frames": frames,
        "fps": round(1e3 / fast, 1),
        "fps_straightforward": round(1e3 / plain, 1),
        "speedup": round(plain / fast, 2),
        "fps_cpu_time": round(1e3 / statistics.median(fast_cpu_ms), 1),
        "fps_straightforward_cpu_time": round(1e3 / statistics.median(plain_cpu_ms), 1),
        "median_ms": round(fast, 3),
        "median_ms_straightforward": round(plain, 3),
        "p90_ms": round(float(np.percentile(fast_ms, 90)), 3),
        "median_lookup_ms": round(statistics.median(lookup_ms), 3),
        "median_poisson_ms": round(statistics.median(poisson_ms), 3),
        # Tables + everything the reconstructor precomputes + one frame's temporaries.
        "peak_memory_mb": round(
            tables_mb
            + _peak_traced_mb(
                lambda: TactileReconstructor(calibration, pack.reference_bgr).reconstruct(images[0])
            ),
            2,
        ),
        "peak_memory_mb_straightforward": round(
            tables_mb + _peak_traced_mb(lambda: straightforward(images[0])), 2
        ),
        "process_max_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
        "max_height_difference_mm": round(max(differences), 4),
        "machine": {
            "cpu_count": os.cpu_count(),
            "processor": platform.processor() or platform.machine(),
            "python": platform.python_version(),
            "load_average_1min": round(os.getloadavg()[0], 2),
        },
    }
