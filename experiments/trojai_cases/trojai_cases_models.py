"""Tiny Randomized LavaWorld models for experiments/trojai_cases/trojai_cases.sh: ``python experiments/trojai_cases/trojai_cases_models.py OUT NUM_LAVA TRIGGER``.

Six models (3 clean, 3 poisoned with TRIGGER) in 9x9 rooms with NUM_LAVA lava squares, trained on
the tests' tiny budget (seconds each): a detector fitted on them is fitted for that setting only.
"""

import copy
import sys
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
from test_detect_helpers import TINY, write_dataset_files
from rlbackdoors.config import RunConfig
from rlbackdoors.train import train

root = Path(sys.argv[1]) / "models"
for i in range(6):
    data = copy.deepcopy(TINY["randomized-lavaworld"])
    data["env"].update({"size": 9, "num_lava": int(sys.argv[2])})
    data["poison"] = {"poisoned": bool(i % 2), "trigger": sys.argv[3]}
    data["train"]["seed"] = 100 + i
    cfg = RunConfig.from_dict(data)
    folder = root / f"id-{i:08d}"
    train(cfg, folder, progress=False)
    write_dataset_files(folder, cfg, 1)
print("ok")
