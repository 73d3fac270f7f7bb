"""Models trained by hand, scored by a benchmark's fitted baselines: does the headroom the table
claims hold for models that were never in its zoo?

    python benchmarks/score_by_hand.py runs/detect/benchmark-lavaworld --models runs/ft-s91 runs/clean-s91 ...

Each model folder (``rlbackdoors train``'s) goes through ``detect infer`` (TrojAI's one-model entry
point, as a performer would run it) under every fit the benchmark made (``det-held_out/NAME``: env
mix only; ``loo-ATTACK/det/NAME``: all but ATTACK), and its probability is placed among that fit's
own test scores: the share of its clean test models scored at least as high (a poisoned model there
looks clean) and of its poisoned ones scored at most as high. Per fit, the AUC of the by-hand
models alone (poisoned against clean; NaN with one label only): whether the detector tells them
apart, whatever its threshold. Writes ``BASE/by-hand.json`` (``--out``: elsewhere; ``models``: a
row per fit and model; ``fits``: the AUC per fit) and prints both tables; each model's ground truth
comes from its own ``ground_truth.csv``.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
from pathlib import Path

from _detect_cli import infer

from rlbackdoors.detect.metrics import auc
from rlbackdoors.io import atomic_write_text


def fits(base: Path) -> list[tuple[str, Path, Path]]:
    """(what it was fitted on, detector folder, the split it was fitted on) for every fit under
    ``base`` with a test score."""
    found = [(f"env mix only: {d.name}", d, base / "held-out" / "train") for d in sorted((base / "det-held_out").glob("*"))]
    found += [(f"all but {loo.name[4:]}: {d.name}", d, loo / "train") for loo in sorted(base.glob("loo-*")) for d in sorted((loo / "det").glob("*"))]
    return [f for f in found if (f[1] / "score-test" / "score.json").is_file() and f[1].name != "constant"]


def stage(folder: Path, where: Path) -> Path:
    """What a performer receives of a trained folder, as a zoo writes it: ``model.pt`` and
    ``reduced-config.json`` (architecture facts; train's config.json names the trigger and the
    label, and detectors refuse it)."""
    from rlbackdoors.zoo.job import COMPLETE_MARK, reduced_config

    where.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(folder / "model.pt", where / "model.pt")
    reduced = reduced_config(where, json.loads((folder / "config.json").read_text()))
    atomic_write_text(where / COMPLETE_MARK, json.dumps(reduced, indent=2, sort_keys=True) + "\n")
    return where


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("base", type=Path, help="a benchmark's run folder (runs/detect/NAME)")
    parser.add_argument("--models", nargs="+", type=Path, required=True, help="model folders trained by hand")
    parser.add_argument("--out", type=Path, help="where the JSON goes (default BASE/by-hand.json): one file per set of models")
    args = parser.parse_args()
    for folder in args.models:
        missing = [f for f in ("model.pt", "config.json", "ground_truth.csv") if not (folder / f).is_file()]
        if missing:
            sys.exit(f"score_by_hand: {folder} is not a trained model folder (no {', '.join(missing)}; rlbackdoors train writes them)")
    found = fits(args.base)
    if not found:
        sys.exit(f"score_by_hand: no fitted and scored detector under {args.base} (run benchmarks/detector_table.py first)")
    staged = {folder: stage(folder, args.base / "by-hand" / "models" / folder.name) for folder in args.models}
    truth = {folder: int((folder / "ground_truth.csv").read_text().strip()) for folder in args.models}
    rows = []
    for what, det, train in found:
        test = json.loads((det / "score-test" / "score.json").read_text())["models"]
        clean = [m["probability"] for m in test if m.get("probability") is not None and not m["label"]]
        poisoned = [m["probability"] for m in test if m.get("probability") is not None and m["label"]]
        for folder in args.models:
            p = infer(det, staged[folder], args.base / "by-hand" / train.parent.name / det.name / folder.name, train)
            rows.append(
                {
                    "fit": what,
                    "model": folder.name,
                    "poisoned": bool(truth[folder]),
                    "probability": p,
                    "clean_test_at_least_as_high": round(sum(c >= p for c in clean) / len(clean), 3) if clean else None,
                    "poisoned_test_at_most_as_high": round(sum(q <= p for q in poisoned) / len(poisoned), 3) if poisoned else None,
                }
            )
    per_fit = {what: auc([r["probability"] for r in rows if r["fit"] == what], [r["poisoned"] for r in rows if r["fit"] == what]) for what, _, _ in found}
    per_fit = {what: None if math.isnan(a) else round(a, 3) for what, a in per_fit.items()}  # JSON has no NaN
    atomic_write_text(args.out or args.base / "by-hand.json", json.dumps({"models": rows, "fits": per_fit}, indent=2) + "\n")
    print("| fit: detector | model | poisoned | probability | clean test models scored >= it | poisoned test models scored <= it |\n|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['fit']} | {r['model']} | {r['poisoned']} | {r['probability']:.3f} | {r['clean_test_at_least_as_high']} | {r['poisoned_test_at_most_as_high']} |"
        )
    print("\n| fit: detector | AUC of the by-hand models alone |\n|---|---|")
    for what, a in per_fit.items():
        print(f"| {what} | {'n/a (one label)' if a is None else f'{a:.3f}'} |")


if __name__ == "__main__":
    main()
