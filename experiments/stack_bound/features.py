"""Cache the stack's member features (effect, weights, behaviour) of every converged model of the
given zoos, one JSON per model, so that the stack's meta model can be studied without searching again.

    OMP_NUM_THREADS=1 python experiments/stack_bound/features.py datasets/round-lavaworld-train datasets/round-lavaworld-test

Writes ``runs/stack-features/ZOO/MODEL.json`` (features, group, label); a model already there is skipped.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch

from rlbackdoors.detect.api import make_detector
from rlbackdoors.detect.dataset import list_models
from rlbackdoors.detect.handle import open_model
from rlbackdoors.io import atomic_write_text

MEMBERS = "effect,weights,behaviour"


def main() -> None:
    torch.set_num_threads(1)
    stack = make_detector("stack", members=MEMBERS)
    for zoo in map(Path, sys.argv[1:]):
        out = Path("runs/stack-features") / zoo.name
        out.mkdir(parents=True, exist_ok=True)
        for model in list_models(zoo):
            path = out / f"{model.name}.json"
            if path.is_file():
                continue
            handle = open_model(model.folder, name=model.name)
            row = {"features": stack.features(handle), "group": stack.group(handle), "label": model.label, "cell": model.metadata.get("cell", "")}
            atomic_write_text(path, json.dumps(row) + "\n")
            print(zoo.name, model.name, flush=True)


if __name__ == "__main__":
    main()
