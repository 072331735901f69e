"""`touchshape bench sim|prior|gelsight|service|explore|compare|explore-bounds|safety`: the
benchmarks (controller.benchmarks), each printing its JSON (safety: a table) and writing it to
``--json``; `compare` pools `explore`'s JSON files."""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from controller.cli.output import print_json
from controller.cli.prior import evaluation_camera
from controller.config import load_config

if TYPE_CHECKING:
    from controller.config import Config
    from models.prior.evaluation import EvalObject
    from models.prior.shape_prior import ShapePrior

METHODS = (
    "active-global,random-global,efficient-global,active-fused,random-fused,efficient-fused,"
    "oracle-fused,active-prior,random-prior,active-direct,oracle-prior,oracle-global"
)
"""All methods (``controller.benchmarks.explore.METHODS`` defines them)."""
DEFAULT_METHODS = "active-global,random-global,efficient-global,active-fused,active-prior"
EPILOG = """examples:
  touchshape bench explore --touches 10 --methods active-fused,random-fused,active-prior,\
oracle-fused --random-runs 10 --workers 2 --json logs/bench_explore.json --plot docs/explore.png
  touchshape bench explore --objects my.obj --up-axis y --touches 5 --methods active-prior \
--json logs/mine.json
"""
BOUNDS_EPILOG = """examples:
  touchshape bench explore-bounds --touches 10 30 --workers 2 --json logs/bench_explore_bounds.json
  touchshape bench explore-bounds --touches 10 --oracle-candidates 8 --workers 2 \
--json logs/bench_explore_bounds_oracle.json
  touchshape bench explore-bounds --touches 10 --updates fused --json /tmp/bounds_fused.json
"""


def add_commands(groups: argparse._SubParsersAction) -> None:
    """Add the `bench` group."""
    bench = groups.add_parser("bench", help="performance benchmarks (JSON)")
    commands = bench.add_subparsers(dest="command", required=True)
    sim = commands.add_parser(
        "sim", help="time the bench's renderer and tactile simulation per frame"
    )
    sim.add_argument(
        "--config", type=Path, default=None, help="TOML config file (default: the sim bench)"
    )
    sim.add_argument("--frames", type=int, default=20, help="frames timed per measurement")
    sim.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    sim.set_defaults(handler=bench_sim)

    prior = commands.add_parser(
        "prior",
        help="time image -> voxels for both presets, training throughput, model sizes",
        epilog="example: touchshape bench prior --json logs/bench_prior.json",
    )
    prior.add_argument("--repeats", type=int, default=10, help="timed calls per measurement")
    prior.add_argument(
        "--weights-dir", type=Path, default=None, help="priors to time (default: shipped)"
    )
    prior.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    prior.set_defaults(handler=bench_prior)

    gelsight = commands.add_parser(
        "gelsight",
        help="reconstruction frames/s (lookup + Poisson, 640x480, one thread) vs a baseline",
        epilog="example: touchshape bench gelsight --json logs/bench_gelsight.json",
    )
    gelsight.add_argument("--frames", type=int, default=200, help="frames timed (median)")
    gelsight.add_argument(
        "--json", type=Path, nargs="?", const=None, help="also write the JSON to this file"
    )
    gelsight.set_defaults(handler=bench_gelsight)

    service = commands.add_parser(
        "service",
        help="trigger-to-capture latency, status latency and loop lag during a session,"
        " compute vs motion time, memory over sessions",
        epilog="example: touchshape bench service --status-hz 50 --sessions 20 --touches 3"
        " --json logs/bench_service.json",
    )
    service.add_argument("--config", type=Path, default=None, help="TOML config file")
    service.add_argument("--sessions", type=int, default=20, help="sessions in the memory series")
    service.add_argument("--touches", type=int, default=3, help="touches per session")
    service.add_argument(
        "--status-hz",
        type=float,
        default=50.0,
        help="poll status at this rate over Zenoh during one session: reply times and the"
        " event loop's lag (0: skip)",
    )
    service.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    service.set_defaults(handler=bench_service)

    explore = commands.add_parser(
        "explore",
        help="shape error vs number of touches per method on the simulated bench (JSON, plot)",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _object_arguments(explore)
    explore.add_argument("--touches", type=int, default=10, help="touches per method")
    explore.add_argument(
        "--methods",
        default=DEFAULT_METHODS,
        help=f"comma-separated, of: {METHODS} (default: {DEFAULT_METHODS})",
    )
    explore.add_argument("--random-runs", type=int, default=10, help="runs of each random method")
    explore.add_argument(
        "--oracle-candidates",
        type=int,
        default=4,
        help="the oracle tries this many active windows and as many random touches",
    )
    explore.add_argument("--prior", default=None, help="prior name (default: the config's)")
    explore.add_argument("--input", choices=("auto", "rgb", "rgbd"), default="auto")
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
    explore.add_argument(
        "--select-lag",
        action="store_true",
        help="choose each target from the estimate before the last refinement, as a session "
        "does while that refinement overlaps the arm's motion",
    )
    explore.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    explore.add_argument("--plot", type=Path, default=None, help="Chamfer vs touches PNG")
    explore.set_defaults(handler=bench_explore)

    compare = commands.add_parser(
        "compare",
        help="one method against another after the last touch, pooled over explore JSONs",
        epilog="example: touchshape bench compare logs/bench/active_s*.json "
        "logs/bench/random_s*.json --method active-global --baseline random-global",
    )
    compare.add_argument("results", type=Path, nargs="+", help="`bench explore` JSON files")
    compare.add_argument("--method", default="active-global")
    compare.add_argument("--baseline", default="random-global")
    compare.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    compare.set_defaults(handler=bench_compare)

    bounds = commands.add_parser(
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
    bounds.add_argument(
        "--updates",
        nargs="+",
        choices=("global", "fused", "prior"),
        default=["global", "fused", "prior"],
        help="shape updates refined by the ideal touches (default: all three)",
    )
    bounds.add_argument(
        "--input",
        choices=("auto", "rgb", "rgbd"),
        default="auto",
        help="camera input vision starts from (auto: RGB-D where the camera gives depth)",
    )
    bounds.add_argument("--prior", default=None, help="prior name (default: the config's)")
    bounds.add_argument("--seed", type=int, default=0)
    bounds.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    bounds.add_argument("--workers", type=int, default=1, help="objects run in this many processes")
    bounds.add_argument("--json", type=Path, default=None, help="also write the JSON here")
    bounds.set_defaults(handler=bench_explore_bounds)
    _add_safety(commands)


SAFETY_EPILOG = """examples:
  touchshape bench safety --categories mug --yaws 1 --touches 3 --json /tmp/safety_mug.json
  touchshape bench safety --yaws 2 --touches 10 --json logs/bench_safety.json
  touchshape bench safety --objects my.obj --up-axis y --fit-size 0.15 --json logs/mine.json
"""


def _add_safety(commands: argparse._SubParsersAction) -> None:
    from models.procedural import CATEGORIES

    safety = commands.add_parser(
        "safety",
        help="full sim sessions per object and yaw: faults, protective stops, and how near each"
        " rigid tool part came to the true object on every motion",
        epilog=SAFETY_EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    safety.add_argument("--config", type=Path, default=None, help="TOML config (default: sim)")
    safety.add_argument(
        "--categories",
        nargs="+",
        default=None,
        choices=CATEGORIES,
        metavar="NAME",
        help="procedural categories, as `explore --object` builds them (default: all 14 when"
        " no --objects)",
    )
    safety.add_argument("--objects", nargs="+", type=Path, default=None, help="mesh files")
    safety.add_argument("--up-axis", default="z", help="up axis of the mesh files (y: ShapeNet)")
    safety.add_argument(
        "--fit-size", type=float, default=None, help="scale mesh files to this extent, metres"
    )
    safety.add_argument("--yaws", type=int, default=1, help="sessions per object, random yaws")
    safety.add_argument("--touches", type=int, default=10, help="touch budget per session")
    safety.add_argument("--seed", type=int, default=0, help="draws the yaws and device noise")
    safety.add_argument("--input", choices=("auto", "rgb", "rgbd"), default="auto")
    safety.add_argument(
        "--logs", type=Path, default=None, help="keep the sessions' logs here (default: a temp dir)"
    )
    safety.add_argument("--json", type=Path, required=True, help="write the JSON here")
    safety.add_argument(
        "--merge",
        nargs="+",
        type=Path,
        default=None,
        metavar="JSON",
        help="run nothing: merge the sessions of earlier runs (e.g. objects split across "
        "processes, same seed) into one JSON with the totals",
    )
    safety.set_defaults(handler=bench_safety)


def bench_sim(args: argparse.Namespace) -> int:
    from controller.benchmarks.sim import benchmark_sim

    print_json(benchmark_sim(load_config(args.config), frames=args.frames), args.json)
    return 0


def bench_prior(args: argparse.Namespace) -> int:
    from controller.benchmarks.prior import benchmark_prior

    config = load_config(None)
    figures = benchmark_prior(
        evaluation_camera(config), repeats=args.repeats, weights_dir=args.weights_dir
    )
    print_json(figures, args.json)
    return 0


def bench_gelsight(args: argparse.Namespace) -> int:
    from controller.benchmarks.gelsight import benchmark_gelsight

    print_json(benchmark_gelsight(frames=args.frames), args.json)
    return 0


def bench_service(args: argparse.Namespace) -> int:
    import tempfile

    from controller.benchmarks.service import benchmark_service
    from controller.perception.learned import make_perception

    config = load_config(args.config)
    with tempfile.TemporaryDirectory(prefix="touchshape-bench-") as logs:
        result = benchmark_service(
            config,
            make_perception,
            Path(logs),
            sessions=args.sessions,
            touches=args.touches,
            status_hz=args.status_hz,
        )
    print_json(result, args.json)
    return 0


def _object_arguments(parser: argparse.ArgumentParser) -> None:
    """--config and the objects: held-out categories or mesh files."""
    from models.procedural import CATEGORIES

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


def _load_priors(config: Config, name: str) -> dict[str, ShapePrior]:
    """The prior ``name`` of the config's ``[models]`` weights by name, or for ``auto`` every
    prior of its preset (the choice is made per image)."""
    from models.prior.auto import AUTO
    from models.prior.shape_prior import ShapePrior, available_priors

    models = config.models
    names = [name]
    if name == AUTO:
        listed = available_priors(models.weights_dir or None)
        names = sorted(
            n for n, specs in listed.items() if models.preset in {s.preset for s in specs}
        )
    return {n: ShapePrior.from_config(replace(models, prior=n)) for n in names}


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
        priors=_load_priors(config, prior_name),
        calibration=load_calibration(config),
        workers=args.workers,
    )
    print_json(result, args.json, shown=result["summary"])
    return result


def bench_explore(args: argparse.Namespace) -> int:
    import torch

    from controller.benchmarks.explore import (
        ExploreSettings,
        run_explore_benchmark,
        with_refinement,
    )
    from controller.benchmarks.explore_summary import plot_curves

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
        select_lag=args.select_lag,
    )
    result = _run_and_print(run_explore_benchmark, args, config, prior_name, settings)
    if args.plot is not None:
        plot_curves(result, args.plot)
    return 0


def bench_compare(args: argparse.Namespace) -> int:
    from controller.benchmarks.explore_summary import compare_methods

    results = []
    for path in args.results:
        try:
            results.append(json.loads(path.read_text()))
        except (OSError, json.JSONDecodeError) as error:
            raise SystemExit(f"touchshape: cannot read {path}: {error}") from error
    try:
        comparison = compare_methods(results, args.method, args.baseline)
    except (KeyError, ValueError) as error:
        raise SystemExit(f"touchshape: cannot compare: {error}") from error
    shown = {k: v for k, v in comparison.items() if k != "pairs_table"}
    print_json(comparison, args.json, shown=shown)
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
        updates=tuple(args.updates),
        input_mode=args.input,
    )
    _run_and_print(run_bounds, args, config, prior_name, settings)
    return 0


def bench_safety(args: argparse.Namespace) -> int:
    """Exit status 1 when any session did not end done or the arm hit anything."""
    import contextlib
    import tempfile

    from controller.benchmarks.safety import (
        TABLE_HEADER,
        SafetySettings,
        format_row,
        format_table,
        run_safety_benchmark,
        safety_objects,
        summarise_safety,
    )
    from controller.perception.learned import make_perception
    from models.files import write_json_atomically

    if args.merge:
        runs = [json.loads(path.read_text()) for path in args.merge]
        merged = runs[0]["config"]
        settings = SafetySettings(
            touches=merged["touches"],
            yaws=merged["yaws"],
            seed=merged["seed"],
            input_mode=merged["input"],
        )
        rows = [row for run in runs for row in run["sessions_run"]]
        result = summarise_safety(rows, settings)
        result["merged_from"] = [str(path) for path in args.merge]
        write_json_atomically(args.json, result)
        print(format_table(result))
        print(f"JSON: {args.json}")
        return 0

    config = load_config(args.config)
    objects = safety_objects(
        args.categories, args.objects, up_axis=args.up_axis, fit_size_m=args.fit_size
    )
    settings = SafetySettings(
        touches=args.touches, yaws=args.yaws, seed=args.seed, input_mode=args.input
    )
    logs = (
        contextlib.nullcontext(str(args.logs))
        if args.logs is not None
        else tempfile.TemporaryDirectory(prefix="touchshape-safety-")
    )
    print(TABLE_HEADER, flush=True)
    with logs as logs_dir:
        result = run_safety_benchmark(
            config,
            objects,
            settings,
            perception_factory=make_perception,
            logs_dir=Path(logs_dir),
            progress=lambda row: print(format_row(row), flush=True),
        )
    result["logs"] = None if args.logs is None else str(args.logs)
    write_json_atomically(args.json, result)
    print(format_table(result))
    print(f"JSON: {args.json}")
    failed = len(result["sessions_run"]) - result["states"].get("done", 0)
    return 1 if failed or result["protective_stops"] else 0
