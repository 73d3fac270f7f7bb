"""Cache the stack's member features of every model a mitigation report names, after mitigation,
beside ``features.py``'s cache of the same models before it.

    OMP_NUM_THREADS=1 python experiments/stack_bound/features_mitigated.py runs/mitigated-round103 datasets/round-lavaworld-test

Writes ``runs/stack-features/mitigated-NAME/MODEL.json`` (features, group, label, cell); the label
and cell are the source zoo's ground truth, read here for scoring only (the mitigation never read
them). A model already cached is skipped.
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import torch

from rlbackdoors.detect.api import make_detector
from rlbackdoors.detect.handle import open_model
from rlbackdoors.io import atomic_write_text

MEMBERS = "effect,weights,behaviour"


def main() -> None:
    torch.set_num_threads(1)
    mitigated, zoo = Path(sys.argv[1]), Path(sys.argv[2])
    cells = {r["model_name"]: r["cell"] for r in csv.DictReader((zoo / "METADATA.csv").open())}
    stack = make_detector("stack", members=MEMBERS)
    out = Path("runs/stack-features") / f"mitigated-{mitigated.name}"
    out.mkdir(parents=True, exist_ok=True)
    for row in json.loads((mitigated / "mitigation-report.json").read_text())["models"]:
        path = out / f"{row['model']}.json"
        if path.is_file():
            continue
        handle = open_model(mitigated / "models" / row["model"], name=row["model"])
        cached = {"features": stack.features(handle), "group": stack.group(handle), "label": int(row["poisoned"]), "cell": cells[row["model"]]}
        atomic_write_text(path, json.dumps(cached) + "\n")
        print(mitigated.name, row["model"], flush=True)


if __name__ == "__main__":
    main()
