"""Lay sourced test meshes on the table in random resting poses and sizes: the safety set.

A real object is put down in any pose it can rest in, not only its most stable one, and objects
of one kind come in many sizes. For each mesh in ``--meshes`` (``scripts/source_test_meshes.py``
writes them to logs/meshes/) this draws ``--poses`` distinct resting poses among those trimesh's
``compute_stable_poses`` finds (uniformly, each with a resting probability of at least 2 %, so
the object does rest there), a size log-uniform in ``--sizes`` (largest extent) and writes

    OUT/<name>_p<k>_<size>cm.obj     z up, base on z = 0, bounding box centred on the z axis
    OUT/manifest.json               source mesh, pose index and its probability, size, extents

Seeded by ``--seed`` and the object's name, so a run on fewer objects repeats the same layouts.

    .venv/bin/python scripts/lay_test_meshes.py --meshes logs/meshes --out logs/meshes_laid
"""

from __future__ import annotations

import argparse
import json
import zlib
from pathlib import Path

import numpy as np
import trimesh

MIN_REST_PROBABILITY = 0.02


def resting_poses(mesh: trimesh.Trimesh, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Transforms that lay the mesh on z = 0 at rest, and their resting probabilities."""
    transforms, probabilities = trimesh.poses.compute_stable_poses(
        mesh, n_samples=400, threshold=0.0, sigma=0.0
    )
    keep = probabilities >= MIN_REST_PROBABILITY
    return transforms[keep], probabilities[keep]


def lay(mesh: trimesh.Trimesh, transform: np.ndarray, size_m: float) -> trimesh.Trimesh:
    laid = mesh.copy()
    laid.apply_transform(transform)
    laid.apply_scale(size_m / float(laid.extents.max()))
    low, high = laid.bounds
    laid.apply_translation([-(low[0] + high[0]) / 2, -(low[1] + high[1]) / 2, -low[2]])
    return laid


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--meshes", type=Path, default=Path("logs/meshes"))
    parser.add_argument("--out", type=Path, default=Path("logs/meshes_laid"))
    parser.add_argument("--poses", type=int, default=3, help="resting poses per object")
    parser.add_argument("--sizes", type=float, nargs=2, default=(0.04, 0.25), metavar=("LO", "HI"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    manifest = []
    for path in sorted(args.meshes.glob("*.obj")):
        mesh = trimesh.load(path, force="mesh")
        rng = np.random.default_rng((args.seed, zlib.crc32(path.stem.encode())))
        transforms, probabilities = resting_poses(mesh, args.seed)
        count = min(args.poses, len(transforms))
        chosen = rng.choice(len(transforms), size=count, replace=False)
        for k, index in enumerate(chosen):
            size_m = float(np.exp(rng.uniform(*np.log(args.sizes))))
            laid = lay(mesh, transforms[index], size_m)
            name = f"{path.stem}_p{k}_{size_m * 100:.0f}cm"
            laid.export(args.out / f"{name}.obj")
            manifest.append(
                {
                    "name": name,
                    "source": str(path),
                    "pose_index": int(index),
                    "rest_probability": round(float(probabilities[index]), 4),
                    "poses_found": len(transforms),
                    "size_m": round(size_m, 4),
                    "extents_m": np.round(laid.extents, 4).tolist(),
                    "watertight": bool(laid.is_watertight),
                }
            )
            print(f"{name:<28} pose {index} (p {probabilities[index]:.3f} of {len(transforms)})")
    (args.out / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    print(f"wrote {len(manifest)} meshes to {args.out}")


if __name__ == "__main__":
    main()
