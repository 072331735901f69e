"""Where the estimate from colour loses: the shape net given the true 2.5D sketches.

`touchshape eval prior --input rgb` on the same objects and views, with the sketch net's outputs
replaced, part by part, by the truth: each view's scene rendered again through the network's
crop camera (the same render that makes the training targets: the object's silhouette, its
nearness and its camera-frame normals). The silhouette replaced also fits the object frame (the
search crop's silhouette is the sketch net's too). What the shape net scores on the true sketches
bounds what any better sketch net could give from colour. Writes one JSON with each variant's
`eval prior` result (docs/prior.md, "Results: the shape net on true sketches").

    .venv/bin/python scripts/prior_true_sketches.py --objects logs/meshes/*.obj --up-axis z \
        --prior object_frame --views 2 --json logs/eval/true_sketches.json

Without --objects: held-out procedural shapes (`--categories`, `--shapes-per-category`; by
default those of scripts/eval_priors.sh's procedural set).
"""

from __future__ import annotations

import argparse
import copy
import json
from pathlib import Path

import numpy as np
import torch

import models.prior.evaluation as evaluation
from controller.cli.prior import evaluation_camera
from controller.config import load_config
from models.prior.evaluation import EvalObject, evaluate_prior, held_out_objects
from models.prior.shape_prior import ShapePrior
from models.prior.virtual_camera import GridCrop
from models.render import Scene, render
from models.shapes import load_mesh_file

PROCEDURAL = [
    "bag",
    "bottle",
    "bowl",
    "camera",
    "can",
    "cap",
    "keyboard",
    "earphone",
    "helmet",
    "jar",
    "knife",
    "laptop",
    "mug",
    "remote",
    "box",
    "superquadric",
    "revolved",
    "box_any",
    "primitive_union",
    "blob",
]
"""scripts/eval_priors.sh's procedural categories and families."""

VARIANTS = {
    "predicted": (),
    "true silhouette": ("silhouette",),
    "true silhouette and depth": ("silhouette", "depth"),
    "true sketches": ("silhouette", "depth", "normals"),
}
"""The parts of the sketch net's output replaced by the truth."""


class SceneRecorder:
    """Keeps the scene of the view `evaluate_prior` renders last (it renders each view once)."""

    def __init__(self) -> None:
        self.scene: Scene | None = None

    def __call__(self, scene: Scene, *args: object, **kwargs: object) -> object:
        self.scene = scene
        return render(scene, *args, **kwargs)  # type: ignore[arg-type]


def with_true_parts(
    prior: ShapePrior, parts: tuple[str, ...], recorder: SceneRecorder, pose: np.ndarray
) -> ShapePrior:
    """A copy of ``prior`` whose sketches have ``parts`` replaced by the view's truth."""
    if not parts:
        return prior
    replaced = copy.copy(prior)

    def sketches(colour_rgb: np.ndarray, crop: GridCrop, cache: object = None) -> dict:
        predicted = dict(ShapePrior.sketches(prior, colour_rgb, crop, None))
        assert recorder.scene is not None
        truth = render(recorder.scene, crop.intrinsics, pose)
        silhouette = torch.from_numpy(truth.silhouette.astype(np.float32))[None, None]
        if "silhouette" in parts:
            predicted["silhouette_logits"] = (2.0 * silhouette - 1.0) * 20.0
        if "depth" in parts:
            nearness = torch.from_numpy(crop.nearness(truth.depth_m).astype(np.float32))
            predicted["depth"] = nearness[None, None] * silhouette
        if "normals" in parts:
            normals = torch.from_numpy(truth.normals_camera.astype(np.float32))
            predicted["normals"] = normals.permute(2, 0, 1)[None] * silhouette
        return predicted

    replaced.sketches = sketches  # type: ignore[method-assign]
    return replaced


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", nargs="+", type=Path, help="mesh files (else procedural)")
    parser.add_argument("--categories", nargs="+", default=list(PROCEDURAL))
    parser.add_argument("--shapes-per-category", type=int, default=3)
    parser.add_argument("--up-axis", default="z")
    parser.add_argument("--prior", default="object_frame")
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, required=True)
    args = parser.parse_args()
    torch.set_num_threads(1)
    config = load_config(None)
    camera = evaluation_camera(config)
    prior = ShapePrior.load(args.prior)
    if args.objects:
        objects = [
            EvalObject(path.stem, "file", load_mesh_file(path, up_axis=args.up_axis))
            for path in args.objects
        ]
    else:
        objects = held_out_objects(args.categories, args.shapes_per_category)
    recorder = SceneRecorder()
    evaluation.render = recorder  # type: ignore[assignment]
    results = {}
    for name, parts in VARIANTS.items():
        variant = with_true_parts(prior, parts, recorder, camera.pose_world_camera)
        results[name] = evaluate_prior(
            {args.prior: variant},
            objects,
            camera,
            views=args.views,
            input_mode="rgb",
            seed=args.seed,
        )
        mean = results[name]["mean"]
        print(
            f"{name:28s} IoU {mean['iou']:.3f}  Chamfer {mean['chamfer_mm']:.1f} mm  "
            f"size error {100 * mean['size_error_median']:.0f} %"
        )
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"prior": args.prior, "variants": results}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
