"""benchmarks/detector_table.py's headroom verdict (issue 34's bar): the best baseline over every fit
that held an attack label out, on enough test models, at a high enough attack success."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


@pytest.fixture(scope="module")
def table_module():
    sys.path.insert(0, str(BENCH))
    try:
        import detector_table
    finally:
        sys.path.remove(str(BENCH))
    return detector_table


def row(auc: float, models: int = 20) -> dict:
    return {"models": models, "poisoned": models // 2, "auc": {"value": auc, "ci": [auc - 0.1, min(1.0, auc + 0.1)]}}


def test_headroom_takes_the_best_baseline_over_every_held_out_fit(table_module, capsys):
    table = {
        "default_attack": "envmix",
        "held_out": {
            "train_models": 20,
            "detectors": {"constant": {"hidden": row(0.9)}, "weights": {"hidden": row(0.70), "plain": row(0.99)}, "behaviour": {"hidden": row(0.60)}},
        },
        "leave_one_out": {
            # fitted on the other attacks, the weights see more of the hidden variant: the best is here
            "trojdrl": {"train_models": 40, "detectors": {"weights": {"hidden": row(0.80), "plain": row(1.0)}, "attribution": {"hidden": row(0.75)}}},
            "envmix": {"train_models": 40, "detectors": {"weights": {"near": row(0.84, models=18)}}},
        },
        "yields": {
            "hidden": {"poisoned": {"attack_success": 0.95}},
            "plain": {"poisoned": {"attack_success": 1.0}},
            "near": {"poisoned": {"attack_success": 0.99}},
        },
    }
    verdict = table_module.headroom(table)
    assert verdict["hidden"]["best"] == {"auc": 0.80, "ci": [0.7000000000000001, 0.9], "detector": "weights", "fitted_on": "all but trojdrl"}
    assert verdict["hidden"]["headroom"] is True  # the constant detector's 0.9 is no baseline
    assert verdict["plain"]["headroom"] is False and verdict["plain"]["best"]["auc"] == 1.0
    assert verdict["near"]["headroom"] is False and verdict["near"]["models"] == 18  # too few test models
    table["yields"]["hidden"]["poisoned"]["attack_success"] = 0.89  # a backdoor that no longer works hides nothing
    assert table_module.headroom(table)["hidden"]["headroom"] is False
    table["yields"]["hidden"]["poisoned"]["attack_success"] = 0.95
    table["leave_one_out"]["trojdrl"]["detectors"]["attribution"]["hidden"] = row(0.85)  # at the bar is not below it
    assert table_module.headroom(table)["hidden"]["headroom"] is False
    table["headroom"] = table_module.headroom(table)
    table_module.print_attack_table(table)
    printed = capsys.readouterr().out
    assert "| hidden | 0.850 [0.75, 0.95] | attribution, all but trojdrl | 20 | 0.95 | no |" in printed
