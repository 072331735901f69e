"""The table of scripts/eval_priors.sh: every prior on every held-out set, and the bars.

Reads ``<dir>/<prior>.<set>.json`` (written by ``touchshape eval prior --json``) and prints a
Markdown table: mean IoU, Chamfer (mm), F-score at 5 mm and median size error per prior and set,
the 14 paper categories apart from the generated families, how often ``auto`` chose each prior,
and whether ``auto`` is at least as good as the best single prior on the mean over all sets.

    .venv/bin/python scripts/summarise_prior_eval.py logs/eval/priors
"""

from __future__ import annotations

import json
import sys
from collections import Counter
from pathlib import Path

from models.prior.evaluation import summarise_rows
from models.procedural import CATEGORIES

SETS = ("procedural", "categories", "families", "small", "real")
"""'categories' is the part of 'procedural' made of the paper's 14 categories."""


def set_means(results: dict) -> dict[str, dict[str, float]]:
    """Mean figures per set of one prior's results (``{set: eval JSON}``)."""
    means: dict[str, dict[str, float]] = {}
    for name, result in results.items():
        means[name] = result["mean"]
        if name == "procedural":
            objects = [o for o in result["objects"] if o["category"] in CATEGORIES]
            if objects:
                means["categories"] = summarise_rows(objects)
    return means


def auto_choices(set_name: str, auto: dict, results: dict[str, dict[str, dict]]) -> str:
    """How often ``auto`` chose each prior, how often it chose the one of best IoU on that
    view (among the single priors evaluated on the same views), and the IoU of always choosing
    best (the oracle)."""
    views = [v for o in auto["objects"] for v in o.get("views", [])]
    chosen = Counter(v["prior"] for v in views)
    text = "chose " + ", ".join(f"{p} {n}" for p, n in sorted(chosen.items()))
    singles = {
        p: [v["iou"] for o in sets[set_name]["objects"] for v in o.get("views", [])]
        for p, sets in results.items()
        if p != "auto" and set_name in sets
    }
    singles = {p: ious for p, ious in singles.items() if len(ious) == len(views)}
    if not views or not singles:
        return text
    best = [max(singles, key=lambda p: singles[p][i]) for i in range(len(views))]
    right = sum(
        v["prior"] in singles and singles[v["prior"]][i] >= singles[best[i]][i]
        for i, v in enumerate(views)
    )
    oracle = sum(singles[best[i]][i] for i in range(len(views))) / len(views)
    return (
        f"{text}; the best single prior of the view {right}/{len(views)} times; "
        f"IoU {sum(v['iou'] for v in views) / len(views):.3f} vs oracle {oracle:.3f}"
    )


def main(folder: Path) -> None:
    results: dict[str, dict[str, dict]] = {}
    for path in sorted(folder.glob("*.*.json")):
        prior, set_name = path.stem.split(".", 1)
        results.setdefault(prior, {})[set_name] = json.loads(path.read_text())
    if not results:
        sys.exit(f"error: no <prior>.<set>.json files in {folder}")
    means = {prior: set_means(sets) for prior, sets in results.items()}
    sets = [s for s in SETS if any(s in m for m in means.values())]
    print("| prior | " + " | ".join(sets) + " | mean IoU over sets |")
    print("|---|" + "---|" * (len(sets) + 1))
    overall: dict[str, float] = {}
    for prior, prior_means in means.items():
        cells = []
        for s in sets:
            m = prior_means.get(s)
            cells.append(
                "-"
                if m is None
                else f"IoU {m['iou']:.3f}, CD {m['chamfer_mm']:.1f} mm, "
                f"F@5 {m['fscore_5mm']:.2f}, size {100 * m['size_error_median']:.0f} %"
            )
        # 'categories' is inside 'procedural': the mean over sets counts each view once.
        scored = [prior_means[s]["iou"] for s in sets if s != "categories" and s in prior_means]
        overall[prior] = sum(scored) / len(scored)
        print(f"| {prior} | " + " | ".join(cells) + f" | {overall[prior]:.3f} |")
    if "auto" in results:
        print()
        for set_name, result in results["auto"].items():
            print(f"auto on {set_name}: " + auto_choices(set_name, result, results))
        singles = {p: v for p, v in overall.items() if p != "auto"}
        if singles:
            best = max(singles, key=lambda p: singles[p])
            verdict = "holds" if overall["auto"] >= singles[best] else "fails"
            print(
                f"\nauto {overall['auto']:.3f} vs best single prior {best} {singles[best]:.3f} "
                f"(mean IoU over sets): {verdict}"
            )


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "logs/eval/priors"))
