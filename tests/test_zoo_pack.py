"""``zoo pack``: a zoo small enough for git (issue 56's CPU route: zoos trained over several days on
machines that keep nothing) that is itself a zoo: it verifies, detectors read it, and ``zoo run`` on
a copy trains only what is missing, with the bytes the zoo would have had. Tiny LavaWorld FC models
(3,200 frames) trained in one group job."""

from __future__ import annotations

import copy
import hashlib
import json
import shutil
from pathlib import Path

import pytest

from rlbackdoors.detect.dataset import list_models
from rlbackdoors.io import FolderLock
from rlbackdoors.folder import WEIGHTS_LEFT_OUT
from rlbackdoors.zoo.pack import KEPT, pack
from rlbackdoors.zoo.plan import plan
from rlbackdoors.zoo.run import run
from rlbackdoors.zoo.spec import ZooError, parse_spec
from rlbackdoors.zoo.verify import verify
from cli_helpers import cli

TINY = {"ppo": {"rollout": 32}, "train": {"max_frames": 3200, "eval_interval": 1600, "eval_episodes": 4, "final_eval_episodes": 4}}
ALWAYS = {"train": {"clean_threshold": 0.0, "poisoned_threshold": 0.0}}


def spec(seed: int = 7) -> dict:
    return {
        "name": "pack",
        "seed": seed,
        "examples": {"episodes": 1},
        "overrides": copy.deepcopy(TINY),
        "cells": [{"world": "lavaworld", "archs": ["fc"], "triggers": ["multiplicative"], "clean": 2, "poisoned": 1, "overrides": ALWAYS}],
    }


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def zoo(tmp_path_factory) -> Path:
    """Three converged models with their logs, curve, GIF and example episodes, trained in one group job."""
    path = tmp_path_factory.mktemp("pack") / "zoo"
    plan(parse_spec(spec()), path)
    run(path, workers=1, group_size=3, progress_interval=60)
    return path


def test_a_pack_keeps_weights_configs_and_metrics_verifies_and_is_read_by_detectors(zoo, tmp_path):
    copied = tmp_path / "zoo"
    shutil.copytree(zoo, copied)
    names = sorted(p.name for p in (copied / "models").iterdir())
    pending = copied / "models" / names[-1]  # back to its planned files: a model still to train
    for entry in pending.iterdir():
        if entry.name not in ("config.json", "ground_truth.csv"):
            shutil.rmtree(entry) if entry.is_dir() else entry.unlink()
    out = tmp_path / "datasets" / "pack"
    packed = pack(copied, out)
    assert (packed.finished, packed.failed, packed.planned) == (2, 0, 1)
    assert packed.bytes == sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    for name in names[:-1]:
        kept = sorted(p.name for p in (out / "models" / name).iterdir())
        assert kept == sorted((*KEPT, "manifest.json"))  # no log.csv, curve, GIF, example episodes
        assert all(sha(out / "models" / name / f) == sha(zoo / "models" / name / f) for f in KEPT)
        assert (zoo / "models" / name / "log.csv").is_file() and (zoo / "models" / name / "clean_vs_triggered.gif").is_file()
    assert sorted(p.name for p in (out / "models" / names[-1]).iterdir()) == ["config.json", "ground_truth.csv"]
    result = verify(out)
    assert result.ok and result.models == 3
    assert len(list_models(out)) == 2  # a detector's dataset: the finished, converged models
    # zoo run on a copy of the pack trains only the missing model, with the bytes the zoo has for it
    again = tmp_path / "again"
    shutil.copytree(out, again)
    summary = run(again, workers=1, group_size=3, progress_interval=60)
    assert summary["trained"] == 1 and summary["done"] == 3
    assert {n: sha(again / "models" / n / "model.pt") for n in names} == {n: sha(zoo / "models" / n / "model.pt") for n in names}


def test_packing_again_replaces_the_pack_and_a_model_in_training_is_kept_as_planned(zoo, tmp_path):
    copied = tmp_path / "zoo"
    shutil.copytree(zoo, copied)
    out = tmp_path / "pack"
    assert cli("zoo", "pack", copied, "--out", out).returncode == 0
    name = sorted(p.name for p in (copied / "models").iterdir())[0]
    busy = copied / "models" / name
    for entry in ("metrics.json", "reduced-config.json", "model.pt"):
        (busy / entry).unlink()
    (busy / "checkpoint.pt").write_bytes(b"a run in progress")
    with FolderLock(busy, "model folder"):  # a live run holds it
        done = cli("zoo", "pack", copied, "--out", out)
    assert done.returncode == 0 and done.stdout.strip().endswith("MB") and "2 finished models" in done.stdout
    assert sorted(p.name for p in (out / "models" / name).iterdir()) == ["config.json", "ground_truth.csv"]  # restarts from scratch
    assert not list(out.parent.glob(".*rlbtmp")) and verify(out).ok


def test_what_a_pack_must_not_overwrite_or_copy_is_refused_in_one_line(zoo, tmp_path):
    other = tmp_path / "other"
    plan(parse_spec(spec(seed=8)), other)
    out = tmp_path / "pack"
    pack(zoo, out)
    before = {p: sha(p) for p in out.rglob("*") if p.is_file()}
    with pytest.raises(ZooError, match=r"zoo pack: --out '.*pack' exists and is not a pack of this zoo \(its zoo.json differs\)"):
        pack(other, out)
    (tmp_path / "file").write_text("x")
    with pytest.raises(ZooError, match=r"exists and is not a pack of this zoo"):
        pack(zoo, tmp_path / "file")
    with pytest.raises(ZooError, match=r"zoo pack: --out '.*' is inside the zoo"):
        pack(zoo, zoo / "packed")
    assert before == {p: sha(p) for p in out.rglob("*") if p.is_file()}  # untouched
    tampered = tmp_path / "tampered"
    shutil.copytree(zoo, tampered)
    first = sorted((tampered / "models").iterdir())[0]
    (first / "metrics.json").write_text("{}")
    refused = cli("zoo", "pack", tampered, "--out", tmp_path / "p2")
    assert refused.returncode == 2 and len(refused.stderr.strip().splitlines()) == 1
    assert refused.stderr.startswith("rlbackdoors: error: zoo ") and "failed verification" in refused.stderr and not (tmp_path / "p2").exists()


def test_converged_weights_only_leaves_out_the_weights_no_detector_reads(tmp_path):
    """A zoo whose one poisoned attempt cannot converge (thresholds of 1.0 at 3,200 frames; one
    attempt allowed): the pack keeps the converged model whole and, for the other, its metrics and a
    note of the left-out weights' sha256 and size. The pack verifies, detectors read the converged
    model only, ``zoo run`` on a copy trains nothing again (the attempt counts), and loading the
    weightless model is refused in one line."""
    never = {"train": {"clean_threshold": 1.0, "poisoned_threshold": 1.0}}
    data = {**spec(seed=11), "max_attempts": 1}
    data["cells"] = [
        {"world": "lavaworld", "archs": ["fc"], "triggers": ["multiplicative"], "clean": 1, "poisoned": 0, "overrides": ALWAYS},
        {"world": "lavaworld", "archs": ["fc"], "triggers": ["additive"], "clean": 0, "poisoned": 1, "overrides": never},
    ]
    zoo = tmp_path / "zoo"
    plan(parse_spec(data), zoo)
    run(zoo, workers=1, group_size=2, progress_interval=60)
    states = {p.name: json.loads((p / "metrics.json").read_text())["converged"] for p in sorted((zoo / "models").iterdir())}
    assert sorted(states.values()) == [False, True]
    out = tmp_path / "pack"
    done = cli("zoo", "pack", zoo, "--out", out, "--converged-weights-only", "--json")
    packed = json.loads(done.stdout)
    assert done.returncode == 0 and (packed["finished"], packed["weights_left_out"]) == (2, 1)
    for name, converged in states.items():
        folder = out / "models" / name
        assert (folder / "model.pt").is_file() == converged and (folder / "metrics.json").is_file()
        if not converged:
            note = json.loads((folder / WEIGHTS_LEFT_OUT).read_text())
            assert (note["sha256"], note["bytes"]) == (sha(zoo / "models" / name / "model.pt"), (zoo / "models" / name / "model.pt").stat().st_size)
            refused = cli("evaluate", folder, "--episodes", "2")
            assert refused.returncode == 2 and "holds no weights" in refused.stderr and len(refused.stderr.strip().splitlines()) == 1
    assert verify(out).ok and [m.name for m in list_models(out)] == [n for n, c in states.items() if c]
    again = tmp_path / "again"
    shutil.copytree(out, again)
    assert run(again, workers=1, group_size=2, progress_interval=60)["trained"] == 0


def test_the_zoos_packed_in_git_verify_with_the_digests_their_readme_publishes():
    """Every pack under datasets/ passes ``zoo verify`` (weights, configs and metrics as packed), and
    its digest starts with the one datasets/README.md publishes for it."""
    import re

    root = Path(__file__).resolve().parents[1] / "datasets"
    readme = (root / "README.md").read_text()
    packs = sorted(p.parent for p in root.glob("*/zoo.json"))
    assert packs, "no pack under datasets/"
    for folder in packs:
        published = re.search(rf"\| `{re.escape(folder.name)}/` \|.*?digest sha256:([0-9a-f]+)", readme)
        assert published, f"datasets/README.md publishes no digest for {folder.name}"
        result = verify(folder)
        assert result.ok, result.lines()
        assert result.digest.startswith(published.group(1)), (folder.name, result.digest)
