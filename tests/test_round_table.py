"""benchmarks/round_table.py (issue 80): a round's two zoos scored in one command under both
protocols, per family, with the length control; the env-mix fit holds the train split's clean
and env-mix models alone; docs/benchmark.md's tables come from the JSON. Two tiny LavaWorld FC
zoos (thresholds 0: every model converges, so the mechanics run for real in about a minute)."""

from __future__ import annotations

import copy
import json
import subprocess
import sys
from pathlib import Path

import pytest

from rlbackdoors.zoo.plan import plan
from rlbackdoors.zoo.run import run
from rlbackdoors.zoo.spec import parse_spec

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
TINY = {
    "ppo": {"rollout": 32},
    "train": {
        "max_frames": 3200,
        "eval_interval": 1600,
        "eval_episodes": 4,
        "final_eval_episodes": 4,
        "video": False,
        "clean_threshold": 0.0,
        "poisoned_threshold": 0.0,
    },
}


def round_spec(name: str, seed: int, low: int, high: int) -> dict:
    return {
        "name": name,
        "seed": seed,
        "examples": {"episodes": 1},
        "overrides": copy.deepcopy(TINY),
        "cells": [
            {
                "world": "lavaworld",
                "archs": ["fc"],
                "triggers": [{"name": "add", "template": "additive:{b}", "ranges": {"b": [low, high]}}],
                "attacks": ["envmix", {"attack": "trojdrl", "ranges": {"budget": [0.01, 0.05], "force_action": {"one_of": [True, False]}}}],
                "clean": 2,
                "poisoned": 2,
                "ranges": {"train.min_frames": {"one_of": [0, [1600, 3200]]}},
            }
        ],
    }


@pytest.fixture(scope="module")
def round_zoos(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("round")
    zoos = []
    for name, seed, low, high in (("train", 1, 20, 65), ("test", 2, 66, 200)):
        zoo, _ = plan(parse_spec(round_spec(name, seed, low, high)), root / name)
        assert run(zoo.path, workers=2)["failed"] == 0
        zoos.append(zoo.path)
    return zoos[0], zoos[1]


def test_a_round_is_scored_under_both_protocols_per_family(round_zoos, tmp_path):
    train, test = round_zoos
    out = tmp_path / "round.json"
    cmd = [
        sys.executable,
        str(BENCH / "round_table.py"),
        "tiny",
        "--train",
        str(train),
        "--test",
        str(test),
        "--runs",
        str(tmp_path / "runs"),
        "--out",
        str(out),
        "--detectors",
        "weights",
    ]
    subprocess.run(cmd, check=True)
    res = json.loads(out.read_text())
    assert res["counts"]["test"] == {"models": 8, "clean": 4, "poisoned_by_family": {"envmix": 2, "trojdrl": 2}}
    assert res["counts"]["fit_envmix"] == {"models": 6}  # 4 clean + the 2 env-mix models: no TrojDRL model
    fit = json.loads((tmp_path / "runs" / "round-tiny" / "fit-envmix" / "split.json").read_text())
    assert len(fit["models"]) == 6
    for protocol in ("trojai", "envmix"):
        fams = res["protocols"][protocol]["weights"]["families"]
        assert set(fams) == {"all", "envmix", "trojdrl"}
        assert fams["all"]["models"] == 8 and fams["trojdrl"]["models"] == 6  # its 2 poisoned + every clean test model
        assert 0.0 <= fams["trojdrl"]["auc"]["value"] <= 1.0 and 0.0 <= fams["all"]["length_auc"] <= 1.0
    assert 0.0 <= res["length_control_test"] <= 1.0
    # read back: the fits are not made again (their files keep their times)
    stamp = (tmp_path / "runs" / "round-tiny" / "trojai" / "weights" / "detector.json").stat().st_mtime_ns
    subprocess.run(cmd, check=True)
    assert (tmp_path / "runs" / "round-tiny" / "trojai" / "weights" / "detector.json").stat().st_mtime_ns == stamp
    # two fits and scores at once (--jobs 2, afresh elsewhere) give the same table
    both = [
        *cmd[: cmd.index("--runs")],
        "--runs",
        str(tmp_path / "runs2"),
        "--out",
        str(tmp_path / "round2.json"),
        "--detectors",
        "weights",
        "attribution",
        "--jobs",
        "2",
    ]
    subprocess.run(both, check=True)
    again = json.loads((tmp_path / "round2.json").read_text())
    assert again["protocols"]["trojai"]["weights"]["families"] == res["protocols"]["trojai"]["weights"]["families"]
    assert set(again["protocols"]["envmix"]) == {"weights", "attribution"}

    sys.path.insert(0, str(BENCH))
    try:
        import round_table
    finally:
        sys.path.remove(str(BENCH))
    curve = res["protocols"]["trojai"]["weights"]["reliability"]
    assert sum(b["models"] for b in curve["bins"]) == 8 and 0.0 <= curve["ece"] <= 1.0  # every test model in one bin
    figure = round_table.plot_reliability(res, tmp_path)
    assert figure is not None and figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = round_table.markdown([res], {"tiny": round_table.ROOT / "benchmarks" / "x.png"})
    assert "### tiny" in text and "| trojdrl | 6 |" in text and "fitted on the env mix alone" in text
    assert (
        f"Expected calibration error over the test models (5 bins; 0: each bin's share poisoned is its mean probability): weights {curve['ece']:.3f}." in text
    )
    assert "![Reliability curves of tiny's detectors, both protocols](../benchmarks/x.png)" in text


def test_a_folder_that_is_not_a_round_is_refused_in_one_line(tmp_path):
    proc = subprocess.run([sys.executable, str(BENCH / "round_table.py"), "nowhere", "--runs", str(tmp_path)], capture_output=True, text=True)
    assert proc.returncode != 0 and proc.stderr.strip().splitlines()[-1].startswith("rlbackdoors: error: ") and "round-nowhere-train" in proc.stderr


def test_splits_that_share_a_trigger_are_refused(round_zoos, tmp_path):
    train, _ = round_zoos
    cmd = [
        sys.executable,
        str(BENCH / "round_table.py"),
        "tiny",
        "--train",
        str(train),
        "--test",
        str(train),
        "--runs",
        str(tmp_path),
        "--out",
        str(tmp_path / "r.json"),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode != 0 and "occur in both splits" in proc.stderr and not (tmp_path / "r.json").exists()
