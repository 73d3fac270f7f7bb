"""Cache the stack's member features (effect, weights, behaviour) of every converged model of the
given zoos, one JSON per model, so that the stack's meta model can be studied without searching again.

    OMP_NUM_THREADS=1 python experiments/stack_bound/features.py datasets/round-lavaworld-train datasets/round-lavaworld-test
    OMP_NUM_THREADS=1 python experiments/stack_bound/features.py --mitigated runs/mitigated-round103 datasets/round-lavaworld-test

Writes ``runs/stack-features/ZOO/MODEL.json`` (features, group, label, cell); a model already there is
skipped. With ``--mitigated DIR ZOO``: every model DIR's mitigation report names, after mitigation,
into ``runs/stack-features/mitigated-DIR/``; the label and cell are ZOO's ground truth, read here for
scoring only (the mitigation never read them).
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import torch

from rlbackdoors.detect.api import make_detector
from rlbackdoors.detect.dataset import list_models
from rlbackdoors.detect.handle import open_model
from rlbackdoors.io import atomic_write_text

MEMBERS = "effect,weights,behaviour"


def cache(stack, folder: Path, name: str, label: int, cell: str, path: Path) -> None:
    """One model's member features into ``path`` (skipped where it is already there)."""
    if path.is_file():
        return
    handle = open_model(folder, name=name)
    row = {"features": stack.features(handle), "group": stack.group(handle), "label": label, "cell": cell}
    atomic_write_text(path, json.dumps(row) + "\n")
    print(path.parent.name, name, flush=True)


def main() -> None:
    torch.set_num_threads(1)
    stack = make_detector("stack", members=MEMBERS)
    if sys.argv[1:2] == ["--mitigated"]:
        mitigated, zoo = Path(sys.argv[2]), Path(sys.argv[3])
        cells = {r["model_name"]: r["cell"] for r in csv.DictReader((zoo / "METADATA.csv").open())}
        out = Path("runs/stack-features") / f"mitigated-{mitigated.name}"
        out.mkdir(parents=True, exist_ok=True)
        for row in json.loads((mitigated / "mitigation-report.json").read_text())["models"]:
            name = row["model"]
            cache(stack, mitigated / "models" / name, name, int(row["poisoned"]), cells[name], out / f"{name}.json")
        return
    for zoo in map(Path, sys.argv[1:]):
        out = Path("runs/stack-features") / zoo.name
        out.mkdir(parents=True, exist_ok=True)
        for model in list_models(zoo):
            cache(stack, model.folder, model.name, model.label, model.metadata.get("cell", ""), out / f"{model.name}.json")


if __name__ == "__main__":
    main()
