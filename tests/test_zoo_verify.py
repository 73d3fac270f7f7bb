"""Zoo verification (issue 32): manifests, plan and label consistency, METADATA.csv; every
tampered model named by ``zoo verify`` and refused by status, report, split, run and the
detectors; ``--skip-unverified`` names what it left out; an old zoo is adopted by
``--write-manifest``; ``--retrain-tampered`` gives back the same model bytes.

Real zoos: four tiny LavaWorld models trained once per module, copied for each tampering.
"""

from __future__ import annotations

import copy
import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from rlbackdoors.detect.dataset import list_models
from rlbackdoors.detect.handle import DetectError
from rlbackdoors.zoo.plan import plan
from rlbackdoors.zoo.run import run
from rlbackdoors.zoo.spec import ZooError, parse_spec
from rlbackdoors.zoo.verify import verify
from cli_helpers import cli

CLI = [sys.executable, "-m", "rlbackdoors.cli"]
TINY = {"ppo": {"rollout": 32}, "train": {"max_frames": 3200, "eval_interval": 1600, "eval_episodes": 5, "final_eval_episodes": 5, "video": False}}
ALWAYS = {"train": {"clean_threshold": 0.0, "poisoned_threshold": 0.0}}
NEVER = {"train": {"clean_threshold": 1.0, "poisoned_threshold": 1.0}}


def spec(overrides: dict, clean: int = 1, poisoned: int = 1, triggers=("multiplicative", "additive")) -> dict:
    return {
        "name": "verify",
        "seed": 5,
        "examples": {"episodes": 1},
        "overrides": copy.deepcopy(TINY),
        "cells": [{"world": "lavaworld", "archs": ["fc"], "triggers": list(triggers), "clean": clean, "poisoned": poisoned, "overrides": overrides}],
    }


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    """4 converged models: 2 cells (multiplicative, additive) x clean / poisoned, trained in one
    group job (one process: what is verified here does not depend on the trainer)."""
    path = tmp_path_factory.mktemp("verify") / "zoo"
    plan(parse_spec(spec(ALWAYS)), path)
    run(path, workers=1, group_size=4, progress_interval=60)
    return path


@pytest.fixture
def zoo(built, tmp_path) -> Path:
    copied = tmp_path / "zoo"
    shutil.copytree(built, copied, symlinks=True)
    return copied


def cli_process(*args) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *map(str, args)], capture_output=True, text=True, timeout=600)


def error_line(proc: subprocess.CompletedProcess) -> str:
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("rlbackdoors: error: "), (proc.returncode, proc.stderr)
    return lines[0]


def models(zoo: Path) -> list[Path]:
    return sorted((zoo / "models").iterdir())


def label_of(folder: Path) -> str:
    return (folder / "ground_truth.csv").read_text().strip()


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# --- an untouched zoo ----------------------------------------------------------------------------
def test_an_untouched_zoo_verifies_clean_with_a_stable_digest(zoo):
    first = verify(zoo)
    assert first.ok and first.models == 4 and len(first.digest) == 64
    for folder in models(zoo):
        listed = json.loads((folder / "manifest.json").read_text())["files"]
        assert {"model.pt", "config.json", "ground_truth.csv", "metrics.json", "reduced-config.json", "clean-example-data/episode-000.npz"} <= set(listed)
        assert listed["model.pt"]["sha256"] == sha(folder / "model.pt")
    proc = cli_process("zoo", "verify", zoo)  # through a real process once
    assert proc.returncode == 0 and f"digest sha256:{first.digest}" in proc.stdout
    assert cli("zoo", "verify", zoo, "--expect", f"sha256:{first.digest}").returncode == 0
    assert cli("zoo", "status", zoo).returncode == 0
    assert len(list_models(zoo)) == 4


def test_a_wrong_expected_digest_fails(zoo):
    bad = "sha256:" + "0" * 64
    proc = cli("zoo", "verify", zoo, "--expect", bad)
    assert proc.returncode == 2 and f"not the expected {bad}" in proc.stdout


# --- tampering: named by verify, refused downstream ----------------------------------------------
def _swap_configs(zoo: Path) -> list[str]:
    a, b = models(zoo)[0], next(m for m in models(zoo)[1:] if label_of(m) != label_of(models(zoo)[0]))
    ta, tb = (a / "config.json").read_bytes(), (b / "config.json").read_bytes()
    (a / "config.json").write_bytes(tb)
    (b / "config.json").write_bytes(ta)
    return [a.name, b.name]


def _one(change):
    def tamper(zoo: Path) -> list[str]:
        folder = models(zoo)[1]
        change(folder)
        return [folder.name]

    return tamper


TAMPERINGS = {
    "model.pt deleted": (_one(lambda f: (f / "model.pt").unlink()), "model.pt is missing"),
    "model.pt truncated": (_one(lambda f: (f / "model.pt").write_bytes((f / "model.pt").read_bytes()[:1000])), "model.pt has 1,000 bytes"),
    "model.pt edited": (
        _one(lambda f: (f / "model.pt").write_bytes(bytes(b ^ (i == 5000) for i, b in enumerate((f / "model.pt").read_bytes())))),
        "model.pt differs",
    ),
    "metrics edited": (
        _one(lambda f: (f / "metrics.json").write_text((f / "metrics.json").read_text().replace('"converged": true', '"converged": false'))),
        "metrics.json",
    ),
    "label flipped": (_one(lambda f: (f / "ground_truth.csv").write_text(str(1 - int(label_of(f))) + "\n")), "ground_truth.csv says"),
    "extra file": (_one(lambda f: (f / "notes.txt").write_text("hi")), "notes.txt is not in the manifest"),
    "example deleted": (_one(lambda f: (f / "clean-example-data" / "episode-000.npz").unlink()), "clean-example-data/episode-000.npz is missing"),
    "manifest deleted": (_one(lambda f: (f / "manifest.json").unlink()), "no manifest.json"),
    "manifest garbled": (_one(lambda f: (f / "manifest.json").write_bytes(b"\xff\xfe")), "manifest.json is unreadable"),
    "configs swapped": (_swap_configs, "config.json is not the one the spec draws for it"),
}


@pytest.mark.parametrize("name", list(TAMPERINGS))
def test_every_tampered_model_is_named_and_refused_downstream(zoo, name, tmp_path):
    tamper, phrase = TAMPERINGS[name]
    names = tamper(zoo)
    result = verify(zoo)
    bad = result.model_problems()
    assert set(bad) == set(names) and all(phrase in bad[n] for n in names), bad
    proc = cli("zoo", "verify", zoo)
    assert proc.returncode == 2 and all(f"{n}: " in proc.stdout for n in names) and phrase in proc.stdout
    for command in (["status"], ["report"], ["split", "--train", "0.5", "--test", "0.5", "--out-train", tmp_path / "a", "--out-test", tmp_path / "b"]):
        line = error_line(cli("zoo", command[0], zoo, *command[1:]))
        assert "failed verification" in line and names[0] in line and "--skip-unverified" in line
    assert not (zoo / "report").exists() and not (tmp_path / "a").exists()
    with pytest.raises(DetectError, match="failed verification"):
        list_models(zoo)
    skipped = list_models(zoo, skip_unverified=True).skipped
    assert set(skipped) == set(names)
    assert "failed verification" in error_line(cli("zoo", "run", zoo))


def test_skip_unverified_names_the_models_it_left_out(zoo, tmp_path):
    (models(zoo)[0] / "model.pt").unlink()
    gone = models(zoo)[0].name
    status = cli("zoo", "status", zoo, "--skip-unverified")
    assert status.returncode == 0 and f"skipped {gone} (failed verification: model.pt is missing)" in status.stdout
    report = cli("zoo", "report", zoo, "--skip-unverified")
    assert report.returncode == 0 and f"skipped {gone}" in report.stderr
    text = (zoo / "report" / "report.md").read_text()
    assert "Skipped: 1 models failed verification" in text and f"{gone}: unverified: model.pt is missing" in text
    rows = {r.split(",")[0]: r for r in (zoo / "METADATA.csv").read_text().splitlines()[1:]}
    assert ",unverified," in rows[gone]  # status unverified: outside every dataset


def test_split_takes_only_verified_entries_and_no_trace_of_the_building_machine(zoo, tmp_path):
    (models(zoo)[0] / "model.pt").unlink()
    gone = models(zoo)[0].name
    proc = cli("zoo", "split", zoo, "--train", "0.5", "--test", "0.5", "--out-train", tmp_path / "tr", "--out-test", tmp_path / "te", "--skip-unverified")
    assert proc.returncode == 0, proc.stderr
    placed = []
    for out in (tmp_path / "tr", tmp_path / "te"):
        info = json.loads((out / "split.json").read_text())
        assert info["zoo"] == "zoo" and info["skipped"] == {gone: "model.pt is missing"}
        for folder in (out / "models").iterdir():
            placed.append(folder.name)
            assert not (folder / "train.log").exists() and not (folder / ".lock").exists()
            assert verify_entry(folder) == []
        text = "".join(p.read_text(errors="replace") for p in out.rglob("*") if p.is_file() and p.suffix in (".json", ".csv"))
        assert str(tmp_path) not in text and str(Path.home()) not in text
        assert len(list_models(out)) == len(list((out / "models").iterdir()))  # a split verifies for the detectors
    assert gone not in placed and len(placed) == 3


def verify_entry(folder: Path) -> list[str]:
    from rlbackdoors.folder import manifest_problems

    return manifest_problems(folder)


def test_run_refuses_a_tampered_zoo_and_retrain_tampered_gives_the_same_bytes(zoo):
    before = {f.name: sha(f / "model.pt") for f in models(zoo)}
    (models(zoo)[2] / "model.pt").unlink()
    swapped = _swap_configs(zoo)
    line = error_line(cli("zoo", "run", zoo, "--workers", "2"))
    assert "--retrain-tampered" in line
    # retrained in a group of their own: on a CPU an agent's bytes do not depend on its group-mates
    proc = cli("zoo", "run", zoo, "--workers", "1", "--group-size", "4", "--retrain-tampered")
    assert proc.returncode == 0, proc.stderr
    assert "emptied, it trains again" in proc.stderr and all(n in proc.stderr for n in swapped)
    assert {f.name: sha(f / "model.pt") for f in models(zoo)} == before
    assert verify(zoo).ok


def test_an_old_zoo_without_manifests_is_adopted_after_its_checks(zoo):
    for folder in models(zoo):
        (folder / "manifest.json").unlink()
    (models(zoo)[3] / "reduced-config.json").write_text('{"layers": {}}\n')  # no longer describes model.pt
    line = error_line(cli("zoo", "status", zoo))
    assert "no manifest.json" in line
    proc = cli("zoo", "verify", zoo, "--write-manifest")
    assert proc.returncode == 2
    assert proc.stdout.count("adopted") == 3 and f"{models(zoo)[3].name}: reduced-config.json does not describe model.pt's tensors" in proc.stdout
    assert not (models(zoo)[3] / "manifest.json").exists()
    assert set(verify(zoo).model_problems()) == {models(zoo)[3].name}  # the other three verify now
    assert cli("zoo", "status", zoo, "--skip-unverified").returncode == 0


def test_metadata_that_is_garbled_or_disagrees_is_named(zoo):
    meta = zoo / "METADATA.csv"
    original = meta.read_bytes()
    meta.write_bytes(b"\xff\xfe garbage")
    result = verify(zoo)
    assert not result.ok and any("METADATA.csv is not UTF-8" in p for p in result.problems[""])
    with pytest.raises(DetectError, match="METADATA.csv"):
        list_models(zoo)
    lines = original.decode().splitlines()
    gone = lines.pop(1).split(",")[0]
    meta.write_text("\n".join(lines) + "\n")
    assert any(f"no row for the finished model {gone}" in p for p in verify(zoo).problems[""])
    meta.write_text(original.decode().replace(",False,", ",True,", 1))
    assert any("METADATA.csv says poisoned=True" in why for why in verify(zoo).model_problems().values())


def test_a_deleted_model_folder_is_named(zoo):
    gone = models(zoo)[0]
    shutil.rmtree(gone)
    result = verify(zoo)
    assert any(f"METADATA.csv lists {gone.name}, which has no model folder" in p for p in result.problems[""])


def test_detectors_name_the_real_cause_when_no_model_converged(tmp_path):
    path = tmp_path / "never"
    plan(parse_spec(spec(NEVER, clean=1, poisoned=0, triggers=("multiplicative",)) | {"max_attempts": 1}), path)
    run(path, workers=1, progress_interval=60)
    assert (next((path / "models").iterdir()) / "model.pt").is_file()
    with pytest.raises(DetectError, match="no finished, converged model .1 are not converged"):
        list_models(path)


def test_verify_refuses_what_is_not_a_zoo(tmp_path):
    with pytest.raises(ZooError, match="is not a zoo"):
        verify(tmp_path)
