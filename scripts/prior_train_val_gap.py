"""How far a shape net fits its training shapes beyond the held-out ones: voxel IoU on true and
predicted sketches, on 512 training views (spread over the split) and 512 validation views of
the same seeded split the training used. A small gap says more data of the same kind would not
help; the net underfits (docs/prior.md, "The ~0.64 plateau"). Run from the repository root:

    .venv/bin/python scripts/prior_train_val_gap.py logs/data/object_frame \
        logs/train/object_frame/shape_on_predicted/shape.pt \
        logs/train/object_frame/sketch/sketch.pt --json logs/eval/train_val_gap.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from models.prior.dataset import SketchVoxelDataset, split_by_shape
from models.prior.networks import ShapeNet, SketchNet, get_preset
from models.prior.training import TrainConfig, evaluate, load_weights


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path)
    parser.add_argument("shape_weights", type=Path)
    parser.add_argument("sketch_weights", type=Path)
    parser.add_argument("--views", type=int, default=512)
    parser.add_argument("--seed", type=int, default=0, help="the training run's split seed")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    preset = get_preset("cpu")
    dataset = SketchVoxelDataset(args.data)
    train_views, val_views = split_by_shape(dataset, 0.05, args.seed)
    shape, sketch = ShapeNet(preset), SketchNet(preset)
    load_weights(shape, args.shape_weights)
    load_weights(sketch, args.sketch_weights)
    config = TrainConfig(stage="shape", data_dirs=(str(args.data),), out_dir="", batch_size=16)
    step = max(1, len(train_views) // args.views)
    spread = train_views[::step][: args.views]
    device = torch.device("cpu")
    result = {
        "shape_weights": str(args.shape_weights),
        "train": evaluate(shape, config, dataset, spread, device, sketch),
        "val": evaluate(shape, config, dataset, val_views[: args.views], device, sketch),
    }
    text = json.dumps(result, indent=2)
    print(text)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(text + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
