"""Zoos: spec validation, deterministic planning, runs that lose nothing (kill -9 included), top-up,
failures, METADATA.csv, splits disjoint by trigger, the report, and the Ray back-end.

Budgets are tiny (LavaWorld FC, a few thousand frames); convergence is steered with the
thresholds: 0.0 makes every model converge, 1.0 none, so both paths are exercised for real.
"""

from __future__ import annotations

import copy
import hashlib
import json
import shutil
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from rlbackdoors.io import FolderLock
from rlbackdoors.validate import ConfigError
from rlbackdoors.zoo.index import LEAD_COLUMNS, read_metadata, scan
from rlbackdoors.zoo.job import is_locked
from rlbackdoors.zoo.plan import Zoo, plan
from rlbackdoors.zoo.report import report, wilson
from rlbackdoors.zoo.run import run
from rlbackdoors.zoo.spec import ZooError, load_spec, parse_spec
from rlbackdoors.zoo.split import split
from cli_helpers import cli as run_cli

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "rlbackdoors.zoo.cli"]
TINY = {"ppo": {"rollout": 32}, "train": {"max_frames": 6400, "eval_interval": 1600, "eval_episodes": 5, "final_eval_episodes": 5, "video": False}}
ALWAYS = {"train": {"clean_threshold": 0.0, "poisoned_threshold": 0.0}}  # every final evaluation passes
# No tiny model gets there; trains 6 evaluations long (the kill test stops one in the middle).
NEVER = {"train": {"clean_threshold": 1.0, "poisoned_threshold": 1.0, "max_frames": 9600}}


def tiny_spec() -> dict:
    """Cell B never converges, so its poisoned group is topped up to max_attempts = 2 (first in
    the spec: its chain of two models starts first); cell A converges (1 clean + 1 poisoned)."""
    return {
        "name": "tiny",
        "seed": 3,
        "examples": {"episodes": 2},
        "overrides": copy.deepcopy(TINY),
        "cells": [
            {
                "world": "lavaworld",
                "archs": ["fc"],
                "triggers": [{"name": "add", "template": "additive:{b}", "ranges": {"b": [20, 200]}}],
                "poisoned": 1,
                "max_attempts": 2,
                "overrides": NEVER,
            },
            {"world": "lavaworld", "archs": ["fc"], "triggers": ["multiplicative"], "clean": 1, "poisoned": 1, "overrides": ALWAYS},
        ],
    }


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def hashes(zoo: Path, name: str = "model.pt") -> dict[str, str]:
    return {p.parent.name: sha(p) for p in sorted((zoo / "models").glob(f"*/{name}"))}


def cli(*args, check: bool = False) -> subprocess.CompletedProcess:
    """``python -m rlbackdoors.zoo.cli`` in this process (cli_helpers); the kills use real processes."""
    return run_cli(*args, module="rlbackdoors.zoo.cli", check=check)


@pytest.fixture(scope="module")
def tiny_zoo(tmp_path_factory) -> tuple[Path, dict]:
    """The tiny zoo, planned and run once without interruption (the reference for the others)."""
    path = tmp_path_factory.mktemp("zoo") / "tiny"
    plan(parse_spec(tiny_spec()), path)
    summary = run(path, workers=2, progress_interval=5.0)
    return path, summary


# --- the spec ------------------------------------------------------------------------------


def _mutate(change):
    spec = tiny_spec()
    change(spec)
    return spec


BAD_SPECS = [
    (lambda s: s["cells"][0].update(world="lavaland"), "cells[0].world='lavaland' is not allowed (allowed: lavaworld"),
    (lambda s: s["cells"][0]["triggers"][0]["ranges"].update(b=[200, 20]), "cells[0].triggers[0].ranges.b=[200, 20] is an empty range"),
    (lambda s: s["cells"][1].update(max_attempts=1, poisoned=3), "cells[1].max_attempts=1 is less than the 3 converged poisoned models"),
    (lambda s: s.update(seeds=1), "seeds is not a spec field (allowed: format, name, seed"),
    (lambda s: s.pop("seed"), "seed (the master seed every model is drawn from) is required"),
    (lambda s: s.update(seed=-1), "seed must be in 0..4,294,967,295, got -1"),
    (lambda s: s["cells"][1].update(archs=["fc", "mlp"]), "cells[1].archs[1]='mlp' is not allowed for lavaworld (allowed: fc, cnn)"),
    (lambda s: s["overrides"]["train"].update(seed=4), "overrides.train.seed is set by the zoo"),
    (lambda s: s["overrides"]["train"].update(max_frame=4), ("overrides (in cells[0], lavaworld): ", "'max_frame'")),  # the rest: the config's
    (lambda s: s["cells"][1].update(overrides={"train": {"max_frame": 4}}), ("cells[1].overrides: ", "'max_frame'")),
    (lambda s: s["cells"][1].update(triggers=["multiplicative:300"]), "cells[1].triggers[0]='multiplicative:300' is not a lavaworld trigger"),
    (lambda s: s["cells"][0]["triggers"][0]["ranges"].update(b=[20, 300]), "cells[0].triggers[0].template with ranges at their high ends"),
    (lambda s: s["cells"][0]["triggers"][0].update(template="additive:{c}"), "cells[0].triggers[0].ranges has no range for c"),
    (lambda s: s["cells"][1].update(models=2), "cells[1]: give either models (with poisoned_share) or clean and poisoned"),
    (lambda s: s["cells"][1].update(clean=0, poisoned=0), "cells[1]: clean + poisoned must be >= 1"),
    (lambda s: s["cells"].append(copy.deepcopy(s["cells"][1])), "cells[2] repeats the cell lavaworld/fc/multiplicative of cells[1]"),
    # "has no named architectures" where the world names none, else the world's list
    (lambda s: s["cells"].append({"world": "safety-car-goal", "archs": ["fc"], "models": 1}), ("cells[2].archs", "safety-car-goal")),
    (lambda s: s.update(cells=[]), "cells must be a non-empty array"),
    (lambda s: s["examples"].update(policy="best"), "examples.policy='best' is not allowed (allowed: sample, greedy)"),
]


@pytest.mark.parametrize("change,message", BAD_SPECS)
def test_bad_specs_are_refused_with_the_field_named(change, message):
    with pytest.raises(ConfigError) as err:
        parse_spec(_mutate(change))
    for part in (message,) if isinstance(message, str) else message:
        assert part in str(err.value)
    assert "\n" not in str(err.value)


def test_a_bad_spec_file_gives_one_error_line_and_writes_nothing(tmp_path):
    spec = tmp_path / "bad.toml"
    spec.write_text('seed = 0\n[[cells]]\nworld = "lavaworld"\nmodels = 6\nmax_attempts = 2\n')
    result = cli("plan", spec, "--out", tmp_path / "zoo")
    assert result.returncode == 2
    assert result.stderr == (
        "rlbackdoors: error: cells[0].max_attempts=2 is less than the 3 converged poisoned models wanted per cell "
        "(max_attempts counts the models trained per cell and label)\n"
    )
    assert not (tmp_path / "zoo").exists()
    spec.write_text("seed = [\n")
    result = cli("plan", spec, "--out", tmp_path / "zoo")
    assert result.returncode == 2 and "is not valid TOML" in result.stderr and not (tmp_path / "zoo").exists()


def test_normalized_spec_reads_back_as_itself():
    spec = parse_spec(tiny_spec())
    again = parse_spec(spec.to_dict())
    assert again.to_dict() == spec.to_dict()
    assert [g.key for g in again.groups] == ["lavaworld/fc/add/poisoned", "lavaworld/fc/multiplicative/clean", "lavaworld/fc/multiplicative/poisoned"]


# --- planning --------------------------------------------------------------------------------


@pytest.mark.parametrize("example", sorted([*(ROOT / "examples").glob("zoo-*.toml"), *(ROOT / "examples").glob("benchmark-*.toml")]), ids=lambda p: p.stem)
def test_every_example_spec_plans_into_configs_that_load(example, tmp_path):
    """The specs the docs point to stay valid as config formats move on: each plans, and every
    planned config.json loads as today's RunConfig with the spec's overrides in it."""
    from rlbackdoors.config import FORMAT_VERSION, RunConfig

    spec = load_spec(example)
    plan(spec, tmp_path / "zoo")
    configs = sorted((tmp_path / "zoo" / "models").glob("*/config.json"))
    assert configs and len(configs) >= sum(g.wanted for g in spec.groups)
    overrides = spec.overrides.get("train", {})
    for path in configs:
        cfg = RunConfig.load(path)
        assert cfg.format_version == FORMAT_VERSION
        assert all(getattr(cfg.train, k) == v for k, v in overrides.items())


def test_plan_is_deterministic_a_no_op_again_and_refuses_another_spec(tmp_path):
    example = ROOT / "examples" / "zoo-lavaworld-small.toml"
    a, b = tmp_path / "a", tmp_path / "b"
    first = cli("plan", example, "--out", a, check=True)
    assert "planned 24 models in 4 cells" in first.stdout
    # a new zoo's trainers, a cell each: the compiled one where it was measured faster and tested equivalent
    assert "trainers: compiled: lavaworld/fc/multiplicative, lavaworld/fc/additive; torch: lavaworld/cnn/multiplicative, lavaworld/cnn/additive" in first.stdout
    assert "zoo: note: not matched" in first.stderr  # clean and poisoned models, matched = false: told once
    matched = cli("plan", ROOT / "examples" / "benchmark-lavaworld.toml", "--out", tmp_path / "m", check=True)
    assert "planned 80 models" in matched.stdout and "not matched" not in matched.stderr
    assert "min_frames < max_frames" in matched.stderr  # matched, but runs stop between 2.5 M and 5 M frames
    equal = cli("plan", ROOT / "examples" / "benchmark-lavaworld-equal.toml", "--out", tmp_path / "e", check=True)
    assert "planned 50 models" in equal.stdout and "note" not in equal.stderr  # every model trains 5 M frames
    plan(load_spec(example), b)
    files_a = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file() and p.name != ".lock")
    assert files_a == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file() and p.name != ".lock")
    assert len([f for f in files_a if f.name == "config.json"]) == 24
    for rel in files_a:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    truth = [int((a / rel).read_text()) for rel in files_a if rel.name == "ground_truth.csv"]
    assert sum(truth) == 12  # half of each cell poisoned
    triggers = {json.loads((a / rel).read_text())["poison"]["trigger"] for rel in files_a if rel.name == "config.json"}
    assert len(triggers) > 12 and all(t.split(":")[0] in ("multiplicative", "additive") for t in triggers)
    for t in triggers:  # the paper's ranges (a bare kind is drawn by the world)
        kind, value = t.split(":")
        assert (10 <= int(value) <= 24) if kind == "multiplicative" else (20 <= int(value) <= 200)
    before = {rel: (a / rel).stat().st_mtime_ns for rel in files_a}
    assert plan(load_spec(example), a)[1] == 0  # nothing written
    assert before == {rel: (a / rel).stat().st_mtime_ns for rel in files_a}
    changed = tmp_path / "changed.toml"
    changed.write_text(example.read_text().replace("seed = 0", "seed = 1"))
    refused = cli("plan", changed, "--out", a)
    assert refused.returncode == 2
    assert refused.stderr.startswith("rlbackdoors: error: zoo ") and "planned from another spec (seed differs)" in refused.stderr
    assert before == {rel: (a / rel).stat().st_mtime_ns for rel in files_a}


def test_top_up_draws_never_change_earlier_models(tmp_path):
    zoo, _ = plan(parse_spec(tiny_spec()), tmp_path / "z")
    group = zoo.spec.groups[0]  # cell B, poisoned: wants 1, may try 2
    first = zoo.folder(zoo.model(group, 0))
    before = {p.name: p.read_bytes() for p in first.iterdir() if p.is_file()}
    assert not zoo.folder(zoo.model(group, 1)).exists()
    assert zoo.ensure(group, 1)  # the top-up
    assert before == {p.name: p.read_bytes() for p in first.iterdir() if p.is_file()}
    fresh = Zoo.open(tmp_path / "z")  # a new coordinator draws the same model for the same slot
    assert fresh.draw(group, 1).to_json() == (zoo.folder(zoo.model(group, 1)) / "config.json").read_text()
    configs = [json.loads(fresh.draw(group, a).to_json()) for a in range(2)]
    assert configs[0]["train"]["seed"] != configs[1]["train"]["seed"]
    ids = [zoo.model(g, a).id for g in zoo.spec.groups for a in range(g.max_attempts)]
    assert sorted(ids) == list(range(zoo.spec.id_space))  # one id per slot, none shared
    assert not zoo.ensure(group, 1)  # already there: nothing written


def test_a_new_zoo_takes_auto_one_trainer_a_cell_and_an_old_zoo_keeps_torchs(tmp_path):
    """A zoo planned now records ``update_backend = "auto"``: a cell takes the compiled trainer
    only where its clean and poisoned models both would (an evasive cell's clean models have no
    variant, so they follow the cell), a cell's own override stands, and a zoo planned before
    the key (no ``update_backend`` in zoo.json) draws its top-ups with torch's, as its models."""
    frames = {"train": {"max_frames": 6400, "video": False}}
    spec = {
        "name": "backends",
        "seed": 3,
        "overrides": frames,
        "cells": [
            {"world": "lavaworld", "archs": ["fc"], "triggers": ["multiplicative"], "clean": 1, "poisoned": 1, "max_attempts": 2},
            {"world": "lavaworld", "archs": ["fc"], "triggers": ["additive"], "clean": 1, "poisoned": 1, "overrides": {"poison": {"evasion": {"near": 1.0}}}},
            {"world": "lavaworld", "archs": ["cnn"], "triggers": ["multiplicative"], "clean": 1, "poisoned": 1},
            {
                "world": "randomized-lavaworld",
                "archs": ["cnn"],
                "triggers": ["cross"],
                "clean": 1,
                "poisoned": 1,
                "overrides": {"ppo": {"update_backend": "torch"}},
            },
        ],
    }
    zoo, _ = plan(parse_spec(spec), tmp_path / "z")
    assert json.loads((tmp_path / "z" / "zoo.json").read_text())["update_backend"] == "auto"
    chosen = {}
    for group in zoo.spec.groups:
        cfg = json.loads((zoo.folder(zoo.model(group, 0)) / "config.json").read_text())
        chosen[group.key] = cfg["ppo"]["update_backend"]
    expected = {
        "lavaworld/fc/multiplicative": "compiled",
        "lavaworld/fc/additive": "torch",
        "lavaworld/cnn/multiplicative": "torch",
        "randomized-lavaworld/cnn/cross": "torch",
    }
    assert chosen == {g.key: expected[g.cell.key] for g in zoo.spec.groups}
    assert plan(parse_spec(spec), tmp_path / "z")[1] == 0  # planned again: the same draws
    # the same spec planned before the key existed
    meta_path = tmp_path / "z" / "zoo.json"
    meta = json.loads(meta_path.read_text())
    del meta["update_backend"]
    meta_path.write_text(json.dumps(meta))
    old = Zoo.open(tmp_path / "z")
    assert old.update_backend == "torch" and old.draw(zoo.spec.groups[0], 1).ppo.update_backend == "torch"
    meta["update_backend"] = "jax"
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(ZooError, match=r"update_backend='jax' is not allowed \(allowed: torch, auto\)$"):
        Zoo.open(tmp_path / "z")


# --- running ---------------------------------------------------------------------------------

DATASET_FILES = ("model.pt", "config.json", "reduced-config.json", "ground_truth.csv", "metrics.json", "log.csv", "training_curve.png", "train.log")


def test_run_trains_every_model_tops_up_and_marks_convergence(tiny_zoo):
    path, summary = tiny_zoo
    assert summary["models"] == 4 and summary["done"] == 4 and summary["converged"] == 2 and summary["failed"] == 0
    assert summary["short"] == ["lavaworld/fc/add/poisoned"]
    states = {s.model.group.key + f"/{s.model.attempt}": s for s in scan(Zoo.open(path))}
    assert sorted(states) == [
        "lavaworld/fc/add/poisoned/0",
        "lavaworld/fc/add/poisoned/1",
        "lavaworld/fc/multiplicative/clean/0",
        "lavaworld/fc/multiplicative/poisoned/0",
    ]
    for key, state in states.items():
        assert state.status == "done"
        for name in DATASET_FILES:
            assert (state.folder / name).is_file(), (key, name)
        assert not (state.folder / "checkpoint.pt").exists()
        assert (state.folder / "ground_truth.csv").read_text() == f"{int('poisoned' in key)}\n"
        assert state.converged == ("multiplicative" in key)
        assert state.metrics is not None and state.converged == state.metrics["converged"]
        if not state.converged:
            assert state.reason.startswith("clean_sr ") and "< 1" in state.reason
        reduced = json.loads((state.folder / "reduced-config.json").read_text())
        assert reduced["world"] == "lavaworld" and reduced["arch"] == "fc" and reduced["layers"]["state_emb.0.weight"] == [100, 147]
        assert "trigger" not in json.dumps(reduced) and "poison" not in json.dumps(reduced)
        assert reduced["env"] == {k: v for k, v in state.config["env"].items() if k != "name"}  # the world's settings
        episodes = sorted((state.folder / "clean-example-data").glob("episode-*.npz"))
        assert [p.name for p in episodes] == ["episode-000.npz", "episode-001.npz"]
        with np.load(episodes[0], allow_pickle=False) as data:
            assert data["obs"].dtype == np.uint8 and data["obs"].shape[1:] == (7, 7, 3)
            assert len(data["obs"]) == len(data["actions"]) == len(data["rewards"]) >= 1
            assert data["outcome"].shape == ()


def test_metadata_has_one_row_per_model_with_flattened_config_and_metrics(tiny_zoo):
    path, _ = tiny_zoo
    rows = read_metadata(path / "METADATA.csv")
    assert len(rows) == 4 and [r["model_name"] for r in rows] == sorted(r["model_name"] for r in rows)
    columns = list(rows[0])
    assert tuple(columns[: len(LEAD_COLUMNS)]) == LEAD_COLUMNS
    for column in (
        "env.name",
        "model.arch",
        "poison.trigger",
        "poison.poisoned",
        "train.seed",
        "train.max_frames",
        "metrics.clean_sr",
        "metrics.final_meets_thresholds",
    ):
        assert column in columns
    for row in rows:
        folder = path / "models" / row["model_name"]
        config = json.loads((folder / "config.json").read_text())
        metrics = json.loads((folder / "metrics.json").read_text())
        assert row["poison.trigger"] == config["poison"]["trigger"] and int(row["train.seed"]) == config["train"]["seed"]
        assert float(row["metrics.clean_sr"]) == metrics["clean_sr"]
        assert row["converged"] == str(metrics["final_meets_thresholds"])
        assert row["poisoned"] == str(config["poison"]["poisoned"]) == str(bool(int((folder / "ground_truth.csv").read_text())))
        assert (row["nonconverged_reason"] == "") == (row["converged"] == "True")


def test_run_again_trains_nothing_and_changes_nothing(tiny_zoo):
    path, _ = tiny_zoo
    files = [p for p in (path / "models").rglob("*") if p.is_file() and p.name not in (".lock", "train.log")]
    before = {p: (p.stat().st_mtime_ns, sha(p)) for p in files}
    summary = run(path, workers=2, progress_interval=5.0)
    assert summary["trained"] == 0 and summary["done"] == 4
    assert before == {p: (p.stat().st_mtime_ns, sha(p)) for p in files}


def test_status_prints_the_table_of_cells(tiny_zoo):
    path, _ = tiny_zoo
    result = cli("status", path, check=True)
    lines = result.stdout.splitlines()
    assert lines[0].split() == ["cell", "label", "wanted", "converged", "not", "conv.", "failed", "running", "left", "attempts", "state"]
    assert lines[2].split() == ["lavaworld/fc/add", "poisoned", "1", "0", "2", "0", "0", "0", "2/2", "short"]
    assert lines[3].split() == ["lavaworld/fc/multiplicative", "clean", "1", "1", "0", "0", "0", "0", "1/1", "complete"]
    assert lines[-1].split() == ["total", "3", "2", "2", "0", "0", "0"]


def test_split_is_disjoint_by_model_and_by_trigger(tiny_zoo, tmp_path):
    path, _ = tiny_zoo
    train, test = tmp_path / "train", tmp_path / "test"
    result = cli("split", path, "--train", 0.5, "--test", 0.5, "--out-train", train, "--out-test", test, "--seed", 1, check=True)
    assert "train:" in result.stdout
    got = {}
    for name, out in (("train", train), ("test", test)):
        rows = read_metadata(out / "METADATA.csv")
        got[name] = rows
        assert rows and all(r["converged"] == "True" for r in rows)
        assert sorted(p.name for p in (out / "models").iterdir()) == [r["model_name"] for r in rows]
        for r in rows:
            folder = out / "models" / r["model_name"]
            assert not (folder / ".lock").exists()
            assert sha(folder / "model.pt") == sha(path / "models" / r["model_name"] / "model.pt")
            assert (folder / "clean-example-data" / "episode-000.npz").is_file()
    names = [{r["model_name"] for r in got[k]} for k in ("train", "test")]
    triggers = [{r["poison.trigger"] for r in got[k]} for k in ("train", "test")]
    assert not names[0] & names[1] and not triggers[0] & triggers[1]
    assert len(names[0] | names[1]) == 2  # every converged model, nothing else
    split(path, 0.5, 0.5, train, test, seed=1)  # the same split again: completes, changes nothing
    assert read_metadata(train / "METADATA.csv") == got["train"]
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "mine.txt").write_text("not a split")
    with pytest.raises(ZooError, match="is not empty and holds another split"):
        split(path, 0.5, 0.5, tmp_path / "elsewhere", tmp_path / "test2", seed=1)
    assert not (tmp_path / "test2").exists()


def test_report_has_the_tables_and_plots_with_the_zoos_numbers(tiny_zoo):
    path, _ = tiny_zoo
    out = report(path)
    assert out == path / "report"
    for name in ("report.md", "tables.csv", "convergence.csv", "budget.csv", "scatter.png", "frames_hist.png", "curves.png"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    metrics = {p.parent.name: json.loads(p.read_text()) for p in (path / "models").glob("*/metrics.json")}
    rows = read_metadata(out / "tables.csv")
    finished_poisoned = next(r for r in rows if r["population"] == "finished" and r["label"] == "poisoned")
    values = [m["clean_sr"] for m in metrics.values() if m["poisoned"]]
    assert int(finished_poisoned["n"]) == 3
    assert math.isclose(float(finished_poisoned["clean_sr_mean"]), float(np.mean(values)))
    assert math.isclose(float(finished_poisoned["clean_sr_std"]), float(np.std(values, ddof=1)))
    assert finished_poisoned["table"] == "1" and finished_poisoned["poisoned_sr_paper"] == "0.98"
    conv = {(r["arch"], r["label"]): r for r in read_metadata(out / "convergence.csv")}
    poisoned = conv[("fc", "poisoned")]
    assert (poisoned["converged"], poisoned["attempted"]) == ("1", "3")
    low, high = wilson(1, 3)
    assert math.isclose(low, 0.0614, abs_tol=1e-3) and math.isclose(high, 0.7923, abs_tol=1e-3)  # the textbook Wilson interval
    assert math.isclose(float(poisoned["wilson_low"]), low) and math.isclose(float(poisoned["wilson_high"]), high)
    text = (out / "report.md").read_text()
    assert "Table 5" in text and "1 / 3" in text and "![clean SR vs poisoned SR](scatter.png)" in text


def _job_pids(zoo: Path) -> list[int]:
    """Processes running a job of this zoo: their stdout is a train.log of its models (jobs are
    forks of the coordinator's fork server, so their command line names no folder)."""
    pids = []
    models = str(zoo.resolve() / "models") + "/"
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                stdout = os.readlink(proc / "fd" / "1")
            except OSError:
                continue
            if stdout.startswith(models):
                pids.append(int(proc.name))
    return pids


def _parent(pid: int) -> int:
    return int((Path("/proc") / str(pid) / "stat").read_text().rpartition(")")[2].split()[1])


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, dead and not yet reaped, does not)."""
    try:
        return (Path("/proc") / str(pid) / "stat").read_text().rpartition(")")[2].split()[0] != "Z"
    except OSError:
        return False


def _wait_for(condition, timeout: float, what: str) -> None:
    deadline = time.time() + timeout
    while not condition():
        if time.time() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.02)


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="finds the job processes through /proc (Linux)")
def test_kill_9_of_a_worker_and_of_the_coordinator_then_rerun_gives_the_same_zoo(tiny_zoo, tmp_path):
    reference, _ = tiny_zoo
    path = tmp_path / "tiny"
    plan(parse_spec(tiny_spec()), path)
    log = open(tmp_path / "run.log", "w")
    coordinator = subprocess.Popen([*CLI, "run", str(path), "--workers", "2", "--progress-interval", "1"], stdout=log, stderr=log)
    try:
        # 1. kill -9 a worker that is mid-training (it has a checkpoint): the coordinator retries it
        def training_worker(not_pid: int | None = None) -> Path | None:
            """A folder of the never-converging cell (6 evaluations long) whose training is under
            way with evaluations left, held by a process other than ``not_pid`` (SIGTERM stops a
            run between updates; in its final evaluation and files it finishes instead, so the
            one-evaluation models of the other cell are no target on a loaded machine)."""
            for ckpt in (path / "models").glob("*/checkpoint.pt"):
                try:
                    rows = (ckpt.parent / "log.csv").read_text().count("\n") - 1
                    long = json.loads((ckpt.parent / "config.json").read_text())["train"]["max_frames"] == NEVER["train"]["max_frames"]
                    pid = json.loads((ckpt.parent / ".lock").read_text())["pid"]
                except (OSError, ValueError, KeyError):
                    continue
                if long and is_locked(ckpt.parent) and rows <= 3 and pid != not_pid:
                    return ckpt.parent
            return None

        _wait_for(lambda: training_worker() is not None, 120, "a worker with a checkpoint")
        folder = training_worker()
        assert folder is not None
        holder = json.loads((folder / ".lock").read_text())["pid"]
        assert holder in _job_pids(path)
        os.kill(holder, signal.SIGKILL)
        # 2. a second coordinator is refused while the first one runs
        second = cli("run", path)
        assert second.returncode == 2
        assert second.stderr.startswith(f"rlbackdoors: error: zoo {str(path)!r} is in use by process {coordinator.pid}")
        # 3. kill -9 the coordinator while a model trains (the retried one or the next). The job is
        # frozen first, so that it cannot finish its last few tiny evaluations in the moment its
        # parent takes to go: thawed, it finds its SIGTERM (parent death) waiting, and checkpoints
        frozen: list[int] = []

        def freeze_a_training_job() -> bool:
            folder = training_worker(not_pid=holder)
            if folder is None:
                return coordinator.poll() is not None
            pid = json.loads((folder / ".lock").read_text())["pid"]
            os.kill(pid, signal.SIGSTOP)
            frozen.append(pid)
            if (folder / "metrics.json").exists():  # it got there before the stop: thaw, look again
                os.kill(frozen.pop(), signal.SIGCONT)
                return False
            return True

        _wait_for(freeze_a_training_job, 120, "another training")
        assert coordinator.poll() is None, "the run finished before it could be killed"
        servers = {_parent(pid) for pid in frozen}  # the fork server the jobs came from
        coordinator.kill()
        coordinator.wait()
        _wait_for(lambda: not any(_alive(s) for s in servers), 60, "the fork server to go with its coordinator")
        for pid in frozen:
            os.kill(pid, signal.SIGCONT)
    finally:
        if coordinator.poll() is None:
            coordinator.kill()
        log.close()
    # no orphans: the children stop (checkpointing) when their coordinator dies
    _wait_for(lambda: not _job_pids(path), 60, "the orphaned jobs to stop")
    assert not any(is_locked(f) for f in (path / "models").iterdir())
    assert "retrying (1/2)" in (tmp_path / "run.log").read_text()
    unfinished = [f.name for f in (path / "models").iterdir() if not (f / "reduced-config.json").is_file()]
    assert unfinished, "the coordinator was killed after the zoo was complete"
    summary = run(path, workers=2, progress_interval=5.0)
    assert summary["trained"] >= 1 and summary["done"] == 4
    assert hashes(path) == hashes(reference) and len(hashes(path)) == 4
    assert hashes(path, "clean-example-data/episode-001.npz") == hashes(reference, "clean-example-data/episode-001.npz")
    assert sorted(p.name for p in (path / "models").iterdir()) == sorted(p.name for p in (reference / "models").iterdir())
    assert not list(path.rglob("*.rlbtmp")) and not list(path.rglob("checkpoint.pt"))
    timing = ("wall_time", "cpu_time", "fps", "versions")

    def comparable(rows):
        return [{k: v for k, v in r.items() if not any(t in k for t in timing)} for r in rows]

    assert comparable(read_metadata(path / "METADATA.csv")) == comparable(read_metadata(reference / "METADATA.csv"))


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="a cuda device makes the failing config train")
def test_a_failing_job_is_retried_then_recorded_and_a_busy_folder_is_waited_for(tmp_path):
    spec = {
        "seed": 5,
        "overrides": copy.deepcopy(TINY),
        "cells": [
            # train.device = cuda on a machine without one: training raises on every try
            {"world": "lavaworld", "archs": ["fc"], "triggers": ["additive"], "poisoned": 1, "overrides": {"train": {"device": "cuda"}}},
            {"world": "lavaworld", "archs": ["cnn"], "triggers": ["additive"], "clean": 1, "overrides": ALWAYS},
        ],
    }
    path = tmp_path / "z"
    zoo, _ = plan(parse_spec(spec), path)
    failing, busy = (zoo.folder(zoo.model(g, 0)) for g in zoo.spec.groups)
    config = (failing / "config.json").read_bytes()
    lock = FolderLock(busy, "model folder").acquire()  # a live process holds this folder
    holder = (busy / ".lock").read_bytes()
    seen_busy = []
    release = threading.Timer(4.0, lambda: (seen_busy.append((busy / ".lock").read_bytes() == holder and not (busy / "model.pt").exists()), lock.release()))
    release.start()
    try:
        summary = run(path, workers=2, max_retries=1, progress_interval=5.0)
    finally:
        release.cancel()
        lock.release()
    assert seen_busy == [True]  # untouched while it was held ...
    assert (busy / "reduced-config.json").is_file()  # ... and trained once it was free
    failure = json.loads((failing / "failed.json").read_text())
    assert failure["tries"] == 2 and "cuda" in failure["error"]
    assert (failing / "config.json").read_bytes() == config  # put back after each failed start
    assert not (failing / "model.pt").exists()
    assert summary["failed"] == 1 and summary["done"] == 1
    rows = {r["model_name"]: r for r in read_metadata(path / "METADATA.csv")}
    assert rows[failing.name]["status"] == "failed" and rows[failing.name]["converged"] == "False"
    assert rows[failing.name]["nonconverged_reason"].startswith("failed: ") and "cuda" in rows[failing.name]["nonconverged_reason"]
    log = (failing / "train.log").read_text()
    assert log.count("=== zoo job") == 2
    again = run(path, workers=2, max_retries=1, progress_interval=5.0)  # recorded: not tried again
    assert again["failed"] == 1 and (failing / "train.log").read_text() == log
    retried = run(path, workers=2, max_retries=0, retry_failed=True, progress_interval=5.0)
    assert retried["failed"] == 1 and (failing / "train.log").read_text().count("=== zoo job") == 3


def test_a_job_killed_while_it_finished_leaves_no_temp_files_after_the_rerun(tiny_zoo, tmp_path):
    """A job killed after metrics.json, while it wrote its example episodes (seen once in CI: the
    kill -9 test above found ``.episode-000.npz.PID.rlbtmp`` in a finished folder): the rerun
    finishes the folder again, removing the half-written file, and lists none in the manifest."""
    reference, _ = tiny_zoo
    path = tmp_path / "tiny"
    shutil.copytree(reference, path, ignore=shutil.ignore_patterns(".lock"))
    folder = sorted((path / "models").iterdir())[0]
    (folder / "reduced-config.json").unlink()  # not marked complete: the job was killed before
    stale = folder / "clean-example-data" / ".episode-000.npz.999999.rlbtmp"
    stale.write_bytes(b"half an episode")
    summary = run(path, workers=1, progress_interval=5.0)
    assert summary["done"] == 4 and summary["trained"] == 0
    assert not stale.exists() and not list(path.rglob("*.rlbtmp"))
    assert ".rlbtmp" not in "".join(p.read_text() for p in folder.iterdir() if p.is_file() and "manifest" in p.name.lower())
    assert hashes(path, "clean-example-data/episode-000.npz") == hashes(reference, "clean-example-data/episode-000.npz")
    assert (folder / "reduced-config.json").read_bytes() == (reference / "models" / folder.name / "reduced-config.json").read_bytes()


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_ray_backend_builds_the_same_zoo_as_the_local_one(tiny_zoo, tmp_path):
    ray = pytest.importorskip("ray", reason="Ray is an optional extra: pip install 'rlbackdoors[ray]'")
    reference, _ = tiny_zoo
    path = tmp_path / "tiny"
    plan(parse_spec(tiny_spec()), path)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        summary = run(path, backend="ray", max_retries=1, progress_interval=5.0)
    finally:
        ray.shutdown()
    assert summary["done"] == 4 and summary["converged"] == 2
    assert hashes(path) == hashes(reference) and len(hashes(path)) == 4
    assert hashes(path, "reduced-config.json") == hashes(reference, "reduced-config.json")
    for folder in (path / "models").iterdir():
        assert "=== zoo job" in (folder / "train.log").read_text()  # the task wrote its own log


def test_cli_refuses_bad_flags_with_one_line(tmp_path):
    result = cli("run", tmp_path / "nowhere")
    assert result.returncode == 2 and result.stderr.startswith("rlbackdoors: error: ") and "is not a zoo (no zoo.json)" in result.stderr
    result = cli("run", tmp_path, "--workers", "0")
    assert result.returncode == 2 and "rlbackdoors: error: zoo run: argument --workers: must be >= 1" in result.stderr
    result = cli("split", tmp_path, "--train", "0.5", "--test", "1.5", "--out-train", "a", "--out-test", "b")
    assert result.returncode == 2 and "--test: must be in (0, 1)" in result.stderr


def test_zoo_mounts_on_the_main_parser():
    from rlbackdoors.argparser import Parser
    from rlbackdoors.zoo.cli import add_zoo_parser, cmd_status

    parser = Parser(prog="rlbackdoors")
    add_zoo_parser(parser.add_subparsers(dest="command", required=True, parser_class=Parser))
    args = parser.parse_args(["zoo", "status", "runs/zoo"])
    assert args.func is cmd_status and args.zoo == "runs/zoo"
    args = parser.parse_args(["zoo", "run", "z", "--backend", "ray", "--address", "auto", "--workers", "8", "--max-retries", "0", "--retry-failed"])
    assert (args.backend, args.address, args.workers, args.max_retries, args.retry_failed) == ("ray", "auto", 8, 0, True)


def test_plan_refuses_a_foreign_folder_and_a_model_folder_it_did_not_draw(tmp_path):
    spec = parse_spec(tiny_spec())
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    with pytest.raises(ZooError, match="is not empty and holds no zoo.json"):
        plan(spec, tmp_path / "mine")
    assert [p.name for p in (tmp_path / "mine").iterdir()] == ["notes.txt"]
    zoo, written = plan(spec, tmp_path / "z")
    assert written == 3
    config = zoo.folder(zoo.model(spec.groups[1], 0)) / "config.json"
    data = json.loads(config.read_text())
    data["train"]["max_frames"] += 1
    config.write_text(json.dumps(data))
    with pytest.raises(ZooError, match="is not the config the zoo's spec draws for lavaworld/fc/multiplicative/clean attempt 0"):
        plan(spec, tmp_path / "z")
    assert json.loads(config.read_text()) == data  # left as it was


def test_planning_again_accepts_the_config_an_older_version_wrote_for_the_same_run(tmp_path):
    """A model folder planned by an older rlbackdoors holds an older config.json format; planning
    the same spec again compares the run it means (config.migrate), so the folder is not refused
    (and its model not thrown away); the file is left as written."""
    spec = parse_spec(tiny_spec())
    zoo, _ = plan(spec, tmp_path / "z")
    config = zoo.folder(zoo.model(spec.groups[0], 0)) / "config.json"
    data = json.loads(config.read_text())
    assert (
        data["format_version"] == 7
        and data["train"]["min_frames"] == 0
        and data["ppo"]["update_backend"] == "torch"
        and data["train"]["eval_backend"] == "torch"
    )
    del data["train"]["min_frames"], data["ppo"]["update_backend"], data["train"]["eval_backend"]  # format 4: none of them, which meant 0 and torch
    data["format_version"] = 4
    config.write_text(json.dumps(data))
    assert plan(spec, tmp_path / "z")[1] == 0
    assert json.loads(config.read_text()) == data
    data["train"]["min_frames"] = 5  # format 4 had no such field: not the run the spec draws
    config.write_text(json.dumps(data))
    with pytest.raises(ZooError, match="is not the config the zoo's spec draws"):
        plan(spec, tmp_path / "z")


def test_report_sets_each_cell_beside_the_papers_figure_for_the_same_arch_and_label():
    from rlbackdoors import worlds
    from rlbackdoors.zoo.report import paper_figure

    lava, rand, cm = (worlds.get(n) for n in ("lavaworld", "randomized-lavaworld", "colorful-memory"))
    assert paper_figure(lava, "cnn", "poisoned", "poisoned_reward") == 0.95 and paper_figure(lava, "fc", "clean", "clean_reward") == 0.90
    assert paper_figure(lava, "fc", "clean", "poisoned_sr") is None  # N/A in the paper's Table 1
    assert paper_figure(rand, "cnn", "clean", "poisoned_sr") == 0.25 and paper_figure(rand, "fc", "clean", "poisoned_reward") == 0.21
    assert paper_figure(cm, "cnn-gru-large", "clean", "poisoned_sr") == 0.05 and paper_figure(cm, "cnn-gru-trojai", "poisoned", "poisoned_reward") == 0.92
    safety = worlds.get("safety-car-goal")  # a zoo's arch label there is the algorithm; the paper's 3 x 256 row
    assert (
        paper_figure(safety, "opac2", "clean", "poisoned_sr") == 0.04 == paper_figure(safety, "mlp", "clean", "poisoned_sr")
        and paper_figure(safety, "opac2", "poisoned", "poisoned_reward") == 33.0
    )
    assert [w.paper.get("clean_convergence_rate") for w in (lava, rand, cm, safety)] == [0.922, 1.0, 0.5, 1.0]
