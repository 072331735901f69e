"""Latency of the touch loop's two model steps: policy selection and one refinement.

Each figure is the median of ``repeats`` runs after a warm-up run, in wall-clock and CPU seconds
(:class:`controller.benchmarks.timing.Stopwatch`). ``python -m controller.benchmarks.touch_latency``
prints :func:`latency_figures` for untrained ``cpu`` (64^3) and ``paper`` (128^3) decoders
(docs/touch.md, Latency).
"""

from __future__ import annotations

import json
from collections.abc import Sequence

import numpy as np
import torch

from controller.benchmarks.timing import repeated
from models.geometry import VoxelGrid, frame_from_z_axis, make_transform
from models.prior.networks import PRESETS
from models.prior.shape_prior import ShapePrior
from models.touch.constraints import TouchResult, pad_grid_world, touch_constraints
from models.touch.policy import above_table_filter, select_touch
from models.touch.refinement import Decode, decode_volume, refine_latent

PAD_SIZE_M = (0.019, 0.014)


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
    result["select"] = repeated(lambda: select_touch(voxels, grid, feasible), repeats).medians()
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
    result["refine"] = repeated(
        lambda: refine_latent(decode, latent, constraints, learning_rate, iterations), repeats
    ).medians()
    return result


def latency_figures(
    prior: ShapePrior,
    latent: torch.Tensor | None,
    resolutions: Sequence[int],
    learning_rate: float,
    iterations: int,
) -> list[dict[str, object]]:
    """:func:`touch_latency` per resolution. The prior's own resolution uses its decoder and
    ``latent`` (an object's vision latent); another resolution uses an untrained decoder of the
    preset with that resolution (the refinement's cost does not depend on the weights; the
    selection's does, and v ~ 0.5 everywhere is its worst case)."""
    figures = []
    for resolution in resolutions:
        if resolution == prior.preset.voxel_resolution:
            decoder, decode, code = f"{prior.name} ({prior.preset.name})", prior.decode, latent
        else:
            presets = [p for p in PRESETS.values() if p.voxel_resolution == resolution]
            if not presets:
                raise ValueError(f"no network preset predicts {resolution}^3 voxels")
            other = ShapePrior.untrained(presets[0].name)
            decoder, decode, code = f"untrained {presets[0].name}", other.decode, None
        entry = touch_latency(
            resolution, decode, code, iterations=iterations, learning_rate=learning_rate
        )
        entry["decoder"] = decoder
        figures.append(entry)
    return figures


def main() -> None:
    """Print the latency JSON of untrained ``cpu`` (64^3) and ``paper`` (128^3) decoders."""
    prior = ShapePrior.untrained("cpu")
    print(json.dumps(latency_figures(prior, None, (64, 128), 1e-3, 10), indent=2))


if __name__ == "__main__":
    main()
