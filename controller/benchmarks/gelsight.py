"""`touchshape bench gelsight`: frames per second of the GelSight reconstruction against a
straightforward baseline, and the memory both take, as JSON (never asserted)."""

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

from controller.benchmarks.timing import Stopwatch, machine
from models.tactile.lut import (
    GelSightLUT,
    build_lut_from_datapack,
    default_datapack_path,
    load_datapack,
    tile_grid,
)
from models.tactile.reconstruction import PoissonSolver, TactileReconstructor, contact_mask


class _StraightforwardGelSight:
    """The benchmark's baseline, not a library path: the same table and the same results, done
    the textbook way - a float64 per-pixel colour lookup and the classic DST-I Poisson solver on
    the (H-2)x(W-2) interior with zero height on the image border (as GelSight's own
    fast_poisson does it), with the eigenvalues recomputed per frame."""

    def __init__(self, calibration: GelSightLUT, reference_bgr: NDArray[np.uint8]) -> None:
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


def _fps(seconds: list[float]) -> float:
    """Frames per second at the median time per frame."""
    return round(1 / statistics.median(seconds), 1)


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
    calibration = build_lut_from_datapack(pack, range(0, len(pack.images_bgr), 2))
    images = pack.images_bgr[1::2]
    tables_mb = (calibration.table_gx.nbytes + calibration.table_gy.nbytes) / 2**20
    reconstructor = TactileReconstructor(calibration, pack.reference_bgr)
    straightforward = _StraightforwardGelSight(calibration, pack.reference_bgr)
    solver = PoissonSolver(calibration.image_shape, calibration.mm_per_px)

    # Thread CPU time beside wall time: on a shared machine it leaves out the time this thread
    # waited for a core, which the wall-clock figures (the ones that count) include.
    fast, plain = Stopwatch(time.thread_time), Stopwatch(time.thread_time)
    lookup, poisson = Stopwatch(), Stopwatch()
    differences = []
    reconstructor.reconstruct(images[0])  # warm-up: first-touch page faults, FFT plans
    straightforward(images[0])
    for frame in range(frames):
        image = images[frame % len(images)]
        result = fast(reconstructor.reconstruct, image)
        plain_height, _ = plain(straightforward, image)
        differences.append(float(np.abs(result.height_mm - plain_height).max()))
    for frame in range(frames):
        solver_input = lookup(reconstructor.gradients, images[frame % len(images)])
        poisson(solver.solve, *solver_input)

    return {
        "benchmark": "gelsight",
        "resolution": [calibration.image_shape[1], calibration.image_shape[0]],
        "frames": frames,
        "fps": _fps(fast.wall_s),
        "fps_straightforward": _fps(plain.wall_s),
        "speedup": round(statistics.median(plain.wall_s) / statistics.median(fast.wall_s), 2),
        "fps_cpu_time": _fps(fast.cpu_s),
        "fps_straightforward_cpu_time": _fps(plain.cpu_s),
        "median_ms": fast.milliseconds()["median_ms"],
        "median_ms_straightforward": plain.milliseconds()["median_ms"],
        "p90_ms": round(float(np.percentile(fast.wall_s, 90)) * 1e3, 3),
        "median_lookup_ms": lookup.milliseconds()["median_ms"],
        "median_poisson_ms": poisson.milliseconds()["median_ms"],
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
        "machine": machine(
            python=platform.python_version(), load_average_1min=round(os.getloadavg()[0], 2)
        ),
    }
