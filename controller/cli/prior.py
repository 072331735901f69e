"""`touchshape data build`, `train sketch|shape|calibrate` and `eval prior`: the shape priors'
training data, networks and evaluation."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

from controller.cli.output import print_json
from controller.config import load_config

if TYPE_CHECKING:
    from controller.config import Config
    from models.prior.evaluation import BenchCamera


def add_commands(groups: argparse._SubParsersAction) -> None:
    """Add the `data build`, `train sketch|shape|calibrate` and `eval prior` commands."""
    from models.families import SHAPE_GROUPS
    from models.procedural import CATEGORIES

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
        choices=SHAPE_GROUPS,
        metavar="NAME",
        help="procedural categories and shape families (default: the 14 categories; 'box' = "
        f"the box family; families: {', '.join(SHAPE_GROUPS[len(CATEGORIES) + 1 :])})",
    )
    build.add_argument(
        "--frame",
        choices=("object", "fixed"),
        default="object",
        help="grid of each view: fitted to the object (default) or the fixed cube on the "
        "object point",
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
            f"multi-GPU: torchrun --nproc_per_node 4 -m controller.cli.main train {stage} ...",
        )
        parser.add_argument(
            "--data",
            type=Path,
            nargs="+",
            required=True,
            help="dataset folders, trained on together",
        )
        parser.add_argument("--out", type=Path, required=True, help="checkpoints and metrics")
        parser.add_argument("--preset", default="cpu", choices=("cpu", "cpu_wide", "paper"))
        parser.add_argument("--epochs", type=int, default=10)
        parser.add_argument("--batch-size", type=int, default=16)
        parser.add_argument("--lr", type=float, default=None, help="default: the paper's")
        parser.add_argument(
            "--lr-decay-epochs",
            type=int,
            nargs="*",
            default=[],
            help="multiply the learning rate by --lr-decay-factor from each of these epochs on",
        )
        parser.add_argument("--lr-decay-factor", type=float, default=0.1)
        parser.add_argument(
            "--max-minutes",
            type=float,
            default=None,
            help="stop after this much training time (resume continues)",
        )
        parser.add_argument(
            "--checkpoint",
            type=Path,
            default=None,
            help="the run's float16 checkpoint, resumed from when it exists (default: "
            "OUT/checkpoint.pt; the object-frame recipe keeps it in training_state/)",
        )
        parser.add_argument(
            "--checkpoint-every", type=int, default=200, help="steps between checkpoints"
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
                "--predicted-sketch-prob",
                type=float,
                default=0.0,
                help="fraction of samples whose input is the --sketch-weights net's prediction",
            )
            parser.add_argument(
                "--sensor-depth-prob",
                type=float,
                default=0.5,
                help="fraction of samples with simulated Kinect depth",
            )
            parser.add_argument(
                "--sensor-normals",
                action="store_true",
                help="samples with Kinect depth also take its normals where known (as RGB-D "
                "inference does)",
            )
        parser.set_defaults(handler=train_network, stage=stage)

    calibrate = train_commands.add_parser(
        "calibrate",
        help="Platt-calibrate a shape net's voxel probabilities on predicted sketches",
        epilog="example: touchshape train calibrate --data logs/data/general "
        "--sketch-weights logs/train/general_sketch/sketch.pt "
        "--shape-weights logs/train/general_shape/shape.pt "
        "--out logs/train/general_shape/shape_calibrated.pt",
    )
    calibrate.add_argument(
        "--data", type=Path, nargs="+", required=True, help="dataset folders (as trained on)"
    )
    calibrate.add_argument("--sketch-weights", type=Path, required=True)
    calibrate.add_argument("--shape-weights", type=Path, required=True)
    calibrate.add_argument("--out", type=Path, required=True, help="calibrated shape weights")
    calibrate.add_argument("--preset", default="cpu", choices=("cpu", "cpu_wide", "paper"))
    calibrate.add_argument("--samples", type=int, default=256, help="views to fit / to report")
    calibrate.add_argument("--seed", type=int, default=0, help="train/val split seed")
    calibrate.add_argument("--threads", type=int, default=None, help="torch CPU threads")
    calibrate.set_defaults(handler=calibrate_shape)

    evaluate = groups.add_parser("eval", help="evaluate models on the simulated bench")
    eval_commands = evaluate.add_subparsers(dest="command", required=True)
    prior = eval_commands.add_parser(
        "prior",
        help="render objects on the bench, predict voxels, report IoU / Chamfer (JSON)",
        epilog="examples:\n  touchshape eval prior --views 4 --json logs/eval_prior_rgb.json\n"
        "  touchshape eval prior --input rgbd --views 4 --json logs/eval_prior_rgbd.json\n"
        "  touchshape eval prior --objects my.obj other.stl --views 8 --json logs/mine.json\n"
        "  touchshape eval prior --prior box --categories box --json logs/eval_box.json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    prior.add_argument("--config", type=Path, default=None, help="TOML config (camera, prior)")
    prior.add_argument(
        "--objects",
        nargs="+",
        type=Path,
        default=None,
        help="mesh files (default: held-out procedural shapes)",
    )
    prior.add_argument("--up-axis", default="z", help="up axis of the mesh files (y: ShapeNet)")
    prior.add_argument(
        "--fit-size",
        type=float,
        default=None,
        help="scale mesh files to this largest extent, metres",
    )
    prior.add_argument(
        "--categories",
        nargs="+",
        default=list(CATEGORIES),
        choices=SHAPE_GROUPS,
        metavar="NAME",
        help="held-out procedural categories or shape families (default: the 14 categories)",
    )
    prior.add_argument("--shapes-per-category", type=int, default=5)
    prior.add_argument(
        "--size-range",
        nargs=2,
        type=float,
        metavar=("LOW", "HIGH"),
        default=None,
        help="scale each held-out shape to a largest extent in this range, metres "
        "(e.g. 0.03 0.06: the small objects)",
    )
    prior.add_argument(
        "--input",
        choices=("auto", "rgb", "rgbd"),
        default="auto",
        help="auto: RGB-D where the camera gives depth (the bench does), as a session starts",
    )
    prior.add_argument(
        "--no-symmetry", action="store_true", help="RGB-D without the symmetry completion"
    )
    prior.add_argument(
        "--pose-fit", action="store_true", help="RGB-D: fit the prior's pose to the depth first"
    )
    prior.add_argument("--views", type=int, default=4, help="random object yaws per object")
    prior.add_argument(
        "--prior",
        default=None,
        help="prior name, or 'auto' to choose among all priors per view (default: the config's)",
    )
    prior.add_argument("--preset", default=None, help="network preset (default: the config's)")
    prior.add_argument("--weights-dir", default=None, help="default: the config's / shipped")
    prior.add_argument("--seed", type=int, default=0, help="view seed")
    prior.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    prior.set_defaults(handler=eval_prior)


def data_build(args: argparse.Namespace) -> int:
    from models.prior.dataset import BuildSpec, ViewRecipe, build_dataset
    from models.prior.networks import get_preset

    config = load_config(None)
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
        frame=args.frame,
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
    from models.prior.training import TrainConfig, train

    config = TrainConfig(
        stage=args.stage,
        data_dirs=tuple(map(str, args.data)),
        out_dir=str(args.out),
        preset=args.preset,
        epochs=args.epochs,
        batch_size=args.batch_size,
        learning_rate=args.lr,
        lr_decay_epochs=tuple(args.lr_decay_epochs),
        lr_decay_factor=args.lr_decay_factor,
        max_minutes=args.max_minutes,
        checkpoint=None if args.checkpoint is None else str(args.checkpoint),
        checkpoint_every_steps=args.checkpoint_every,
        seed=args.seed,
        init_weights=args.init,
        sketch_weights=getattr(args, "sketch_weights", None),
        positive_weight=getattr(args, "positive_weight", 1.0),
        sensor_depth_prob=getattr(args, "sensor_depth_prob", 0.5),
        sensor_normals=getattr(args, "sensor_normals", False),
        predicted_sketch_prob=getattr(args, "predicted_sketch_prob", 0.0),
        augment=not args.no_augment,
        threads=args.threads,
    )
    print_json(train(config))
    return 0


def calibrate_shape(args: argparse.Namespace) -> int:
    import torch

    from models.metrics import voxel_iou
    from models.prior.dataset import SketchVoxelDataset, split_by_shape
    from models.prior.networks import ShapeNet, SketchNet, get_preset
    from models.prior.platt import PlattScaling, predicted_logits
    from models.prior.training import load_weights, save_weights

    if args.threads:
        torch.set_num_threads(args.threads)
    preset = get_preset(args.preset)
    sketch, shape = SketchNet(preset), ShapeNet(preset)
    load_weights(sketch, args.sketch_weights)
    load_weights(shape, args.shape_weights)
    dataset = SketchVoxelDataset(args.data)
    train_idx, val_idx = split_by_shape(dataset, 0.05, args.seed)

    def spread(indices: list[int]) -> list[int]:
        step = max(1, len(indices) // args.samples)
        return indices[::step][: args.samples]

    logits, truth = predicted_logits(sketch, shape, dataset, spread(train_idx))
    platt = PlattScaling.fit(logits, truth)
    tuned = platt.with_iou_offset(logits, truth)
    del logits, truth
    val_logits, val_truth = predicted_logits(sketch, shape, dataset, spread(val_idx))
    result = {
        "scale": platt.scale,
        "platt_offset": platt.offset,
        "offset": tuned.offset,
        "val_views": len(val_truth),
        "val_iou_before": voxel_iou(torch.sigmoid(val_logits), val_truth),
        "val_iou_after": voxel_iou(torch.sigmoid(tuned.apply(val_logits)), val_truth),
    }
    tuned.fold_into(shape)
    save_weights(shape, "shape", args.preset, args.out)
    print_json(result, None)
    return 0


def evaluation_camera(config: Config) -> BenchCamera:
    """The config's RGB-D camera and scene, as the prior's evaluation renders them."""
    from models.camera import CameraIntrinsics
    from models.prior.evaluation import BenchCamera

    camera = config.cameras.rgbd
    return BenchCamera(
        intrinsics=CameraIntrinsics.kinect_v2_colour(camera.colour_scale),
        pose_world_camera=camera.pose_world_camera(),
        object_albedo_rgb=config.sim.object_albedo_rgb,
        table_size_m=config.sim.table_size_m,
    )


def eval_prior(args: argparse.Namespace) -> int:
    from controller.perception.learned import vision_settings
    from models.prior.auto import AUTO
    from models.prior.evaluation import EvalObject, evaluate_prior, held_out_objects
    from models.prior.shape_prior import ShapePrior, available_priors
    from models.shapes import load_mesh_file

    config = load_config(args.config)
    models = dataclasses.replace(
        config.models,
        prior=args.prior or config.models.prior,
        preset=args.preset or config.models.preset,
        weights_dir=args.weights_dir or config.models.weights_dir,
    )
    if models.prior == AUTO:
        names = sorted(
            name
            for name, specs in available_priors(models.weights_dir or None).items()
            if models.preset in {spec.preset for spec in specs}
        )
    else:
        names = [models.prior]
    priors = {
        name: ShapePrior.from_config(dataclasses.replace(models, prior=name)) for name in names
    }
    if args.objects:
        objects = [
            EvalObject(
                path.stem,
                "file",
                load_mesh_file(path, up_axis=args.up_axis, fit_max_extent_m=args.fit_size),
            )
            for path in args.objects
        ]
    else:
        size = tuple(args.size_range) if args.size_range else None
        objects = held_out_objects(args.categories, args.shapes_per_category, size_range_m=size)
    result = evaluate_prior(
        priors,
        objects,
        evaluation_camera(config),
        views=args.views,
        input_mode="rgbd" if args.input == "auto" else args.input,
        settings=vision_settings(models, pose_fit=args.pose_fit, symmetry=not args.no_symmetry),
        seed=args.seed,
    )
    print_json(result, args.json)
    return 0


def main(argv: list[str] | None = None) -> int:
    """The prior commands alone: `python -m controller.cli.prior train shape ...`. They need
    torch and the geometry libraries only, so a training machine without the robot stack (no
    Zenoh, Rerun or ur-rtde: a lent GPU, a cluster node) runs the same recipe."""
    import logging

    parser = argparse.ArgumentParser(prog="python -m controller.cli.prior")
    add_commands(parser.add_subparsers(dest="group", required=True, metavar="COMMAND"))
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    return args.handler(args)


if __name__ == "__main__":
    raise SystemExit(main())
