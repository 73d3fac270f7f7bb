"""model.pt SHA-256 (first 16 hex digits) of tiny runs on the "jax" and "compiled" backends, for a
refactor that must not move bytes: run it before (``PYTHONPATH=<a worktree of the old commit>/src``)
and after, on the same machine, and diff the two files.

    python experiments/compiled_update/refactor_bytes.py /tmp/after.json

Colorful Memory's "jax" run was added when the recurrent update became shared with the compiled
recurrent iteration (2026-12-06, issue 79). Used when algos/jax_update.py moved into algos/compiled.py and the two backends' agent step became
one (2026-12-02, 2-core AMD EPYC family 25): all 10 hashes equal before and after.
"""

from __future__ import annotations

import hashlib
import json
import sys
import tempfile
from pathlib import Path

import torch

from rlbackdoors.config import RunConfig
from rlbackdoors.train import train
from rlbackdoors.train.group import train_group

TINY = {"max_frames": 7680, "eval_interval": 2560, "eval_episodes": 4, "final_eval_episodes": 4, "video": False}


def config(seed: int, backend: str, world: str = "lavaworld", arch: str = "fc", poison: dict | None = None) -> RunConfig:
    data = {"env": {"name": world}, "model": {"arch": arch}, "ppo": {"update_backend": backend}, "train": {"seed": seed, **TINY}}
    if poison:
        data["poison"] = poison
    return RunConfig.from_dict(data)


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def main(out: Path) -> dict:
    torch.set_num_threads(1)
    root = Path(tempfile.mkdtemp())
    lone = {
        "jax lone": config(1, "jax"),
        "compiled lone": config(1, "compiled"),
        "compiled cnn": config(1, "compiled", arch="cnn"),
        "compiled rlw cnn": config(1, "compiled", world="randomized-lavaworld", arch="cnn"),
        "compiled trojdrl teacher": config(1, "compiled", poison={"attack": "trojdrl", "evasion": {"finetune": True, "teacher": 0.5}}),
        "jax colorful memory": config(1, "jax", world="colorful-memory", arch="cnn-gru-small-onehot"),
        "compiled colorful memory": config(1, "compiled", world="colorful-memory", arch="cnn-gru-small-onehot"),
    }
    hashes: dict = {}
    for name, cfg in lone.items():
        train(cfg, root / name, progress=False)
        hashes[name] = sha(root / name / "model.pt")
    for backend, k in (("jax", 3), ("compiled", 2)):
        train_group([(s, config(s, backend), root / f"{backend}-g{s}") for s in range(1, k + 1)], k)
        hashes[f"{backend} group"] = [sha(root / f"{backend}-g{s}" / "model.pt") for s in range(1, k + 1)]
    out.write_text(json.dumps(hashes, indent=1, sort_keys=True) + "\n")
    print(json.dumps(hashes, indent=1, sort_keys=True))
    return hashes


if __name__ == "__main__":
    main(Path(sys.argv[1]))
