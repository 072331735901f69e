"""What the exploration benchmark's JSON says: per-method summaries over objects, and the
paper's figure (docs/explore.md, JSON)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from controller.perception.learned import REPEAT_RADIUS_M
from models.prior.evaluation import _mean as finite_mean

METRICS = ("chamfer_mm", "fscore_5mm", "fscore_2mm", "iou", "touch_fidelity_mm")
"""The shape metrics of a curve, one value after each number of touches (the touch fidelity:
the median distance from the contact points so far to the surface, None before a contact)."""


TIMES = ("select_s", "refine_s", "robot_s")
"""Per touch: the policy's choice (with the planner's checks), the refinement, and the robot
time the session's planner gives the touch (``robot_time``; none for the oracle)."""


def robot_seconds_curve(result: dict) -> list[float | None]:
    """A result's robot time after 0..N touches (seconds; None after the touches it made, or
    for a method without robot times): the running sum of its ``robot_s``."""
    times = result.get("robot_s") or []
    if not times or any(t is None for t in times):
        return [None] * len(result["chamfer_mm"])
    total = [0.0, *np.cumsum(times).tolist()]
    return total + [None] * (len(result["chamfer_mm"]) - len(total))


def _mean_curve(curves: Sequence[Sequence[float | None]]) -> list[float | None]:
    """Pointwise mean over the finite values (None where there are none)."""
    return [finite_mean(values) for values in zip(*curves, strict=True)]


def mean_runs(runs: list[dict]) -> dict:
    """The mean curves of several seeded runs, with the runs themselves."""
    mean: dict[str, Any] = {key: _mean_curve([r[key] for r in runs]) for key in METRICS}
    made = min(r["touches_made"] for r in runs)  # timings: over the touches every run made
    for key in TIMES:
        mean[key] = _mean_curve([r.get(key, [])[:made] for r in runs])
    mean["touches_made"] = float(np.mean([r["touches_made"] for r in runs]))
    mean["runs"] = runs
    return mean


def change_pct(before: float | None, after: float | None) -> float | None:
    """The change from ``before`` to ``after``, % of ``before`` (None without a positive
    ``before`` and an ``after``)."""
    if before is None or after is None or not before > 0:
        return None
    return 100.0 * (after - before) / before


def _touch_statistics(results: Sequence[dict]) -> dict[str, Any]:
    """How the touches of some results ended: a GelSight imprint (contact points), a force stop
    without one (the housing or another rigid part met the object first, or a flat face filled
    the pad: only the sweep is known free) with what stopped it, or a miss; how much the
    refinements did: the median ratio of the touch loss after / before refining and the mean
    voxels flipped; and how many touches repeated an earlier one."""
    runs = [run for r in results for run in r.get("runs", [r])]
    contact = [c for run in runs for c in run["contact"]]
    imprint = [i for run in runs for i in run["imprint"]]
    # Results written before the bench told what stopped the fingers have no "stopped_by".
    stopped_by = [s for run in runs for s in run.get("stopped_by", [None] * len(run["imprint"]))]
    force_only_by = Counter(
        str(s)
        for c, i, s in zip(contact, imprint, stopped_by, strict=True)
        if c and not i and s is not None
    )
    ratios = [after / before for run in runs for before, after in run["touch_loss"] if before > 0]
    flipped = [f for run in runs for f in run["flipped"]]
    repeated = sum(_repeats(run["target"]) for run in runs)
    return {
        "imprint": int(sum(imprint)),
        "force_only": int(sum(c and not i for c, i in zip(contact, imprint, strict=True))),
        "miss": int(sum(not c for c in contact)),
        "force_only_stopped_by": dict(force_only_by.most_common()),
        "touch_loss_after_over_before_median": float(np.median(ratios)) if ratios else None,
        "flipped_voxels_mean": float(np.mean(flipped)) if flipped else None,
        "repeated_targets": repeated,
    }


def _repeats(targets: Sequence[Sequence[float]]) -> int:
    """Touches aimed within ``REPEAT_RADIUS_M`` of an earlier touch's target, same direction."""
    count = 0
    for n, touch in enumerate(targets):
        point, direction = np.asarray(touch[:3]), np.asarray(touch[3:])
        count += any(
            np.linalg.norm(point - np.asarray(earlier[:3])) < REPEAT_RADIUS_M
            and float(direction @ np.asarray(earlier[3:])) > 0.99
            for earlier in targets[:n]
        )
    return count


def summarise(objects: Sequence[dict], methods: Sequence[str], touches: int) -> dict:
    """Mean curves per method over objects, the mean % change of Chamfer after ``touches``
    touches versus none, median timings, and the ``bar``: does active-prior lower the Chamfer
    distance by 30 %, beat random-prior from 3 touches on and active-direct at the end (each
    where those methods ran)."""
    summary: dict[str, Any] = {"objects": len(objects), "touches": touches, "methods": {}}
    for method in methods:
        results = [obj["methods"][method] for obj in objects]
        entry: dict[str, Any] = {key: _mean_curve([r[key] for r in results]) for key in METRICS}
        entry["chamfer_change_pct"] = finite_mean(
            [change_pct(r["chamfer_mm"][0], r["chamfer_mm"][-1]) for r in results]
        )
        entry["empty_predictions_at_end"] = sum(r["chamfer_mm"][-1] is None for r in results)
        for key in TIMES:
            values = [v for r in results for v in r.get(key, []) if v is not None]
            entry[f"{key}_median"] = float(np.median(values)) if values else None
        entry["robot_s_cumulative"] = _mean_curve([robot_seconds_curve(r) for r in results])
        entry["touches"] = _touch_statistics(results)
        summary["methods"][method] = entry
    curves = {m: summary["methods"][m]["chamfer_mm"] for m in methods}
    bar: dict[str, Any] = {}
    if "active-fused" in curves:
        bar.update(_fused_bar(objects, summary["methods"], curves, touches))
    if "active-global" in curves:
        bar.update(_global_bar(objects, summary["methods"], curves, touches))
    if "active-prior" in curves:
        change = summary["methods"]["active-prior"]["chamfer_change_pct"]
        bar["active_prior_chamfer_change_pct"] = change
        bar["active_prior_lowers_chamfer_30pct"] = change is not None and change <= -30.0
        active = curves["active-prior"]

        def below(other: list[float | None], counts: Sequence[int]) -> bool:
            return all(
                active[n] is not None and other[n] is not None and active[n] < other[n]
                for n in counts
            )

        if "random-prior" in curves:
            bar["active_beats_random_from_3"] = below(
                curves["random-prior"], range(min(3, touches), touches + 1)
            )
        if "active-direct" in curves:
            bar["active_beats_direct_at_end"] = below(curves["active-direct"], [touches])
    summary["bar"] = bar
    return summary


def _fused_bar(
    objects: Sequence[dict], methods: dict[str, Any], curves: dict[str, list], touches: int
) -> dict[str, Any]:
    """The fused shape's bar: active-fused lowers the Chamfer distance by >= 30 %
    per object on average to <= 3.5 mm, no object ends > 1 % worse than its vision estimate,
    it beats random-fused at 3, 5 and N touches (by >= 5 % at N), and the touch fidelity's
    median is <= 0.3 mm after N touches."""
    entry = methods["active-fused"]
    changes = [
        change_pct(
            o["methods"]["active-fused"]["chamfer_mm"][0],
            o["methods"]["active-fused"]["chamfer_mm"][-1],
        )
        for o in objects
    ]
    worst = max((c for c in changes if c is not None), default=None)
    final = entry["chamfer_mm"][-1]
    fidelity = [
        v
        for o in objects
        for v in [o["methods"]["active-fused"]["touch_fidelity_mm"][-1]]
        if v is not None
    ]
    bar: dict[str, Any] = {
        "active_fused_chamfer_change_pct": entry["chamfer_change_pct"],
        "active_fused_final_chamfer_mm": final,
        "active_fused_worst_object_change_pct": worst,
        "active_fused_touch_fidelity_median_mm": float(np.median(fidelity)) if fidelity else None,
    }
    bar["active_fused_lowers_chamfer_30pct_to_3_5mm"] = (
        entry["chamfer_change_pct"] is not None
        and entry["chamfer_change_pct"] <= -30.0
        and final is not None
        and final <= 3.5
    )
    bar["no_object_worse_than_1pct"] = worst is not None and worst <= 1.0
    bar["touch_fidelity_within_0_3mm"] = bool(fidelity) and float(np.median(fidelity)) <= 0.3
    if "random-fused" in curves:
        active, random = curves["active-fused"], curves["random-fused"]
        counts = sorted({min(3, touches), min(5, touches), touches})
        bar["active_fused_vs_random_fused_pct"] = {
            n: change_pct(random[n], active[n]) for n in counts
        }
        bar["active_fused_beats_random_fused"] = (
            all(
                active[n] is not None and random[n] is not None and active[n] < random[n]
                for n in counts
            )
            and (change_pct(random[touches], active[touches]) or 0.0) <= -5.0
        )
    return bar


def _global_bar(
    objects: Sequence[dict], methods: dict[str, Any], curves: dict[str, list], touches: int
) -> dict[str, Any]:
    """The global update's bar (the default update): active-global lowers the Chamfer
    distance by >= 25 % per object on average with no object > 1 % worse, beats random-global
    by >= 5 % at N touches (where it ran), >= 90 % of its contacts leave an imprint, and the
    touch fidelity's median is <= 0.3 mm after N touches."""
    entry = methods["active-global"]
    runs = [o["methods"]["active-global"] for o in objects]
    changes = [change_pct(r["chamfer_mm"][0], r["chamfer_mm"][-1]) for r in runs]
    worst = max((c for c in changes if c is not None), default=None)
    fidelity = [r["touch_fidelity_mm"][-1] for r in runs if r["touch_fidelity_mm"][-1] is not None]
    counts = entry["touches"]
    contacts = counts["imprint"] + counts["force_only"]
    imprint_share = counts["imprint"] / contacts if contacts else None
    change = entry["chamfer_change_pct"]
    bar: dict[str, Any] = {
        "active_global_chamfer_change_pct": change,
        "active_global_worst_object_change_pct": worst,
        "active_global_imprint_share": imprint_share,
        "active_global_touch_fidelity_median_mm": float(np.median(fidelity)) if fidelity else None,
        "active_global_lowers_chamfer_25pct": change is not None and change <= -25.0,
        "active_global_no_object_worse_than_1pct": worst is not None and worst <= 1.0,
        "active_global_imprints_90pct": imprint_share is not None and imprint_share >= 0.9,
        "active_global_fidelity_within_0_3mm": bool(fidelity) and float(np.median(fidelity)) <= 0.3,
    }
    if "random-global" in curves:
        versus = change_pct(curves["random-global"][touches], curves["active-global"][touches])
        bar["active_global_vs_random_global_pct"] = versus
        bar["active_global_beats_random_global_5pct"] = versus is not None and versus <= -5.0
    return bar


def compare_methods(
    results: Sequence[dict],
    method: str,
    baseline: str,
    *,
    resamples: int = 10_000,
    seed: int = 0,
) -> dict[str, Any]:
    """``method`` against ``baseline`` after the last touch, pooled over benchmark JSONs
    (``run_explore_benchmark``'s, several seeds or sets): a pair is one object of one run
    (seed, input, prior, object) where both methods ran, in the same file or in two.

    Returns, JSON-ready: the pairs, the mean final Chamfer distance of each method and the
    bar's measure, the % change of the mean (``vs_baseline_pct``, also per seed), the geometric
    mean and median of the per-pair ratios, how many pairs the method ends lower, and 95 %
    bootstrap intervals of the two pooled figures. Why a bootstrap over objects: one object's
    runs of different seeds share its vision estimate and its hard places, so the objects, not
    the pairs, are the independent draws; an interval that holds 0 says the sets cannot tell
    the methods apart."""
    finals: dict[str, dict[tuple, float]] = {method: {}, baseline: {}}
    for result in results:
        for obj in result["objects"]:
            key = (result["seed"], obj.get("input"), obj.get("prior"), obj["name"])
            for name, found in finals.items():
                if name not in obj["methods"]:
                    continue
                if key in found:
                    raise ValueError(f"{name} on {key} appears twice: one run per seed and object")
                final = obj["methods"][name]["chamfer_mm"][-1]
                if final is None:
                    raise ValueError(f"{name} on {key} predicted nothing: no Chamfer distance")
                found[key] = float(final)
    keys = sorted(finals[method].keys() & finals[baseline].keys())
    if not keys:
        raise ValueError(f"no object ran both {method} and {baseline}")
    ours = np.array([finals[method][k] for k in keys])
    theirs = np.array([finals[baseline][k] for k in keys])
    log_ratio = np.log(ours / theirs)
    objects = sorted({k[3] for k in keys})
    members = [np.array([i for i, k in enumerate(keys) if k[3] == name]) for name in objects]
    rng = np.random.default_rng(seed)
    mean_change, geometric_change = [], []
    for _ in range(resamples):
        drawn = np.concatenate([members[i] for i in rng.integers(len(members), size=len(members))])
        mean_change.append(100.0 * (ours[drawn].mean() / theirs[drawn].mean() - 1.0))
        geometric_change.append(100.0 * (np.exp(log_ratio[drawn].mean()) - 1.0))
    seeds = sorted({k[0] for k in keys})
    per_seed = {}
    for run_seed in seeds:
        chosen = [i for i, k in enumerate(keys) if k[0] == run_seed]
        per_seed[str(run_seed)] = change_pct(theirs[chosen].mean(), ours[chosen].mean())
    return {
        "method": method,
        "baseline": baseline,
        "pairs": len(keys),
        "objects": len(objects),
        "seeds": seeds,
        "final_chamfer_mm_mean": {method: float(ours.mean()), baseline: float(theirs.mean())},
        "vs_baseline_pct": change_pct(float(theirs.mean()), float(ours.mean())),
        "vs_baseline_pct_ci95": np.percentile(mean_change, [2.5, 97.5]).tolist(),
        "vs_baseline_pct_per_seed": per_seed,
        "per_pair_geometric_mean_pct": float(100.0 * (np.exp(log_ratio.mean()) - 1.0)),
        "per_pair_geometric_mean_pct_ci95": np.percentile(geometric_change, [2.5, 97.5]).tolist(),
        "per_pair_median_pct": float(100.0 * (np.exp(np.median(log_ratio)) - 1.0)),
        "method_lower": int(np.sum(ours < theirs)),
        "pairs_table": [
            {"seed": k[0], "input": k[1], "prior": k[2], "object": k[3], method: a, baseline: b}
            for k, a, b in zip(keys, ours.tolist(), theirs.tolist(), strict=True)
        ],
    }


def plot_curves(result: dict, path: Path) -> None:
    """The paper's figure, mean Chamfer distance versus number of touches, one curve per
    method; beside it the same against the mean robot time spent (methods with robot times
    only). PNG, matplotlib Agg."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, (by_touch, by_time) = plt.subplots(1, 2, figsize=(11.0, 4.0), dpi=120, sharey=True)
    for method, entry in result["summary"]["methods"].items():
        curve = np.array([np.nan if v is None else v for v in entry["chamfer_mm"]])
        by_touch.plot(range(len(curve)), curve, marker="o", markersize=3, label=method)
        seconds = entry.get("robot_s_cumulative") or []
        seconds = np.array([np.nan if v is None else v for v in seconds])
        if seconds.size and np.isfinite(seconds).any():
            by_time.plot(seconds, curve[: seconds.size], marker="o", markersize=3, label=method)
    by_touch.set_xlabel("number of touches")
    by_touch.set_ylabel("mean Chamfer distance (mm)")
    by_time.set_xlabel("mean robot time (s, the session's planner)")
    figure.suptitle(
        f"{result['summary']['objects']} objects, prior {result['prior']} ({result['input']})"
    )
    for axes in (by_touch, by_time):
        axes.grid(alpha=0.3)
    by_touch.legend()
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    plt.close(figure)
