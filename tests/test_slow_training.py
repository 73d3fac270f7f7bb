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
