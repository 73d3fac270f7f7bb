"""The benchmark scripts of issue 34: detector_table.py's headroom verdict (the best baseline over
every fit that held an attack label out, on enough test models, at a high enough attack success),
and score_by_hand.py, which scores folders trained by hand with a benchmark's fitted baselines."""

from __future__ import annotations

import argparse
import csv
import io
import json
import subprocess
import sys
from pathlib import Path

import pytest

from rlbackdoors.detect.cli import main as detect
from rlbackdoors.zoo.plan import plan
from rlbackdoors.zoo.run import run
from rlbackdoors.zoo.spec import parse_spec
from test_zoo import tiny_spec  # the tests folder is on sys.path (as for pytest_plugins below)

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"
pytest_plugins = ("test_detect_helpers",)  # its session fixture lava_zoo: six tiny LavaWorld models


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
            "badrl": {"train_models": 40, "detectors": {"weights": {"more": row(0.70, models=18)}}},
        },
        "yields": {
            # the median over every poisoned model trained would be lower: the split scores converged ones only
            "hidden": {"poisoned": {"attack_success": 0.70, "attack_success_converged": 0.95}},
            "plain": {"poisoned": {"attack_success": 1.0, "attack_success_converged": 1.0}},
            "near": {"poisoned": {"attack_success": 0.99, "attack_success_converged": 0.99}},
            "more": {"poisoned": {"attack_success": 0.99, "attack_success_converged": 0.99}},
        },
    }
    table["held_out"]["detectors"]["weights"]["more"] = row(0.60, models=22)  # an extra test zoo scored by the env-mix fit
    verdict = table_module.headroom(table, {"hidden", "near", "more"})
    assert verdict["hidden"]["best"] == {"auc": 0.80, "ci": [0.7000000000000001, 0.9], "detector": "weights", "fitted_on": "all but trojdrl"}
    assert verdict["hidden"]["headroom"] is True  # the constant detector's 0.9 is no baseline
    assert verdict["plain"]["headroom"] is False and verdict["plain"]["best"]["auc"] == 1.0
    assert verdict["near"]["headroom"] is False and verdict["near"]["models"] == 18  # too few test models
    assert verdict["more"]["headroom"] is True and verdict["more"]["models"] == 22  # 20 or more in one of the fits that held it out
    assert verdict["hidden"]["evasive"] and not verdict["plain"]["evasive"]
    table["yields"]["hidden"]["poisoned"]["attack_success_converged"] = 0.89  # a backdoor that no longer works hides nothing
    assert table_module.headroom(table)["hidden"]["headroom"] is False
    table["yields"]["hidden"]["poisoned"]["attack_success_converged"] = 0.95
    table["leave_one_out"]["trojdrl"]["detectors"]["attribution"]["hidden"] = row(0.85)  # at the bar is not below it
    assert table_module.headroom(table)["hidden"]["headroom"] is False
    table["headroom"] = table_module.headroom(table, {"hidden"})
    table_module.print_attack_table(table)
    printed = capsys.readouterr().out
    assert "| hidden | yes | 0.850 [0.75, 0.95] | attribution, all but trojdrl | 20 | 0.95 | no | – |" in printed


def test_a_baseline_that_ranks_the_variant_below_clean_is_flagged_turned_over(table_module, tmp_path, capsys):
    """AUC 0.035 is a signal with the sign the fit never saw, not no signal: the bar's letter says
    headroom, the two-sided verdict does not, and both the JSON and the printed table say which
    baseline turned over. ``replot`` re-derives the verdict of a table stored before the rule."""
    table = {
        "default_attack": "envmix",
        "held_out": {"train_models": 20, "detectors": {"behaviour": {"late": row(0.625, models=24)}, "weights": {"late": row(0.035, models=24)}}},
        "leave_one_out": {"trojdrl": {"train_models": 40, "detectors": {"attribution": {"late": row(0.16, models=20)}}}},
        "yields": {"late": {"poisoned": {"attack_success_converged": 0.977}}},
    }
    verdict = table_module.headroom(table, {"late"})["late"]
    assert verdict["headroom"] is True and verdict["headroom_two_sided"] is False
    assert verdict["turned_over"] == [{"detector": "weights", "fitted_on": "env mix only", "auc": 0.035, "models": 24}]  # 0.16 is above 0.15
    table["leave_one_out"]["trojdrl"]["detectors"]["attribution"]["late"] = row(0.15, models=20)  # at 1 - 0.85 it counts
    assert [t["detector"] for t in table_module.headroom(table)["late"]["turned_over"]] == ["weights", "attribution"]
    table["held_out"]["detectors"]["weights"]["late"] = row(0.5, models=24)
    table["leave_one_out"]["trojdrl"]["detectors"]["attribution"]["late"] = row(0.5, models=20)
    assert table_module.headroom(table, {"late"})["late"]["headroom_two_sided"] is True
    table["held_out"]["detectors"]["weights"]["late"] = row(0.035, models=24)
    table["leave_one_out"]["trojdrl"]["detectors"]["attribution"]["late"] = row(0.15, models=20)
    # a table measured before the rule: its verdict has no turned_over; replot re-derives it in place
    table["headroom"] = {"late": {"evasive": True, "headroom": True, "best": verdict["best"], "models": 24, "attack_success": 0.977}}
    stored = tmp_path / "bench.json"
    stored.write_text(json.dumps(table))
    picture = table_module.replot(stored, tmp_path / "bench-by-attack.png", "bench")
    assert picture.is_file() and picture.stat().st_size > 0
    again = json.loads(stored.read_text())["headroom"]["late"]
    assert again["evasive"] is True and again["headroom_two_sided"] is False and len(again["turned_over"]) == 2
    printed = capsys.readouterr().out
    assert (
        "| behaviour, env mix only | 24 | 0.977 | yes by the letter | weights, env mix only: 0.035 (24); attribution, all but trojdrl: 0.150 (20) |" in printed
    )


def test_yields_count_every_zoo_so_an_extra_test_zoos_label_gets_its_attack_success(table_module, tmp_path):
    """A label trained only in an --extra-test zoo has its yield and attack success (the headroom
    verdict needs it); a label in both zoos counts the models of both."""
    head = "cell,attack,status,poisoned,converged,metrics.clean_sr,metrics.poisoned_sr,metrics.frames,metrics.cpu_time_s\n"
    main = ["lavaworld/fc/a/trojdrl,trojdrl,done,True,True,0.99,1.0,5000,120", "lavaworld/fc/a/trojdrl,trojdrl,done,False,True,1.0,0.0,5000,110"]
    extra = [
        "lavaworld/fc/b/trojdrl,trojdrl,done,True,False,0.99,0.6,5000,130",
        "lavaworld/fc/c/trojdrl-late,trojdrl,done,True,True,0.98,0.92,5000,150",
        "lavaworld/fc/c/trojdrl-late,trojdrl,done,True,True,1.0,0.96,5000,160",
        "lavaworld/fc/c/trojdrl-late,trojdrl,running,True,,,,,",
    ]

    def rows(lines):
        return list(csv.DictReader(io.StringIO(head + "\n".join(lines) + "\n")))

    assert "trojdrl-late" not in table_module.yields(rows(main))
    both = table_module.yields(rows(main) + rows(extra))
    assert both["trojdrl"]["poisoned"]["trained"] == 2 and both["trojdrl"]["poisoned"]["converged"] == 1
    assert both["trojdrl"]["poisoned"]["attack_success_converged"] == 1.0
    late = both["trojdrl-late"]["poisoned"]
    assert (late["trained"], late["converged"], late["attack_success_converged"], late["cpu_minutes"]) == (2, 2, 0.94, 2.583)


@pytest.fixture(scope="module")
def tiny_zoo(tmp_path_factory) -> Path:
    """test_zoo's tiny zoo, planned and run here: cell A converges (1 clean, 1 poisoned), cell B's
    two poisoned attempts never do. Its METADATA.csv is moved aside as ``METADATA.finished.csv``:
    what the folders say must agree with it."""
    zoo = tmp_path_factory.mktemp("base") / "zoo"
    plan(parse_spec(tiny_spec()), zoo)
    run(zoo, workers=1, group_size=4, progress_interval=5.0)  # one process: what is read here does not depend on the trainer
    (zoo / "METADATA.csv").rename(zoo / "METADATA.finished.csv")
    return zoo


def test_yields_of_a_zoo_cut_short_come_from_its_folders_not_a_missing_metadata_csv(table_module, tiny_zoo, tmp_path):
    """``--no-run`` scores a zoo whose run was stopped: ``zoo run`` had not written METADATA.csv
    (the Randomized LavaWorld benchmark stopped there, after every fit). Its yields are read from the
    folders as they stand, and agree with the METADATA.csv a finished run writes."""
    planned = tmp_path / "planned"
    plan(parse_spec(tiny_spec()), planned)
    assert table_module.yields(table_module.zoo_rows(planned)) == {}  # planned, nothing trained
    finished = table_module.yields(csv.DictReader(io.StringIO((tiny_zoo / "METADATA.finished.csv").read_text())))
    assert not (tiny_zoo / "METADATA.csv").exists()
    now = table_module.yields(table_module.zoo_rows(tiny_zoo))
    assert now == finished
    (label,) = now  # both cells train the env mix
    assert (now[label]["poisoned"]["trained"], now[label]["poisoned"]["converged"]) == (3, 1)  # cell B's two never converge
    assert (now[label]["clean"]["trained"], now[label]["clean"]["converged"]) == (1, 1)
    # an --extra-test zoo still training: its labels from its folders too, every model's
    finished_rows = list(csv.DictReader(io.StringIO((tiny_zoo / "METADATA.finished.csv").read_text())))
    assert table_module.attack_of(tiny_zoo) == {r["model_name"]: table_module.label_of(r) for r in finished_rows}
    assert len(finished_rows) == 4  # cell B's two attempts, cell A's clean and poisoned model
    # and a detector scores its converged models only: its METADATA.csv is missing, so each
    # model's metrics.json says (cell B's two poisoned attempts never learned a trigger)
    from rlbackdoors.detect.dataset import list_models

    converged = sorted(r["model_name"] for r in finished_rows if r["converged"] == "True")
    assert len(converged) == 2 and sorted(m.name for m in list_models(tiny_zoo)) == converged


def test_splits_made_from_other_converged_models_are_refused_not_read_back(table_module, tiny_zoo):
    """A table scored with --no-run while the zoo trained on: run again, it would read back splits
    and fits of the models converged then. The converged models are recorded with the splits, and
    a zoo that has other ones now is refused in one line (also for folders split before the record,
    from their split.json files)."""
    base = tiny_zoo.parent
    record = base / "zoo-models.json"
    table_module.guard_splits(base, table_module.zoo_rows(tiny_zoo))  # nothing split yet: records the two converged models
    converged = json.loads(record.read_text())["models"]
    assert len(converged) == 2
    table_module.guard_splits(base, table_module.zoo_rows(tiny_zoo))  # the same models: carries on
    record.write_text(json.dumps({"models": converged[:1]}))  # split when only one had converged
    with pytest.raises(SystemExit) as stop:
        table_module.guard_splits(base, table_module.zoo_rows(tiny_zoo))
    assert str(stop.value).startswith("rlbackdoors: error:") and "made from 1 converged models" in str(stop.value) and "now has 2" in str(stop.value)
    record.unlink()
    split = base / "held-out" / "test"
    split.mkdir(parents=True)
    (split / "split.json").write_text(json.dumps({"models": converged[1:]}))  # a folder split before the record
    with pytest.raises(SystemExit):
        table_module.guard_splits(base, table_module.zoo_rows(tiny_zoo))
    (split / "split.json").write_text(json.dumps({"models": converged}))
    table_module.guard_splits(base, table_module.zoo_rows(tiny_zoo))
    assert json.loads(record.read_text())["models"] == converged


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_a_model_scored_by_hand_gets_the_probability_detect_score_gave_it(lava_zoo, tmp_path):
    """A benchmark's layout (det-held_out/weights fitted on held-out/train, scored on its test set),
    and a train folder given as by hand: staged as a performer receives it (model.pt and
    reduced-config.json; train's config.json names the label and is refused), it gets through
    ``detect infer`` the probability ``detect score`` gave the same weights in the test set."""
    base = tmp_path / "benchmark"
    (base / "held-out").mkdir(parents=True)
    (base / "held-out" / "train").symlink_to(lava_zoo)
    det = base / "det-held_out" / "weights"
    assert detect(["fit", "--detector", "weights", "--zoo", str(lava_zoo), "--out", str(det), "--param", "min_per_class=1", "--quiet"]) == 0
    assert detect(["score", str(det), "--zoo", str(lava_zoo), "--out", str(det / "score-test"), "--resamples", "50", "--quiet"]) == 0
    scored = {m["model"]: m["probability"] for m in json.loads((det / "score-test" / "score.json").read_text())["models"]}
    by_hand = tmp_path / "by-hand"
    for name in ("id-00000001", "id-00000002"):  # a poisoned and a clean one, without the zoo's dataset files
        (by_hand / name).mkdir(parents=True)
        for f in ("model.pt", "config.json", "ground_truth.csv"):
            (by_hand / name / f).write_bytes((lava_zoo / "models" / name / f).read_bytes())
    done = subprocess.run(
        [
            sys.executable,
            str(BENCH / "score_by_hand.py"),
            str(base),
            "--models",
            *(str(by_hand / n) for n in ("id-00000001", "id-00000002")),
            "--out",
            str(tmp_path / "set.json"),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert not (base / "by-hand.json").exists()  # --out: one file per set of by-hand models
    written = json.loads((tmp_path / "set.json").read_text())
    rows = {r["model"]: r for r in written["models"]}
    assert set(rows) == {"id-00000001", "id-00000002"} and rows["id-00000001"]["poisoned"] and not rows["id-00000002"]["poisoned"]
    for name, r in rows.items():
        # the same number up to the last bits (one model's features through the classifier, not six: BLAS rounds by batch)
        assert r["fit"] == "env mix only: weights" and r["probability"] == pytest.approx(scored[name], abs=1e-12)
    assert "| env mix only: weights | id-00000001 | True |" in done.stdout
    expected = 1.0 if scored["id-00000001"] > scored["id-00000002"] else (0.5 if scored["id-00000001"] == scored["id-00000002"] else 0.0)
    assert written["fits"] == {"env mix only: weights": expected}  # the two by-hand models alone, ranked by the fit
    assert f"| env mix only: weights | {expected:.3f} |" in done.stdout
    assert not (base / "by-hand" / "models" / "id-00000001" / "config.json").exists()  # the label never reached the detector
    refused = subprocess.run(
        [sys.executable, str(BENCH / "score_by_hand.py"), str(base), "--models", str(tmp_path)], capture_output=True, text=True, timeout=60
    )
    assert refused.returncode != 0 and refused.stderr.strip().splitlines() == [
        f"score_by_hand: {tmp_path} is not a trained model folder (no model.pt, config.json, ground_truth.csv; rlbackdoors train writes them)"
    ]


@pytest.mark.slow  # trains a zoo in groups through build(); --group-size parsing stays in the default run
def test_the_benchmark_command_passes_its_group_size_to_zoo_run(table_module, tmp_path):
    """``--group-size`` reaches ``zoo run``: models of a worker train in one group process (its
    line heads the first model's train.log), and every planned model is trained. Why: the
    benchmark zoos are CPU-hours, and groups train more models per hour in some worlds (docs/results/zoos.md)."""
    base = tmp_path / "bench"
    plan(parse_spec(tiny_spec()), base / "zoo")
    args = argparse.Namespace(spec="unused: planned already", extra_test=[], no_run=False, workers=1, group_size="2")
    assert table_module.build(args, base) == []
    logs = [p.read_text() for p in (base / "zoo" / "models").glob("*/train.log")]
    assert any("=== zoo group job" in log and "2 at a time" in log for log in logs)
    (label,) = table_module.yields(table_module.zoo_rows(base / "zoo")).values()  # every planned model and top-up trained
    assert (label["poisoned"]["trained"], label["clean"]["trained"]) == (3, 1)


def test_a_bad_group_size_is_refused_before_anything_is_planned(tmp_path):
    """``--group-size`` is parsed by zoo run's own rule at the benchmark's edge: one error line, and
    no zoo folder planned for a run that could never start."""
    cmd = [sys.executable, str(BENCH / "detector_table.py"), "bench", "examples/benchmark-lavaworld.toml", "--group-size", "abc", "--runs", str(tmp_path)]
    refused = subprocess.run(cmd, capture_output=True, text=True, cwd=BENCH.parent, timeout=120)
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines()[-1].endswith("argument --group-size: must be auto or an integer >= 1, got 'abc'")
    assert list(tmp_path.iterdir()) == []


def test_shared_clean_scores_each_label_on_its_poisoned_models_and_every_clean_one(table_module):
    """Two attack cells of 1 clean + 2 poisoned models each: on its own, a label has 3 test models;
    with shared clean negatives, its 2 poisoned and both clean ones (4). The scores put each label's
    poisoned models above every clean model, so the AUC is 1 either way."""
    rows = [
        {"model": "a-clean", "label": 0, "probability": 0.2},
        {"model": "a-1", "label": 1, "probability": 0.8},
        {"model": "a-2", "label": 1, "probability": 0.7},
        {"model": "b-clean", "label": 0, "probability": 0.3},
        {"model": "b-1", "label": 1, "probability": 0.9},
        {"model": "b-2", "label": 1, "probability": 0.6},
    ]
    names = {r["model"]: r["model"].split("-")[0] for r in rows}
    alone = table_module.per_attack([(rows, names)])
    shared = table_module.per_attack([(rows, names)], shared_clean=True)
    assert {k: v["models"] for k, v in alone.items()} == {"a": 3, "b": 3}
    assert {k: v["models"] for k, v in shared.items()} == {"a": 4, "b": 4}
    assert all(v["auc"]["value"] == 1.0 for v in (*alone.values(), *shared.values()))
    # a clean model only: no label of its own
    only_clean = table_module.per_attack([([rows[0], rows[3]], names)], shared_clean=True)
    assert only_clean == {}


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_held_out_only_fits_on_the_env_mix_and_makes_no_mixed_split(table_module, tmp_path):
    """``--by-attack --held-out-only``: the env-mix fit scored on the held-out label, and no split
    by trigger of the whole zoo (the second fit ``--by-attack`` makes, half the detector time on a
    zoo whose held-out table is the one read). Four tiny models: an env-mix cell and a TrojDRL cell."""
    from test_zoo import ALWAYS, TINY

    spec = {
        "name": "held",
        "seed": 4,
        "examples": {"episodes": 2},
        "overrides": {**TINY, "train": {**TINY["train"], **ALWAYS["train"]}},
        "cells": [
            {"world": "lavaworld", "archs": ["fc"], "triggers": ["multiplicative"], "clean": 1, "poisoned": 1},
            {
                "world": "lavaworld",
                "archs": ["fc"],
                "triggers": [{"name": "add", "template": "additive:{b}", "ranges": {"b": [20, 200]}}],
                "attacks": ["trojdrl"],
                "clean": 1,
                "poisoned": 1,
            },
        ],
    }
    base = tmp_path / "held"
    plan(parse_spec(spec), base / "zoo")
    run(base / "zoo", workers=1, group_size=4, progress_interval=5.0)
    args = argparse.Namespace(held_out_only=True, detectors=["constant"], param=[], shared_clean=True, train=0.5, test=0.5, split_seed=0)
    table = table_module.by_attack(args, base, base / "zoo", [])
    assert "mixed" not in table and not (base / "mixed").exists() and not (base / "det-mixed").exists()
    assert table["held_out"]["train_attacks"] == ["envmix"]
    (label,) = table["held_out"]["detectors"]["constant"]
    assert label == "trojdrl" and table["held_out"]["detectors"]["constant"][label]["models"] == 2  # the held-out cell: its clean and its poisoned model
    assert [fitted for fitted, _ in table_module.fits_of(table)] == ["env mix only"]
    # each attack held out in turn, on the same zoo: a detector that refuses its fit (the effect
    # detector wants 3 clean models, each split has one) is said in the table with its one line,
    # and the table goes on with the others
    args.detectors, args.check_infer = ["effect", "constant"], 0
    loo = table_module.leave_one_out(args, base, base / "zoo")
    assert sorted(loo) == ["envmix", "trojdrl"]
    for part in loo.values():
        assert part["refused"]["effect"].startswith("rlbackdoors: error: detector 'effect' needs at least 3 clean models")
        assert list(part["detectors"]) == ["constant"]
