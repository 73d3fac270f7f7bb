"""Issue 81's length check on the round's clean models: do clean models trained on long after they
converged score like those stopped at convergence?

    python experiments/long_trained_clean/score.py datasets/round-lavaworld-test datasets/round-lavaworld-train \
        --fit datasets/benchmark-lavaworld-effect --detectors effect,weights

Each detector is fitted on the fit zoo's clean and env-mix models (the paper's attack; no evasive
variant), then scores every converged clean model of the round packs. A round draws each model's
``train.min_frames`` (0: stop at convergence; else train on to 1.2-3 M frames first), so the clean
models split into "stopped" and "trained on"; the issue asks their mean probabilities within 0.05.
Labels and lengths are read from the packs by this script alone. Writes ``--json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from rlbackdoors.bench.machine import machine_info
from rlbackdoors.detect.api import get_detector
from rlbackdoors.detect.handle import open_model
from rlbackdoors.io import atomic_write_text


def converged(zoo: Path):
    for folder in sorted((zoo / "models").iterdir()):
        metrics = folder / "metrics.json"
        if (folder / "model.pt").is_file() and metrics.is_file():
            m = json.loads(metrics.read_text())
            if m.get("converged"):
                yield folder, m, json.loads((folder / "config.json").read_text())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rounds", nargs="+", type=Path)
    ap.add_argument("--fit", type=Path, required=True)
    ap.add_argument("--detectors", default="effect,weights")
    ap.add_argument("--json", type=Path, required=True)
    args = ap.parse_args(argv)
    began, load = time.time(), os.getloadavg()
    fit, labels = [], []
    for folder, _, cfg in converged(args.fit):
        poisoned = cfg["poison"]["poisoned"]
        if poisoned and (cfg["poison"].get("attack", "envmix") != "envmix" or cfg["poison"].get("evasion")):
            continue
        fit.append(open_model(folder))
        labels.append(int(poisoned))
    clean = [(folder, m, cfg) for zoo in args.rounds for folder, m, cfg in converged(zoo) if not cfg["poison"]["poisoned"]]
    handles = [open_model(folder) for folder, _, _ in clean]
    result: dict = {"fit": {"zoo": args.fit.name, "models": len(fit), "poisoned": int(sum(labels))}, "detectors": {}}
    for name in args.detectors.split(","):
        det = get_detector(name)().fit(fit, np.array(labels))
        probs = det.predict_proba(handles)
        rows = [
            {"model": f"{folder.parent.parent.name}/{folder.name}", "frames": m["frames"], "min_frames": cfg["train"].get("min_frames", 0), "p": round(float(p), 4)}
            for (folder, m, cfg), p in zip(clean, probs)
        ]
        stopped = [r["p"] for r in rows if not r["min_frames"]]
        trained_on = [r["p"] for r in rows if r["min_frames"]]
        result["detectors"][name] = {
            "stopped": {"n": len(stopped), "mean_p": round(float(np.mean(stopped)), 4) if stopped else None},
            "trained_on": {"n": len(trained_on), "mean_p": round(float(np.mean(trained_on)), 4) if trained_on else None},
            "gap": round(float(np.mean(trained_on) - np.mean(stopped)), 4) if stopped and trained_on else None,
            "models": rows,
        }
        print(name, {k: v for k, v in result["detectors"][name].items() if k != "models"}, file=sys.stderr, flush=True)
    result.update(machine=machine_info(), loadavg_before=[round(x, 2) for x in load], wall_s=round(time.time() - began, 1))
    atomic_write_text(args.json, json.dumps(result, indent=2, sort_keys=True) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
