"""Cross-validated detector scores on models trained one by one (no zoo), e.g. Safety Car Goal.

    python benchmarks/dataset_cv.py safety-cv runs/recipes/safety-m02/s? runs/recipes/safety-clean/s? \
        --detector behaviour --param behaviour:confirm_episodes=32 --detector weights --folds 4

A world whose models take CPU-hours each (Safety Car Goal: 8-40 CPU-minutes to converge on one
core) gets a dataset of tens of models, too few to split into a train and a test zoo. This script
makes one dataset of the given training folders and scores each detector on it by stratified
cross-validation (``rlbackdoors detect cv``: every probability from a classifier fitted without
that model):

1. ``runs/detect/NAME/source/`` links each folder under an opaque, stable name (``id-`` and 8
   digits of the SHA-256 of its path: neither the label nor the order shows through);
2. ``rlbackdoors zoo import-trojai`` indexes them as ``runs/detect/NAME/zoo`` (world, settings
   and trigger from each folder's own config.json; clean example episodes written);
3. ``rlbackdoors detect cv`` per detector into ``runs/detect/NAME/cv-DETECTOR`` (a killed run
   resumes there; features are computed once per model).

It writes ``benchmarks/results/detectors/NAME.json``: per detector the metrics with CIs, the folds, the
seconds per model, the per-model rows (found trigger next to the true one), and the machine with
its load. The folders are only read. Adding folders later makes a new import (step 2 again into
a fresh zoo); models seen before keep their names, so their features are read back.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
from pathlib import Path

from _detect_cli import rlbackdoors

from rlbackdoors.bench.machine import machine_info
from rlbackdoors.detect.dataset import read_metadata
from rlbackdoors.io import atomic_write_text, remove_tree

ROOT = Path(__file__).resolve().parents[1]


def opaque_name(folder: Path) -> str:
    return f"id-{int(hashlib.sha256(str(folder.resolve()).encode()).hexdigest()[:12], 16) % 10**8:08d}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("name")
    parser.add_argument("models", nargs="+", help="training folders (model.pt, config.json, ground_truth.csv)")
    parser.add_argument("--detector", action="append", required=True, help="a feature detector to cross-validate (repeatable)")
    parser.add_argument("--param", action="append", default=[], metavar="DETECTOR:KEY=VALUE", help="a parameter of one detector (repeatable)")
    parser.add_argument("--folds", type=int, default=5)
    parser.add_argument("--examples", type=int, default=5, help="clean example episodes per model (default 5)")
    args = parser.parse_args()
    work = ROOT / "runs" / "detect" / args.name
    folders = sorted({Path(m).resolve() for m in args.models if (Path(m) / "model.pt").is_file()})
    names = {opaque_name(f): f for f in folders}
    if len(names) != len(folders):
        sys.exit("rlbackdoors: error: two folders drew the same opaque name; rename one")
    source = work / "source"
    source.mkdir(parents=True, exist_ok=True)
    for link in source.iterdir():
        if link.name not in names:
            link.unlink()
    for name, folder in names.items():
        link = source / name
        if not link.is_symlink() or link.resolve() != folder:
            link.unlink(missing_ok=True)
            link.symlink_to(folder, target_is_directory=True)
    zoo = work / "zoo"
    if (zoo / "METADATA.csv").is_file() and sorted(read_metadata(zoo)) != sorted(names):
        remove_tree(zoo)  # other folders than last time: a fresh import (features are reused by name)
    rlbackdoors("zoo", "import-trojai", str(source), "--out", str(zoo), "--episodes", "0", "--examples", str(args.examples), quiet=True)
    results = {}
    for detector in args.detector:
        params = [p.split(":", 1)[1] for p in args.param if p.split(":", 1)[0] == detector]
        out = work / f"cv-{detector}"
        argv = ["detect", "cv", "--detector", detector, "--zoo", str(zoo), "--out", str(out), "--folds", str(args.folds), "--quiet"]
        rlbackdoors(*argv, *(x for p in params for x in ("--param", p)))
        scored = json.loads((out / "score.json").read_text())
        for row in scored["models"]:
            row["folder"] = str(names[row["model"]].relative_to(ROOT)) if names[row["model"]].is_relative_to(ROOT) else str(names[row["model"]])
        results[detector] = {k: scored[k] for k in ("params", "all", "cv", "seconds_per_model", "failed", "models")}
        s = scored["all"]
        print(
            f"{detector}: AUC {s['auc']['value']:.3f} CE {s['ce']['value']:.3f} Brier {s['brier']['value']:.3f} over {s['n']} models ({s['poisoned']} poisoned)"
        )
    out_file = ROOT / "benchmarks" / "results" / "detectors" / f"{args.name}.json"
    payload = {"command": " ".join(sys.argv[1:]), "models": len(folders), "detectors": results, "machine": machine_info(), "loadavg": os.getloadavg()}
    atomic_write_text(out_file, json.dumps(payload, indent=2) + "\n")
    print(f"-> {out_file}")


if __name__ == "__main__":
    main()
