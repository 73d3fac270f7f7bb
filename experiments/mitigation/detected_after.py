"""Issue 82's last check: do the detectors score mitigated models as clean?

    python experiments/mitigation/detected_after.py runs/mitigated-envmix \
        --zoo datasets/benchmark-lavaworld-effect-envmix --fit datasets/benchmark-lavaworld-effect

Fits ``effect`` on the fit zoo's clean and env-mix models (no evasive variant: the paper's attack),
then scores every model the mitigation report names, before (the zoo's folder) and after (the
mitigated folder). Reports the AUC of before against after over the poisoned models (1.0: every
source scored above every mitigated model; the issue asks >= 0.9), and over the clean ones (0.5:
mitigation moved nothing the detector reads), with the mean probabilities. Labels are read from the
zoos' ground truth by this script alone. Writes the JSON next to the report, or to ``--json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from sklearn.metrics import roc_auc_score

from rlbackdoors.bench.machine import machine_info
from rlbackdoors.detect import load_detector
from rlbackdoors.detect.baselines.effect import EffectDetector
from rlbackdoors.detect.handle import open_model
from rlbackdoors.io import atomic_write_text


def fit_models(fit: Path) -> tuple[list, np.ndarray, list[str]]:
    handles, labels, names = [], [], []
    for folder in sorted((fit / "models").iterdir()):
        metrics = folder / "metrics.json"
        if not (folder / "model.pt").is_file() or not metrics.is_file() or not json.loads(metrics.read_text()).get("converged"):
            continue
        poison = json.loads((folder / "config.json").read_text())["poison"]
        poisoned = (folder / "ground_truth.csv").read_text().strip() == "1"
        if poisoned and (poison.get("attack", "envmix") != "envmix" or poison.get("evasion")):
            continue  # the paper's attack alone
        handles.append(open_model(folder))
        labels.append(int(poisoned))
        names.append(folder.name)
    return handles, np.array(labels), names


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mitigated", type=Path, help="rlbackdoors mitigate ZOO's --out folder (mitigation-report.json, models/)")
    ap.add_argument("--zoo", type=Path, required=True, help="the zoo it mitigated")
    ap.add_argument("--fit", type=Path, help="a zoo to fit the detector on (its clean and env-mix models)")
    ap.add_argument("--detector", type=Path, help="a fitted detector's folder (any detector) instead of --fit")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)  # small batches: a second thread beside a busy core slows the search tenfold
    began, load = time.time(), os.getloadavg()
    if (args.fit is None) == (args.detector is None):
        ap.error("give --fit ZOO or --detector FOLDER")
    if args.detector is not None:
        det = load_detector(args.detector)
        fitted = {"detector": det.name, "folder": str(args.detector), "params": det.params}
    else:
        handles, labels, names = fit_models(args.fit)
        det = EffectDetector().fit(handles, labels)
        fitted = {"zoo": args.fit.name, "models": len(names), "poisoned": int(labels.sum()), "calibration": det.calibration_note}
    report = json.loads((args.mitigated / "mitigation-report.json").read_text())
    rows = []
    for row in report["models"]:
        before = float(det.predict_proba([open_model(args.zoo / "models" / row["model"])])[0])
        after = float(det.predict_proba([open_model(args.mitigated / "models" / row["model"])])[0])
        rows.append({"model": row["model"], "poisoned": row["poisoned"], "family": row["family"], "before": before, "after": after})
        print(f"{row['model']} {'poisoned' if row['poisoned'] else 'clean'}: {before:.3f} -> {after:.3f}", file=sys.stderr, flush=True)

    def auc(items) -> float | None:
        if not items:
            return None
        y = [1] * len(items) + [0] * len(items)
        return round(float(roc_auc_score(y, [r["before"] for r in items] + [r["after"] for r in items])), 4)

    poisoned, clean = [r for r in rows if r["poisoned"]], [r for r in rows if not r["poisoned"]]
    result = {
        "command": "python experiments/mitigation/detected_after.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "fit": fitted,
        "auc_before_vs_after_poisoned": auc(poisoned),
        "auc_before_vs_after_clean": auc(clean),
        "mean_probability": {
            side: {k: round(float(np.mean([r[side] for r in v])), 4) if v else None for k, v in (("poisoned", poisoned), ("clean", clean))}
            for side in ("before", "after")
        },
        "machine": machine_info(),
        "loadavg_before": [round(x, 2) for x in load],
        "wall_s": round(time.time() - began, 1),
        "models": rows,
    }
    out = args.json or args.mitigated / "detected-after.json"
    atomic_write_text(out, json.dumps(result, indent=2, sort_keys=True) + "\n")
    print(json.dumps({k: result[k] for k in ("fit", "auc_before_vs_after_poisoned", "auc_before_vs_after_clean", "mean_probability")}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
