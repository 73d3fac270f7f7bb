"""Check fitted detectors on a second, independent zoo, on the models whose triggers the train split never used.

    python benchmarks/detector_validation.py NAME --train runs/detect/lavaworld-64/train \\
        --zoo runs/detect/lavaworld-64-validation/zoo DET_FOLDER [DET_FOLDER ...]

A detector change chosen after looking at one test split is not measured by that split any
more. This scores each fitted detector (``rlbackdoors detect score``, resumable) on every
converged model of a zoo built from another master seed, then reports AUC, cross-entropy and
Brier with 95 % bootstrap CIs on the subset whose triggers are not among the train split's
(read from the models' ``config.json`` by this script, never by a detector), and on all of
them, per trigger family too. ``--pool DATASET`` (repeatable: e.g. the train zoo's own test
split, a top-up zoo) also scores those datasets' held-out models and reports them pooled with the
zoo's, one held-out set of all their sizes. Writes ``benchmarks/results/detectors/NAME.json`` with the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from _detect_cli import score

from rlbackdoors.bench.machine import machine_info
from rlbackdoors.detect.dataset import list_models
from rlbackdoors.detect.metrics import summarize_rows
from rlbackdoors.io import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]


def trigger(folder: Path) -> str:
    return str(json.loads((folder / "config.json").read_text())["poison"]["trigger"])


def score_name(dataset: Path) -> str:
    """The name a dataset's scores are kept under in a detector's folder: a zoo folder is named
    after its parent (``runs/detect/X/zoo`` -> ``X``), a split after itself (``test``)."""
    return dataset.parent.name if dataset.name == "zoo" else dataset.name


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("name")
    parser.add_argument("detectors", nargs="+", help="fitted detector folders")
    parser.add_argument("--train", required=True, help="the dataset the detectors were fitted on")
    parser.add_argument("--zoo", required=True, help="the independent zoo to score")
    parser.add_argument("--pool", action="append", default=[], help="a dataset whose held-out models are pooled with the zoo's (repeatable)")
    args = parser.parse_args()
    seen = {trigger(m.folder) for m in list_models(args.train)}
    models = {m.name: m for m in list_models(args.zoo)}
    held_out = {name for name, m in models.items() if trigger(m.folder) not in seen}
    # (dataset, the name its scores are kept under, its held-out models); two datasets kept under one
    # name would read each other's scores, so that is refused.
    pools = [(p, score_name(Path(p)), {m.name for m in list_models(p) if trigger(m.folder) not in seen}) for p in args.pool]
    kept = [score_name(Path(args.zoo))] + [name for _, name, _ in pools]
    if len(set(kept)) < len(kept):
        parser.error(f"--zoo and --pool datasets must keep their scores under different names, got {kept}")
    results = {}
    for det in map(Path, args.detectors):
        out = det / f"score-{score_name(Path(args.zoo))}"
        scored = score(det, args.zoo, out, quiet=True)
        rows = scored["models"]
        families = sorted({r.get("trigger_family", "") for r in rows})
        results[str(det)] = {
            "detector": scored["detector"],
            "params": scored["params"],
            "held_out": summarize_rows([r for r in rows if r["model"] in held_out]),
            "all": summarize_rows(rows),
            "held_out_by_family": {f: summarize_rows([r for r in rows if r["model"] in held_out and r.get("trigger_family") == f]) for f in families},
            "seconds_per_model": scored["seconds_per_model"],
        }
        if args.pool:
            pooled = [r for r in rows if r["model"] in held_out]
            for path, name, names in pools:
                pooled += [r for r in score(det, path, det / f"score-{name}", quiet=True)["models"] if r["model"] in names]
            results[str(det)]["pooled"] = summarize_rows(pooled)
    summary = {
        "command": " ".join(sys.argv[1:]),
        "train": args.train,
        "zoo": args.zoo,
        "models": len(models),
        "held_out_models": len(held_out),
        "pool": args.pool,
        "pool_held_out_models": {name: len(names) for _, name, names in pools},
        "train_triggers": len(seen),
        "detectors": results,
        "machine": machine_info(),
        "loadavg": os.getloadavg(),
    }
    path = ROOT / "benchmarks" / "results" / "detectors" / f"{args.name}.json"
    atomic_write_text(path, json.dumps(summary, indent=2) + "\n")
    print(f"{len(held_out)} of {len(models)} models have triggers the train split never used")
    print("| detector | models | AUC [95% CI] | CE [95% CI] | Brier [95% CI] |\n|---|---|---|---|---|")
    for det, r in results.items():
        for label, m in (("held out", r["held_out"]), ("all", r["all"]), ("pooled", r.get("pooled"))):
            if m is None:
                continue
            cells = [f"{m[k]['value']:.3f} [{m[k]['ci'][0]:.3f}, {m[k]['ci'][1]:.3f}]" if m.get(k) and m[k]["ci"] else "–" for k in ("auc", "ce", "brier")]
            print(f"| {det} ({label}) | {m['n']} | {' | '.join(cells)} |")
    print(f"-> {path}")


if __name__ == "__main__":
    main()
