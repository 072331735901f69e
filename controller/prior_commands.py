"""CLI commands of the shape priors: `data build`, `train`, `eval prior`, `bench prior`."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from controller.config import load_config


def _write_json(result: dict, path: Path | None) -> None:
    text = json.dumps(result, indent=2)
    print(text)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text + "\n")


def add_prior_commands(
    groups: argparse._SubParsersAction, bench_commands: argparse._SubParsersAction
) -> None:
    """Add the `data build`, `train sketch|shape`, `eval prior` and `bench prior` commands."""
    from models.dataset import ALL_CATEGORIES
    from models.shapes import CATEGORIES

    data = groups.add_parser("data", help="training data for the shape priors")
    data_commands = data.add_subparsers(dest="command", required=True)
    build = data_commands.add_parser(
        "build",
        help="render shapes into sharded training data (RGB, sketches, voxels) with a manifest",
        epilog="examples:\n  touchshape data build --out logs/data/general "
        "--shapes-per-category 80 --views 6 --seed 0\n  touchshape data build --out "
        "logs/data/shapenet --source ~/ShapeNetCore.v2 --shapes-per-category 100 --views 20",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    build.add_argument("--out", type=Path, required=True, help="dataset folder (resumable)")
    build.add_argument(
        "--source",
        default="procedural",
        help="'procedural' or a ShapeNetCore-style folder (synset/model/models/"
        "model_normalized.obj, y up)",
    )
    build.add_argument(
        "--categories",
        nargs="+",
        default=list(CATEGORIES),
        choices=ALL_CATEGORIES,
        metavar="NAME",
        help="procedural categories (default: the 14; 'box' = the box family)",
    )
    build.add_argument("--shapes-per-category", type=int, default=40)
    build.add_argument("--views", type=int, default=6, help="views per shape")
    build.add_argument("--seed", type=int, default=0, help="first shape seed (< 1,000,000)")
    build.add_argument("--preset", default="cpu", help="network preset: image and voxel sizes")
    build.add_argument("--workers", type=int, default=2, help="parallel processes")
    build.set_defaults(handler=data_build)

    train = groups.add_parser("train", help="train the sketch or shape network")
    train_commands = train.add_subparsers(dest="command", required=True)
    for stage in ("sketch", "shape"):
        parser = train_commands.add_parser(
            stage,
            help=f"train the {'2.5D sketch' if stage == 'sketch' else '3D shape'} network",
            epilog=f"example: touchshape train {stage} --preset cpu --data logs/data/general "
            f"--out logs/train/general_{stage} --epochs 4\n"
            f"multi-GPU: torchrun --nproc_per_node 4 -m controller.cli train {stage} ...",
        )
        parser.add_argument("--data", type=Path, required=True, help="dataset folder")
        parser.add_argument("--out", type=Path, required=True, help="checkpoints and metrics")
        parser.add_argument("--preset", default="cpu", choices=("cpu", "paper"))
        parser.add_argument("--epochs", type=int, default=10)
        parser.add_argument("--batch-size", type=int, default=16)
        parser.add_argument("--lr", type=float, default=None, help="default: the paper's")
        parser.add_argument(
            "--max-minutes",
            type=float,
            default=None,
            help="stop after this much training time (resume continues)",
        )
        parser.add_argument("--seed", type=int, default=0)
        parser.add_argument("--threads", type=int, default=None, help="torch CPU threads")
        parser.add_argument("--init", default=None, help="start from these weights (.pt)")
        parser.add_argument("--no-augment", action="store_true", help="no colour/light jitter")
        if stage == "shape":
            parser.add_argument(
                "--sketch-weights",
                default=None,
                help="also validate on sketches predicted by these weights",
            )
            parser.add_argument(
                "--positive-weight",
                type=float,
                default=1.0,
                help="BCE weight of occupied voxels (1 = the paper's BCE)",
            )
            parser.add_argument(
                "--sensor-depth-prob",
                type=float,
                default=0.5,
                help="fraction of samples with simulated Kinect depth",
            )
        parser.set_defaults(handler=train_network, stage=stage)


def data_build(args: argparse.Namespace) -> int:
    from models.dataset import BuildSpec, ViewRecipe, build_dataset
    from models.networks import get_preset

    config = load_config(getattr(args, "config", None))
    camera = config.cameras.rgbd
    preset = get_preset(args.preset)
    recipe = ViewRecipe(
        image_size=preset.image_size,
        voxel_resolution=preset.voxel_resolution,
        grid_extent_m=config.voxel_grid.extent_m,
        camera_height_m=camera.height_m,
        camera_tilt_deg=camera.tilt_deg,
        camera_distance_m=camera.horizontal_distance_m,
        full_colour_scale=camera.colour_scale,
    )
    spec = BuildSpec(
        out_dir=str(args.out),
        source=args.source,
        categories=tuple(args.categories),
        shapes_per_category=args.shapes_per_category,
        views=args.views,
        seed=args.seed,
        recipe=recipe,
    )
    manifest = build_dataset(spec, workers=args.workers)
    views = sum(shard["views"] for shard in manifest["shards"])
    print(f"{len(manifest['shards'])} shards, {views} views in {args.out}")
    return 0


def train_network(args: argparse.Namespace) -> int:
    from models.training import TrainConfig, train

    config = TrainConfig(
        stage=args.stage,
        data_dir=str(args.data),
        out_dir=str(args.out),
        preset=args.preset,
        epochs=args.epochs,
        batch_size=args.batch_size,
        learning_rate=args.lr,
        max_minutes=args.max_minutes,
        seed=args.seed,
        init_weights=args.init,
        sketch_weights=getattr(args, "sketch_weights", None),
        positive_weight=getattr(args, "positive_weight", 1.0),
        sensor_depth_prob=getattr(args, "sensor_depth_prob", 0.5),
        augment=not args.no_augment,
        threads=args.threads,
    )
    print(json.dumps(train(config), indent=2))
    return 0
