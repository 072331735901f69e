"""CLI commands of the exploration benchmark: `bench explore` (issue 5, items 5 and 6) and
`bench explore-bounds` (how far touches can lower the error at all)."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from controller.cli.output import print_json
from controller.config import load_config

if TYPE_CHECKING:
    from controller.config import Config
    from models.prior.evaluation import EvalObject
    from models.prior.shape_prior import ShapePrior

METHODS = "active-prior,random-prior,active-direct,oracle-prior"
"""All methods, the default (``controller.benchmarks.explore.METHODS`` defines them)."""
EPILOG = """examples:
  touchshape bench explore --touches 10 --methods active-prior,random-prior,active-direct,\
oracle-prior --random-runs 3 --oracle-candidates 4 --json logs/bench_explore.json \
--plot docs/explore.png
  touchshape bench explore --objects my.obj --up-axis y --touches 5 --methods active-prior \
--json logs/mine.json
"""
BOUNDS_EPILOG = """examples:
  touchshape bench explore-bounds --touches 10 30 --workers 2 --json logs/bench_explore_bounds.json
  touchshape bench explore-bounds --touches 10 --oracle-candidates 8 --workers 2 \
--json logs/bench_explore_bounds_oracle.json
"""


def _object_arguments(parser: argparse.ArgumentParser) -> None:
    """--config and the objects: held-out categories or mesh files."""
    from models.shapes import CATEGORIES

    parser.add_argument("--config", type=Path, default=None, help="TOML config (default: sim)")
    parser.add_argument(
        "--objects",
        nargs="+",
        type=Path,
        default=None,
        help="mesh files (default: 14 held-out procedural objects, one per category)",
    )
    parser.add_argument(
        "--categories",
        nargs="+",
        default=list(CATEGORIES),
        choices=CATEGORIES,
        metavar="NAME",
        help="held-out procedural categories without --objects (default: the 14)",
    )
    parser.add_argument("--up-axis", default="z", help="up axis of the mesh files (y: ShapeNet)")
    parser.add_argument(
        "--fit-size", type=float, default=None, help="scale mesh files to this extent, metres"
    )


def _objects(args: argparse.Namespace) -> list[EvalObject]:
    from controller.benchmarks.explore import file_objects
    from models.prior.evaluation import held_out_objects

    if args.objects:
        return file_objects(args.objects, up_axis=args.up_axis, fit_size_m=args.fit_size)
    return held_out_objects(args.categories, 1)


def _load_prior(config: Config, name: str) -> ShapePrior:
    """The config's ``[models]`` prior, or the one named instead."""
    from models.prior.shape_prior import ShapePrior

    return ShapePrior.from_config(replace(config.models, prior=name))


def _run_and_print(
    run: Callable[..., dict[str, Any]],
    args: argparse.Namespace,
    config: Config,
    prior_name: str,
    settings: Any,
) -> dict[str, Any]:
    """``run`` (the benchmark or its bounds) on the objects the arguments name; prints the
    summary and writes the JSON to ``--json``."""
    from controller.perception.learned import load_calibration

    result = run(
        config,
        _objects(args),
        settings,
        prior=_load_prior(config, prior_name),
        calibration=load_calibration(config),
        workers=args.workers,
    )
    print_json(result, args.json, shown=result["summary"])
    return result


def add_explore_benchmark_command(bench_commands: argparse._SubParsersAction) -> None:
    """Add `bench explore` and `bench explore-bounds`."""
    explore = bench_commands.add_parser(
        "explore",
        help="shape error vs number of touches per method on the simulated bench (JSON, plot)",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _object_arguments(explore)
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

    bounds = bench_commands.add_parser(
        "explore-bounds",
        help="how far touches can lower the Chamfer distance: floor, latent fit, ideal touches",
        epilog=BOUNDS_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _object_arguments(bounds)
    bounds.add_argument(
        "--touches", type=int, nargs="+", default=[10, 30], help="ideal touch counts reported"
    )
    bounds.add_argument("--fit-steps", type=int, default=300, help="Adam steps of the latent fit")
    bounds.add_argument(
        "--oracle-candidates",
        type=int,
        default=0,
        help="also ideal touches each chosen by the truth among this many targets (0: no)",
    )
    bounds.add_argument("--prior", default=None, help="prior name (default: the config's)")
    bounds.add_argument("--seed", type=int, default=0)
    bounds.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    bounds.add_argument("--workers", type=int, default=1, help="objects run in this many processes")
    bounds.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    bounds.set_defaults(handler=bench_explore_bounds)


def bench_explore(args: argparse.Namespace) -> int:
    import torch

    from controller.benchmarks.explore import (
        ExploreSettings,
        plot_curves,
        run_explore_benchmark,
        with_refinement,
    )

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
    result = _run_and_print(run_explore_benchmark, args, config, prior_name, settings)
    if args.plot is not None:
        plot_curves(result, args.plot)
    return 0


def bench_explore_bounds(args: argparse.Namespace) -> int:
    import torch

    from controller.benchmarks.explore_bounds import BoundsSettings, run_bounds

    torch.set_num_threads(args.threads)
    config = load_config(args.config)
    prior_name = args.prior or config.models.prior
    settings = BoundsSettings(
        touch_counts=tuple(args.touches),
        fit_steps=args.fit_steps,
        oracle_candidates=args.oracle_candidates,
        prior=prior_name,
        seed=args.seed,
    )
    _run_and_print(run_bounds, args, config, prior_name, settings)
    return 0
