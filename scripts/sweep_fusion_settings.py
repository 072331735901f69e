"""Offline sweep of the fused update's settings on recorded touches (docs/touch.md).

  python scripts/sweep_fusion_settings.py collect --out logs/fusion_sweep [--categories ...]
  python scripts/sweep_fusion_settings.py evaluate --out logs/fusion_sweep --policy active \
      --variants '{"gp35": {"support_m": 0.035}, "gp50": {"support_m": 0.05}}'

`collect` runs 10 touches per held-out object (seed 1,000,000) on the simulated bench with the
random and the active policy (the `prior` update chooses them, as `bench explore` would) and
pickles the touches, the vision estimate and the truth. `evaluate` fuses the first 3, 5 and 10
touches with each variant (``FusionSettings`` fields, plus ``latent_iters`` to refine the
latent first) and prints the Chamfer distance and its mean per-object change. The touches are
the same for every variant, so the sweep compares fusion alone.
"""

from __future__ import annotations

import argparse
import json
import pickle
from pathlib import Path

import numpy as np
import torch

from controller.benchmarks.explore import ExploreSettings, ObjectRun
from controller.config import load_config
from controller.perception.learned import load_calibration
from models.metrics import SURFACE_SAMPLES, sample_surface, surface_metrics
from models.prior.evaluation import held_out_objects
from models.prior.shape_prior import ShapePrior
from models.procedural import CATEGORIES
from models.touch.constraints import VoxelConstraints, touch_constraints
from models.touch.fused import FusedShape, FusionSettings, prior_surface
from models.touch.observations import observations_of
from models.touch.refinement import refine_latent

COUNTS = (3, 5, 10)


def collect(out: Path, categories: list[str]) -> None:
    config = load_config(None)
    prior = ShapePrior.load("general")
    out.mkdir(parents=True, exist_ok=True)
    for category in categories:
        obj = held_out_objects([category], 1)[0]
        settings = ExploreSettings(touches=10, methods=("random-prior",), random_runs=1)
        run = ObjectRun(config, load_calibration(config), prior, obj, settings)
        perception = run.perception(5)
        record = {
            "name": obj.name,
            "grid": run.grid,
            "vision_probabilities": run.vision.probabilities,
            "latent": run.vision.latent.numpy(),
            "true_points": run.true_points,
            "touches": {},
        }
        for policy in ("random", "active"):
            request = run.request(policy, "prior")
            estimate, outcomes = run.vision, []
            for touch in range(10):
                target = perception.select(estimate, request, outcomes, run.bench.allowed)
                trial = (
                    None
                    if target is None
                    else run.trial(perception, estimate, outcomes, target, request, (1, touch))
                )
                if trial is None:
                    break
                estimate = trial.estimate
                outcomes.append(trial.outcome)
            record["touches"][policy] = [o.touch for o in outcomes if o.touch is not None]
        run.close()
        (out / f"{obj.name}.pkl").write_bytes(pickle.dumps(record))
        print(obj.name, {k: len(v) for k, v in record["touches"].items()}, flush=True)


def evaluate(out: Path, policy: str, variants: dict[str, dict]) -> None:
    prior = ShapePrior.load("general")

    def chamfer(mesh, truth) -> float:
        return surface_metrics(sample_surface(mesh, SURFACE_SAMPLES, 11), truth).chamfer_mm

    rows = {}
    for path in sorted(out.glob("*.pkl")):
        record = pickle.loads(path.read_bytes())
        grid, truth = record["grid"], record["true_points"]
        touches = record["touches"][policy]
        row = {"vision": chamfer(prior_surface(record["vision_probabilities"], grid), truth)}
        for name, spec in variants.items():
            spec = dict(spec)
            iterations = spec.pop("latent_iters", 0)
            settings = FusionSettings(**spec)
            row[name] = []
            for count in COUNTS:
                voxels = record["vision_probabilities"]
                if iterations:  # as the pipeline refines: after every touch, all so far
                    vision = latent = torch.as_tensor(record["latent"])
                    for made in range(1, count + 1):
                        constraints = VoxelConstraints.none(grid.resolution)
                        for touch in touches[:made]:
                            constraints = constraints.merged(touch_constraints(touch, grid))
                        result = refine_latent(
                            prior.decode,
                            latent,
                            constraints,
                            learning_rate=3e-3,
                            iterations=iterations,
                            loss="threshold",
                            anchor_latent=vision,
                            anchor_weight=0.03,
                        )
                        latent = result.latent
                    voxels = result.voxels.numpy()
                fused = FusedShape.from_prior(
                    voxels, grid, observations_of(touches[:count]), settings
                )
                row[name].append(chamfer(fused.mesh(), truth))
        rows[record["name"]] = row
        print(
            record["name"],
            round(row["vision"], 2),
            {k: [round(x, 2) for x in v] for k, v in row.items() if k != "vision"},
            flush=True,
        )
    print(f"mean per-object change % after {COUNTS} touches; worst object at {COUNTS[-1]}")
    for name in variants:
        change = np.array(
            [[100 * (c - r["vision"]) / r["vision"] for c in r[name]] for r in rows.values()]
        )
        print(f"{name:24s} {np.round(change.mean(axis=0), 2)} worst {change[:, -1].max():.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("command", choices=["collect", "evaluate"])
    parser.add_argument("--out", type=Path, default=Path("logs/fusion_sweep"))
    parser.add_argument("--categories", nargs="+", default=list(CATEGORIES))
    parser.add_argument("--policy", choices=["random", "active"], default="active")
    parser.add_argument("--variants", default='{"default": {}}')
    args = parser.parse_args()
    if args.command == "collect":
        collect(args.out, args.categories)
    else:
        evaluate(args.out, args.policy, json.loads(args.variants))


if __name__ == "__main__":
    main()
