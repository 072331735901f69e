"""Latency of the touch loop's two model steps: policy selection and one refinement.

The exploration benchmark calls :func:`touch_latency` per resolution (64^3 and 128^3 in the
issue) with the decoder it uses there. Each figure is the median over ``repeats`` runs after one
warm-up run, as wall-clock seconds and as this process's CPU seconds (all threads): on a shared
machine the wall clock includes time spent waiting for a core, the CPU time does not.

``python -m controller.benchmarks.touch_latency`` prints the JSON for untrained decoders of the ``cpu`` (64^3)
and ``paper`` (128^3) presets of :mod:`models.prior.networks`: the computation does not depend on the
weights.
"""

from __future__ import annotations

import json
import statistics
import time
from collections.abc import Callable

import numpy as np
import torch

from models.geometry import VoxelGrid, frame_from_z_axis, make_transform
from models.touch.constraints import TouchResult, pad_grid_world, touch_constraints
from models.touch.policy import above_table_filter, select_touch
from models.touch.refinement import Decode, decode_volume, refine_latent

PAD_SIZE_M = (0.019, 0.014)


def _timed(run: Callable[[], object], repeats: int) -> dict[str, float]:
    run()  # warm-up: caches, allocator, lazy initialisation
    wall, cpu = [], []
    for _ in range(repeats):
        wall_start, cpu_start = time.perf_counter(), time.process_time()
        run()
        wall.append(time.perf_counter() - wall_start)
        cpu.append(time.process_time() - cpu_start)
    return {"wall_s": statistics.median(wall), "cpu_s": statistics.median(cpu)}


def _soft_sphere(resolution: int) -> np.ndarray:
    """A blurry sphere filling 60 % of the grid: a stand-in vision estimate."""
    centres = np.arange(resolution) + 0.5
    i, j, k = np.meshgrid(centres, centres, centres, indexing="ij")
    radius = np.sqrt(
        (i - resolution / 2) ** 2 + (j - resolution / 2) ** 2 + (k - 0.4 * resolution) ** 2
    )
    blur = 1.5 * resolution / 64
    return (1.0 / (1.0 + np.exp((radius - 0.3 * resolution) / blur))).astype(np.float32)


def touch_latency(
    resolution: int,
    decode: Decode | None = None,
    latent: torch.Tensor | None = None,
    iterations: int = 10,
    learning_rate: float = 1e-3,
    repeats: int = 3,
    extent_m: float = 0.26,
) -> dict[str, object]:
    """Select and refine latency at one resolution, JSON-ready.

    Selection (with :func:`above_table_filter` at a 10 cm standoff) runs on ``decode(latent)``
    when a decoder is given (it must output ``resolution``^3), else on a soft sphere.
    Refinement (``iterations`` Adam steps) uses the constraints of one simulated touch at the
    selected target: the pad's rays at 1 mm spacing, contact on the plane through the target.
    Without a decoder only selection is timed. Pass the vision latent of a real object for
    representative figures: selection gets cheaper the more of the volume is confidently empty
    (docs/touch.md).
    """
    grid = VoxelGrid(resolution, extent_m)
    if decode is not None:
        latent = latent if latent is not None else torch.zeros(1, 200)
        with torch.no_grad():
            voxels = decode_volume(decode, latent).cpu().numpy()
        if voxels.shape[0] != resolution:
            raise ValueError(f"decoder outputs {voxels.shape[0]}^3, expected {resolution}^3")
    else:
        voxels = _soft_sphere(resolution)
    result: dict[str, object] = {"resolution": resolution, "torch_threads": torch.get_num_threads()}
    feasible = above_table_filter(standoff_m=0.1)
    result["select"] = _timed(lambda: select_touch(voxels, grid, feasible), repeats)
    candidate = select_touch(voxels, grid, feasible)
    if decode is None or candidate is None:
        return result
    direction = candidate.approach_direction_world
    pose_world_pad = make_transform(frame_from_z_axis(direction), candidate.target_world)
    contacts = pad_grid_world(pose_world_pad, PAD_SIZE_M, 0.001)
    touch = TouchResult.from_contact(contacts, direction, candidate.target_world - 0.1 * direction)
    constraints = touch_constraints(touch, grid)
    result["constraint_voxels"] = {
        "empty": len(constraints.empty),
        "occupied": len(constraints.occupied),
    }
    result["refine_iterations"] = iterations
    result["refine"] = _timed(
        lambda: refine_latent(decode, latent, constraints, learning_rate, iterations), repeats
    )
    return result


def main() -> None:
    """Print the latency JSON for untrained ``cpu`` (64^3) and ``paper`` (128^3) decoders."""
    from models.prior.networks import VoxelDecoder, get_preset

    torch.manual_seed(0)
    report = []
    for preset_name in ("cpu", "paper"):
        preset = get_preset(preset_name)
        decoder = VoxelDecoder(preset).eval()
        latent = torch.randn(1, 200)

        def decode(z: torch.Tensor, decoder: VoxelDecoder = decoder) -> torch.Tensor:
            return torch.sigmoid(decoder(z))

        entry = touch_latency(preset.voxel_resolution, decode, latent)
        entry["preset"] = preset_name
        report.append(entry)
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
