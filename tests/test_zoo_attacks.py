"""Zoos that mix attacks (issue 33): cells per attack, METADATA's attack columns, report rows per
attack, and a split that holds an attack out. Tiny LavaWorld FC budgets; every model converges
(thresholds 0), so the mechanics run for real in seconds."""

from __future__ import annotations

import copy
import json

import pytest

from rlbackdoors.validate import ConfigError
from rlbackdoors.zoo.index import read_metadata
from rlbackdoors.zoo.plan import plan
from rlbackdoors.zoo.report import report
from rlbackdoors.zoo.run import run
from rlbackdoors.zoo.spec import parse_spec
from rlbackdoors.zoo.split import split

TINY = {"ppo": {"rollout": 32}, "train": {"max_frames": 3200, "eval_interval": 1600, "eval_episodes": 4, "final_eval_episodes": 4, "video": False}}
ALWAYS = {"train": {"clean_threshold": 0.0, "poisoned_threshold": 0.0}}


def spec() -> dict:
    return {
        "name": "attacks",
        "seed": 11,
        "examples": {"episodes": 1},
        "overrides": copy.deepcopy(TINY),
        "cells": [
            {"world": "lavaworld", "archs": ["fc"], "triggers": ["additive"], "clean": 1, "poisoned": 1, "overrides": ALWAYS},
            {
                "world": "lavaworld",
                "archs": ["fc"],
                "triggers": ["multiplicative"],
                "attacks": ["sleepernets", {"attack": "trojdrl", "name": "trojdrl-5pc", "params": {"budget": 0.05}}],
                "clean": 1,
                "poisoned": 1,
                "overrides": ALWAYS,
            },
        ],
    }


def test_cells_expand_per_attack_and_old_specs_keep_their_keys_and_normal_form():
    parsed = parse_spec(spec())
    assert [c.key for c in parsed.cells] == [
        "lavaworld/fc/additive",
        "lavaworld/fc/multiplicative/sleepernets",
        "lavaworld/fc/multiplicative/trojdrl-5pc",
    ]
    assert parsed.cells[2].overrides["poison"] == {"attack": "trojdrl", "attack_params": {"budget": 0.05}}
    assert "attacks" not in parsed.normalized["cells"][0] and parsed.normalized["cells"][1]["attacks"][1]["params"] == {"budget": 0.05}
    assert parse_spec(parsed.normalized).normalized == parsed.normalized


def test_attack_parameters_drawn_from_ranges_are_per_model_and_reproducible(tmp_path):
    raw = spec()
    raw["cells"][1]["attacks"] = [{"attack": "trojdrl", "params": {"reward": 0.2}, "ranges": {"budget": [0.005, 0.02], "target_action": [0, 1]}}]
    raw["cells"][1]["poisoned"] = 4
    parsed = parse_spec(raw)
    zoo, _ = plan(parsed, tmp_path / "a")
    drawn = [zoo.draw(g, a).poison.attack_params for g in parsed.groups if g.cell.attack.ranges for a in range(g.max_attempts)]
    assert all(0.005 <= p["budget"] <= 0.02 and p["target_action"] in (0, 1) and p["reward"] == 0.2 for p in drawn)
    assert len({p["budget"] for p in drawn}) == len(drawn) and {p["target_action"] for p in drawn} == {0, 1}
    again, _ = plan(parse_spec(parsed.normalized), tmp_path / "b")
    assert [again.draw(g, a).poison.attack_params for g in parsed.groups if g.cell.attack.ranges for a in range(g.max_attempts)] == drawn
    envmix = [g for g in parsed.groups if not g.cell.attack.ranges]
    assert zoo.draw(envmix[0], 0) == plan(parse_spec(spec()), tmp_path / "c")[0].draw(envmix[0], 0)  # other cells draw as before


@pytest.mark.parametrize(
    "attacks, message",
    [
        (["nope"], r"cells\[1\].attacks\[0\].attack='nope' is not allowed \(allowed: envmix, trojdrl"),
        ([{"attack": "badrl", "params": {"budget": 3}}], r"cells\[1\].attacks\[0\].params.budget=3 is not allowed"),
        (["badrl", "badrl"], r"cells\[1\].attacks: two share the name 'badrl'"),
        ([], r"cells\[1\].attacks must be a non-empty list"),
        ([{"attack": "badrl", "ranges": {"budget": [0.5, 2.0]}}], r"cells\[1\].attacks\[0\].ranges.budget=2.0 is not allowed"),
        ([{"attack": "badrl", "ranges": {"budget": [0.5, 0.1]}}], r"ranges.budget must be \[low, high\] with low <= high"),
        ([{"attack": "badrl", "params": {"budget": 0.1}, "ranges": {"budget": [0.1, 0.2]}}], r"budget is also fixed in params"),
    ],
)
def test_bad_attacks_in_a_spec_are_refused_naming_the_field(attacks, message):
    raw = spec()
    raw["cells"][1]["attacks"] = attacks
    with pytest.raises(ConfigError, match=message):
        parse_spec(raw)


def test_an_attack_a_world_cannot_serve_is_refused_when_the_spec_is_read():
    raw = spec()
    del raw["overrides"]
    raw["cells"][1] = {"world": "colorful-memory", "attacks": ["badrl"], "poisoned": 1}
    with pytest.raises(ConfigError, match=r"cells\[1\].attacks\[0\]: .*poison.attack='badrl': attack 'badrl' chooses single frames by the critic's value"):
        parse_spec(raw)


def test_a_zoo_of_attacks_records_them_reports_them_and_holds_one_out(tmp_path):
    path = tmp_path / "zoo"
    plan(parse_spec(spec()), path)
    run(path, workers=2, group_size=3, progress_interval=5.0)  # two group jobs: attacks train in groups too
    rows = read_metadata(path / "METADATA.csv")
    assert len(rows) == 6 and all(json.loads((path / "models" / r["model_name"] / "metrics.json").read_text())["trainer"] == "group" for r in rows)
    assert len(rows) == 6 and all(r["converged"] == "True" for r in rows)
    by_cell = {(r["cell"], r["poisoned"]): r for r in rows}
    assert by_cell[("lavaworld/fc/additive", "True")]["attack"] == "envmix"
    poisoned = by_cell[("lavaworld/fc/multiplicative/trojdrl-5pc", "True")]
    assert poisoned["attack"] == "trojdrl" and poisoned["poison.attack_params.budget"] == "0.05"
    assert 0 < float(poisoned["metrics.attack_budget_used.poisoned_fraction"]) <= 0.05
    assert by_cell[("lavaworld/fc/multiplicative/sleepernets", "False")]["metrics.poisoned"] == "False"

    out = report(path)
    text = (out / "report.md").read_text()
    assert "| poisoned (sleepernets) |" in text and "| poisoned (trojdrl-5pc) |" in text and "| poisoned |" in text
    conv = (out / "convergence.csv").read_text()
    assert "trojdrl-5pc" in conv

    result = split(path, 0.0, 0.0, tmp_path / "train", tmp_path / "test", hold_out_attacks=["sleepernets", "trojdrl"])
    test_rows = read_metadata(tmp_path / "test" / "METADATA.csv")
    train_rows = read_metadata(tmp_path / "train" / "METADATA.csv")
    assert {r["attack"] for r in test_rows} == {"sleepernets", "trojdrl"} and {r["attack"] for r in train_rows} == {"envmix"}
    assert result["test"]["models"] == 4 and result["train"]["models"] == 2
    assert not {r["poison.trigger"] for r in test_rows} & {r["poison.trigger"] for r in train_rows}
    info = json.loads((tmp_path / "test" / "split.json").read_text())
    assert info["hold_out_attacks"] == ["sleepernets", "trojdrl"]
    with pytest.raises(ConfigError, match=r"--hold-out-attack 'badrl' is not an attack of this zoo"):
        split(path, 0.0, 0.0, tmp_path / "t2", tmp_path / "t3", hold_out_attacks=["badrl"])


def test_like_attacks_queue_side_by_side_for_compiled_groups(tmp_path):
    """zoo run orders the ready models of an attempt by what a compiled group's program depends on
    (world, arch, attack; the clean models of every cell alike), so a group job's slots hold like
    models: each label's models come together, the clean ones of both cells as one."""
    from rlbackdoors.zoo.run import _affinity

    zoo, _ = plan(parse_spec(spec()), tmp_path / "z")
    first = sorted((m for m in zoo.all_planned() if m.attempt == 0), key=lambda m: (_affinity(m), m.group.index))
    kinds = [_affinity(m)[2] for m in first]
    assert kinds == sorted(kinds) and set(kinds) == {"", "envmix", "sleepernets", "trojdrl"}
    assert kinds.count("") == 3  # the clean models of the env-mix cell and of both attacks' cells
    assert [m.group.cell.attack.name for m in first if m.group.poisoned] == ["envmix", "sleepernets", "trojdrl-5pc"]
