"""A small zoo of every world, end to end: plan, run, report, split (slow: a few minutes on 2 cores).

Budgets are tiny and the thresholds 0, so every model "converges": this checks the zoo's machinery
for each world (its config class, training function, clean example episodes, reduced config and
report rows), not the models.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rlbackdoors import worlds
from rlbackdoors.zoo.index import read_metadata
from rlbackdoors.zoo.plan import plan
from rlbackdoors.zoo.report import report
from rlbackdoors.zoo.run import run
from rlbackdoors.zoo.spec import load_spec
from rlbackdoors.zoo.split import split

SPEC = Path(__file__).resolve().parents[1] / "examples" / "zoo-four-worlds-smoke.toml"


@pytest.mark.slow
def test_a_zoo_of_every_world_plans_runs_reports_and_splits(tmp_path):
    zoo = tmp_path / "zoo"
    spec = load_spec(SPEC)
    assert {c.world for c in spec.cells} == set(worlds.names())
    plan(spec, zoo)
    summary = run(zoo, workers=2, progress_interval=30.0)
    assert summary["failed"] == 0 and summary["done"] == summary["models"] == 16 and summary["short"] == []
    rows = read_metadata(zoo / "METADATA.csv")
    assert {r["world"] for r in rows} == set(worlds.names())
    for row in rows:
        folder = zoo / "models" / row["model_name"]
        reduced = json.loads((folder / "reduced-config.json").read_text())
        assert reduced["world"] == row["world"] and reduced["parameters"] > 0
        episodes = sorted((folder / "clean-example-data").glob("*.npz"))
        assert len(episodes) == 2
        with np.load(episodes[0], allow_pickle=False) as data:
            obs = [k for k in data.files if k == "obs" or k.startswith("obs_")]
            assert obs and len(data["actions"]) == len(data["rewards"]) == len(data[obs[0]]) >= 1
    out = report(zoo)
    tables = read_metadata(out / "tables.csv")
    assert {(r["world"], r["label"]) for r in tables if r["population"] == "dataset"} == {(w, label) for w in worlds.names() for label in ("clean", "poisoned")}
    table5 = [r for r in read_metadata(out / "convergence.csv") if r["arch"] == "all" and r["label"] == "poisoned"]
    assert {r["world"] for r in table5} == set(worlds.names()) and all(r["converged"] == r["attempted"] for r in table5)
    result = split(zoo, 0.5, 0.5, tmp_path / "train", tmp_path / "test", seed=0)
    assert result["train"]["models"] + result["test"]["models"] == 16
    train = {r["poison.trigger"] for r in read_metadata(tmp_path / "train" / "METADATA.csv")}
    test = {r["poison.trigger"] for r in read_metadata(tmp_path / "test" / "METADATA.csv")}
    assert train and test and not train & test
