"""Score a cross-fitted detector table's detectors on a control zoo of clean models, and pool.

    python benchmarks/detector_control.py colorful-memory-40-control \\
        --base runs/detect/colorful-memory-40 --control runs/detect/colorful-memory-clean-long/zoo \\
        det/weights det/attribution det/behaviour det/stack exp/weights-shares

A zoo whose poisoned models trained longer than its clean ones lets any statistic that grows
with training rank it perfectly. The control is clean models trained at least as long as the
poisoned ones (``examples/zoo-colorful-memory-clean-long.toml``). For each detector folder
``DET`` under ``--base`` and its swapped twin ``DET-swap`` (``detector_table.py --crossfit``),
this scores the control (``rlbackdoors detect score``, resumable), counts the control models each
calls poisoned (p > 0.5), and pools the cross-fitted scores of the zoo's models with the control
models (mean of the two fits' probabilities; label clean): AUC, cross-entropy and Brier with
95 % bootstrap CIs. Writes ``benchmarks/results/detectors/NAME.json`` with the machine and its load.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import numpy as np

from _detect_cli import score

from rlbackdoors.bench.machine import machine_info
from rlbackdoors.detect.metrics import summarize_rows
from rlbackdoors.io import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]


def scores(det: Path, zoo: Path, name: str) -> list[dict]:
    """Per-model rows of ``detect score`` of ``det`` on ``zoo``: run every time (it resumes, so
    only models the control gained since are scored)."""
    return score(det, zoo, det / name, again=True, quiet=True)["models"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("name")
    parser.add_argument("detectors", nargs="+", help="detector folders under --base (each with a -swap twin)")
    parser.add_argument("--base", required=True, help="the detector table's folder (runs/detect/NAME)")
    parser.add_argument("--control", required=True, help="the control zoo of clean models")
    args = parser.parse_args()
    base, control = Path(args.base), Path(args.control)
    results = {}
    for det in args.detectors:
        folds = [base / det, base / f"{det}-swap"]
        zoo_rows = [r for fold in folds for r in json.loads((fold / "score-test" / "score.json").read_text())["models"]]
        fold_rows = [{r["model"]: r for r in scores(fold, control, "score-control")} for fold in folds]
        if any(r["label"] for rows in fold_rows for r in rows.values()):
            sys.exit(f"detector_control: {control} holds a poisoned model; a control is clean models only")
        common = sorted(set(fold_rows[0]) & set(fold_rows[1]))  # a model may converge between the two scorings
        by_model = {m: [rows[m]["probability"] for rows in fold_rows] for m in common}
        called = [sum(by_model[m][i] > 0.5 for m in common) for i in range(2)]
        pooled = summarize_rows(zoo_rows + [{"probability": float(np.mean(v)), "label": 0} for v in by_model.values()])
        results[det] = {
            "zoo_models": len(zoo_rows),
            "control_models": len(by_model),
            "control_called_poisoned": {"fit on train": called[0], "fit on test": called[1]},
            "control_median_probability": [float(np.median([v[i] for v in by_model.values()])) for i in range(2)],
            **{k: pooled[k] for k in ("auc", "ce", "brier")},
        }
        r = results[det]
        print(
            f"{det}: control {r['control_models']} clean, called poisoned {called[0]} / {called[1]}; "
            f"with the zoo's {len(zoo_rows)}: AUC {r['auc']['value']:.3f} CE {r['ce']['value']:.3f} Brier {r['brier']['value']:.3f}"
        )
    out = ROOT / "benchmarks" / "results" / "detectors" / f"{args.name}.json"
    summary = {"command": " ".join(sys.argv[1:]), "detectors": results, "machine": machine_info(), "loadavg": os.getloadavg()}
    atomic_write_text(out, json.dumps(summary, indent=2) + "\n")
    print(f"-> {out}")


if __name__ == "__main__":
    main()
