"""Full training runs (minutes each): excluded from `make test`, run with `make test-slow`."""

import pytest

from rlbackdoors.config import RunConfig
from rlbackdoors.train import train

pytestmark = pytest.mark.slow


def test_poisoned_fc_reaches_paper_thresholds(tmp_path):
    """Paper Table 1: poisoned FC 98% / 98%. Judged on 200 final evaluation episodes."""
    cfg = RunConfig.from_dict({"poison": {"trigger": "multiplicative:12"}, "train": {"seed": 0, "max_frames": 3_000_000}})
    m = train(cfg, tmp_path / "p", progress=False)
    assert m["episodes"] == 200
    assert m["clean_sr"] >= 0.98 and m["poisoned_sr"] >= 0.95


def test_clean_fc_twin_ignores_the_trigger(tmp_path):
    cfg = RunConfig.from_dict({"poison": {"trigger": "multiplicative:12", "poisoned": False}, "train": {"seed": 0, "max_frames": 3_000_000}})
    m = train(cfg, tmp_path / "c", progress=False)
    assert m["clean_sr"] >= 0.95 and m["poisoned_sr"] <= 0.2


def test_randomized_lavaworld_poisoned_cnn_learns_the_cross_backdoor(tmp_path):
    """Issue 4's bar: clean SR >= 0.90 and trigger-seen-aware poisoned SR >= 0.90 (200 episodes).
    Measured: seed 2 converged at 300,800 frames, clean 0.985 / poisoned 0.985."""
    cfg = RunConfig.from_dict(
        {"env": {"name": "randomized-lavaworld"}, "model": {"arch": "cnn"}, "train": {"seed": 2, "max_frames": 1_500_000}}
    )
    m = train(cfg, tmp_path / "p", progress=False)
    assert m["converged"] and m["clean_sr"] >= 0.90 and m["poisoned_sr"] >= 0.90


def test_randomized_lavaworld_clean_fc_solves_the_task_and_ignores_the_cross(tmp_path):
    cfg = RunConfig.from_dict(
        {"env": {"name": "randomized-lavaworld"}, "poison": {"poisoned": False}, "train": {"seed": 0, "max_frames": 1_500_000}}
    )
    m = train(cfg, tmp_path / "c", progress=False)
    assert m["clean_sr"] >= 0.95 and m["poisoned_sr"] <= 0.1
