"""Scale meshes from the pybullet wheel's data to everyday-object sizes, each in its most stable
resting pose on the table (z up, bottom centre at the origin): the unseen objects of the safety
benchmark's run in docs/benchmarks.md. They are not in the repository; get them with

    pip download --no-deps pybullet==3.2.7 -d /tmp/pb && cd /tmp/pb && unzip -q pybullet-*.whl
    python scripts/prepare_pybullet_meshes.py /tmp/pb/pybullet_data OUT_DIR
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import trimesh

SIZES_M = {
    "duck.obj": 0.12,
    "teddy2_VHACD_CHs.obj": 0.20,
    "bunny.obj": 0.15,
    "soccerball.obj": 0.07,
    "random_urdfs/000/000.obj": 0.05,
    "random_urdfs/003/003.obj": 0.04,
    "random_urdfs/004/004.obj": 0.25,
    "random_urdfs/156/156.obj": 0.10,
    "random_urdfs/284/284.obj": 0.18,
    "random_urdfs/552/552.obj": 0.08,
}
"""File in pybullet_data -> largest extent (metres)."""


def main(data_dir: Path, out_dir: Path) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, size_m in SIZES_M.items():
        mesh = trimesh.load(data_dir / name, force="mesh")
        mesh.apply_scale(size_m / mesh.extents.max())
        transforms, probabilities = trimesh.poses.compute_stable_poses(mesh.convex_hull)
        mesh.apply_transform(transforms[int(np.argmax(probabilities))])
        mesh.apply_scale(size_m / mesh.extents.max())
        low, high = mesh.bounds
        mesh.apply_translation([-(low[0] + high[0]) / 2, -(low[1] + high[1]) / 2, -low[2]])
        stem = Path(name).stem.split("_VHACD")[0].replace("teddy2", "teddy")
        stem = f"random_{stem}" if name.startswith("random_urdfs") else stem
        out = out_dir / f"{stem}_{round(size_m * 100)}cm.obj"
        mesh.export(out)
        print(out, np.round(mesh.extents, 3).tolist())


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
