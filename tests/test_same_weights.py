"""Refactors must not change behaviour: a tiny run of each world, same config and seed, gives the
same model.pt bytes as recorded before the run API was unified (issue 14).

Bytes depend on the machine (CPU kernels, library builds), so the hashes are recorded per machine
fingerprint in ``tests/data/weights_hashes.json``; on a machine with no record the test says so
and skips. ``python tests/test_same_weights.py --record`` records this machine's hashes.
"""

from __future__ import annotations

import hashlib
import json
import platform
import sys
from pathlib import Path

import pytest

HASHES = Path(__file__).with_name("data") / "weights_hashes.json"
GRID_TINY = {"ppo": {"rollout": 32}, "train": {"seed": 1, "max_frames": 3200, "eval_interval": 1600, "eval_episodes": 8, "final_eval_episodes": 8}}
RUNS = {
    "lavaworld": {**GRID_TINY, "env": {"name": "lavaworld"}},
    "randomized-lavaworld": {**GRID_TINY, "env": {"name": "randomized-lavaworld"}},
    "colorful-memory": {
        "env": {"name": "colorful-memory"},
        "ppo": {"rollout": 24, "batch_size": 120},
        "train": {"seed": 1, "max_frames": 2400, "eval_interval": 1200, "eval_episodes": 4, "final_eval_episodes": 4},
    },
    "safety-car-goal": {
        "env": {"name": "safety-car-goal", "max_steps": 40},
        "poison": {"trigger": "formation:0.5:1.0:2.5", "num_clean_envs": 2, "num_poisoned_envs": 1},
        "opac2": {"depth": 2, "width": 16, "batch_size": 32, "learning_starts": 120, "updates_per_step": 0.25},
        "train": {"max_frames": 480, "eval_interval": 240, "eval_episodes": 3, "final_eval_episodes": 4, "checkpoint_minutes": 0, "video": False},
    },
}


def fingerprint(simd: bool = True) -> str:
    """The machine as far as model bytes depend on it. ``simd``: with the widest vector unit the
    CPU reports (two "AMD EPYC" of other generations give the GRU other bytes: avx2 vs avx512);
    without it, the key the first records were made under."""
    import numba
    import numpy
    import torch

    cpu, flags = platform.processor() or platform.machine(), set()
    try:
        lines = open("/proc/cpuinfo").read().splitlines()
        cpu = next(line.split(":", 1)[1].strip() for line in lines if line.startswith("model name"))
        flags = set(next(line.split(":", 1)[1].split() for line in lines if line.startswith("flags")))
    except (OSError, StopIteration):
        pass
    key = f"{cpu} | {platform.machine()} | torch {torch.__version__} | numpy {numpy.__version__} | numba {numba.__version__}"
    if simd:
        key += " | " + next((f for f in ("avx512f", "avx2", "avx", "sse4_2") if f in flags), "no-simd-flags")
    return key


def train_tiny(world: str, out: Path) -> str:
    """Train the tiny run of ``world`` through the CLI's config path; the sha256 of its model.pt."""
    from rlbackdoors.cli import main

    config = out.with_suffix(".json")
    config.write_text(json.dumps(RUNS[world]))
    assert main(["train", "--config", str(config), "--out", str(out), "--quiet"]) == 0
    return hashlib.sha256((out / "model.pt").read_bytes()).hexdigest()


@pytest.mark.parametrize("world", list(RUNS))
def test_tiny_run_gives_the_recorded_model_bytes(world, tmp_path, capsys):
    records = json.loads(HASHES.read_text()) if HASHES.is_file() else {}
    here = fingerprint() if fingerprint() in records else fingerprint(simd=False)  # the first records name no vector unit
    if here not in records:
        pytest.skip(f"no model hashes recorded for this machine ({fingerprint()}); record them with `python {__file__} --record`")
    assert train_tiny(world, tmp_path / world) == records[here][world]


if __name__ == "__main__" and sys.argv[1:] == ["--record"]:
    import tempfile

    records = json.loads(HASHES.read_text()) if HASHES.is_file() else {}
    with tempfile.TemporaryDirectory() as tmp:
        records[fingerprint()] = {world: train_tiny(world, Path(tmp) / world) for world in RUNS}
    HASHES.parent.mkdir(exist_ok=True)
    HASHES.write_text(json.dumps(records, indent=2, sort_keys=True) + "\n")
    print(json.dumps(records[fingerprint()], indent=2))
