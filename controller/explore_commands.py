"""CLI command of the exploration benchmark: `bench explore` (issue 5, items 5 and 6)."""

from __future__ import annotations

import argparse
from pathlib import Path

from controller.config import load_config
from controller.output import print_json

METHODS = "active-prior,random-prior,active-direct,oracle-prior"
"""All methods, the default (``controller.explore_benchmark.METHODS`` defines them)."""
EPILOG = """examples:
  touchshape bench explore --touches 10 --methods active-prior,random-prior,active-direct,\
oracle-prior --random-runs 3 --oracle-candidates 4 --json logs/bench_explore.json \
--plot docs/explore.png
  touchshape bench explore --objects my.obj --up-axis y --touches 5 --methods active-prior \
--json logs/mine.json
"""


def add_explore_benchmark_command(bench_commands: argparse._SubParsersAction) -> None:
    """Add `bench explore`."""
    from models.shapes import CATEGORIES

    explore = bench_commands.add_parser(
        "explore",
        help="shape error vs number of touches per method on the simulated bench (JSON, plot)",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    explore.add_argument("--config", type=Path, default=None, help="TOML config (default: sim)")
    explore.add_argument(
        "--objects",
        nargs="+",
        type=Path,
        default=None,
        help="mesh files (default: 14 held-out procedural objects, one per category)",
    )
    explore.add_argument(
        "--categories",
        nargs="+",
        default=list(CATEGORIES),
        choices=CATEGORIES,
        metavar="NAME",
        help="held-out procedural categories without --objects (default: the 14)",
    )
    explore.add_argument("--up-axis", default="z", help="up axis of the mesh files (y: ShapeNet)")
    explore.add_argument(
        "--fit-size", type=float, default=None, help="scale mesh files to this extent, metres"
    )
    explore.add_argument("--touches", type=int, default=10, help="touches per method")
    explore.add_argument(
        "--methods",
        default=METHODS,
        help=f"comma-separated, of: {METHODS}",
    )
    explore.add_argument("--random-runs", type=int, default=10, help="runs of random-prior")
    explore.add_argument(
        "--oracle-candidates",
        type=int,
        default=4,
        help="the oracle tries this many active windows and as many random touches",
    )
    explore.add_argument("--prior", default=None, help="prior name (default: the config's)")
    explore.add_argument("--input", choices=("rgb", "rgbd"), default="rgb")
    explore.add_argument(
        "--refine-lr", type=float, default=None, help="refinement learning rate (config's)"
    )
    explore.add_argument(
        "--refine-iterations", type=int, default=None, help="iterations per touch (config's)"
    )
    explore.add_argument(
        "--refine-loss",
        choices=("sum", "balanced", "threshold"),
        default=None,
        help="touch loss form (config's models.refine_loss)",
    )
    explore.add_argument("--seed", type=int, default=0)
    explore.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    explore.add_argument(
        "--workers", type=int, default=1, help="objects run in this many processes"
    )
    explore.add_argument(
        "--no-timing", action="store_true", help="skip the 64^3 / 128^3 latency figures"
    )
    explore.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    explore.add_argument("--plot", type=Path, default=None, help="Chamfer vs touches PNG")
    explore.set_defaults(handler=bench_explore)


def bench_explore(args: argparse.Namespace) -> int:
    import torch

    from controller.explore_benchmark import (
        ExploreSettings,
        file_objects,
        plot_curves,
        run_explore_benchmark,
        with_refinement,
    )
    from controller.pipeline import load_calibration
    from models.evaluation import held_out_objects
    from models.prior import ShapePrior

    torch.set_num_threads(args.threads)
    config = with_refinement(
        load_config(args.config), args.refine_lr, args.refine_iterations, args.refine_loss
    )
    prior_name = args.prior or config.models.prior
    settings = ExploreSettings(
        touches=args.touches,
        methods=tuple(m.strip() for m in args.methods.split(",") if m.strip()),
        random_runs=args.random_runs,
        oracle_candidates=args.oracle_candidates,
        input_mode=args.input,
        prior=prior_name,
        seed=args.seed,
        timing_resolutions=() if args.no_timing else (64, 128),
    )
    if args.objects:
        objects = file_objects(args.objects, up_axis=args.up_axis, fit_size_m=args.fit_size)
    else:
        objects = held_out_objects(args.categories, 1)
    models = config.models
    prior = ShapePrior.load(
        prior_name,
        preset=models.preset,
        weights_dir=models.weights_dir or None,
        device=models.device,
    )
    result = run_explore_benchmark(
        config,
        objects,
        settings,
        prior=prior,
        calibration=load_calibration(config),
        workers=args.workers,
    )
    print_json(result, args.json, shown=result["summary"])
    if args.plot is not None:
        plot_curves(result, args.plot)
    return 0
