"""Tiny model folders and zoos for the detector tests (no tests here; imported by test_detect_*.py).

Models are real: trained by ``rlbackdoors.train.train`` on the tiny budgets of
``tests/test_same_weights.py`` (seconds each), so they are barely trained; tests that need a
model whose backdoor actually fires build one differently and say so.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

GRID_TINY = {"ppo": {"rollout": 32}, "train": {"max_frames": 3200, "eval_interval": 1600, "eval_episodes": 8, "final_eval_episodes": 8, "video": False}}
TINY = {
    "lavaworld": {**GRID_TINY, "env": {"name": "lavaworld"}},
    "randomized-lavaworld": {**GRID_TINY, "env": {"name": "randomized-lavaworld"}, "curriculum": {"enabled": False}},
    "colorful-memory": {
        "env": {"name": "colorful-memory"},
        "ppo": {"rollout": 24, "batch_size": 120},
        "train": {"max_frames": 2400, "eval_interval": 1200, "eval_episodes": 4, "final_eval_episodes": 4, "video": False},
    },
    "safety-car-goal": {
        "env": {"name": "safety-car-goal", "max_steps": 40},
        "poison": {"num_clean_envs": 2, "num_poisoned_envs": 1},
        "opac2": {"depth": 2, "width": 16, "batch_size": 32, "learning_starts": 120, "updates_per_step": 0.25},
        "train": {"max_frames": 480, "eval_interval": 240, "eval_episodes": 3, "final_eval_episodes": 4, "checkpoint_minutes": 0, "video": False},
    },
}


def make_model(folder: Path, world: str, poisoned: bool, seed: int, trigger: str | None = None, arch: str | None = None, examples: int = 2) -> Path:
    """Train a tiny model of ``world`` into ``folder`` and write the zoo's dataset files
    (reduced-config.json, clean-example-data/) as ``rlbackdoors zoo`` does."""
    import copy

    from rlbackdoors.config import RunConfig
    from rlbackdoors.train import train

    data = copy.deepcopy(TINY[world])
    data.setdefault("poison", {})["poisoned"] = poisoned
    if trigger is not None:
        data["poison"]["trigger"] = trigger
    if arch is not None:
        data["model"] = {"arch": arch}
    data["train"]["seed"] = seed
    cfg = RunConfig.from_dict(data)
    train(cfg, folder, progress=False)
    write_dataset_files(folder, cfg, examples)
    return folder


def write_dataset_files(folder: Path, cfg, episodes: int) -> None:
    from rlbackdoors.zoo.examples import write_examples
    from rlbackdoors.zoo.job import reduced_config

    config = json.loads((folder / "config.json").read_text())
    write_examples(folder, cfg, episodes=episodes, seed=2_000_000)
    (folder / "reduced-config.json").write_text(json.dumps(reduced_config(folder, config), indent=2, sort_keys=True) + "\n")


def make_zoo(root: Path, models: list[dict]) -> Path:
    """``root/models/id-0000000N/`` for each ``make_model`` kwargs dict, and a METADATA.csv."""
    rows = []
    for i, spec in enumerate(models):
        name = f"id-{i:08d}"
        make_model(root / "models" / name, **spec)
        config = json.loads((root / "models" / name / "config.json").read_text())
        trigger = config["poison"]["trigger"]
        rows.append(
            {
                "model_name": name,
                "world": config["env"]["name"],
                "arch": config["model"]["arch"] or "opac2",
                "trigger_family": trigger.split(":")[0],
                "poisoned": spec["poisoned"],
                "status": "done",
                "converged": True,
                "poison.trigger": trigger,
            }
        )
    with open(root / "METADATA.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return root


LAVA_ZOO = [
    {"world": "lavaworld", "poisoned": p, "seed": s, "trigger": t, "arch": a}
    for p, s, t, a in (
        (False, 11, "multiplicative:12", "fc"),
        (True, 12, "multiplicative:12", "fc"),
        (False, 13, "additive:50", "fc"),
        (True, 14, "additive:50", "fc"),
        (False, 15, "multiplicative:20", "cnn"),
        (True, 16, "multiplicative:20", "cnn"),
    )
]


@pytest.fixture(scope="session")
def lava_zoo(tmp_path_factory) -> Path:
    """Six tiny LavaWorld models (FC and CNN, 3 clean + 3 poisoned), trained once per session."""
    return make_zoo(tmp_path_factory.mktemp("lava-zoo"), LAVA_ZOO)


@pytest.fixture(scope="session")
def world_models(tmp_path_factory) -> dict[str, Path]:
    """One tiny poisoned model folder per world (Safety Car Goal: width 16), trained once."""
    root = tmp_path_factory.mktemp("worlds")
    triggers = {"safety-car-goal": "formation:0.5:1.0:2.5"}
    return {w: make_model(root / f"id-{i:08d}", w, True, 1, triggers.get(w)) for i, w in enumerate(TINY)}


class KillAfter:
    """A progress callback that records its lines and raises KeyboardInterrupt (Ctrl-C) once
    ``n`` models have been computed: the job dies between two models, as a kill would leave it."""

    def __init__(self, n: int | None):
        self.n, self.lines = n, []

    def __call__(self, line: str) -> None:
        self.lines.append(line)
        if self.n is not None and sum(x.startswith("[") for x in self.lines) >= self.n:
            raise KeyboardInterrupt

    @property
    def computed(self) -> int:
        return sum(x.startswith("[") for x in self.lines)
