"""No link in a zoo is ever followed (issue 32): a link at any level (models/, a model folder,
a file, clean-example-data/, replay/, report/, METADATA.csv) is named by ``zoo verify`` and
refused by every command, and nothing outside the zoo is written or deleted, also when the link
is swapped in while ``zoo run`` trains.
"""

from __future__ import annotations

import copy
import hashlib
import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest

from rlbackdoors.detect.dataset import list_models
from rlbackdoors.detect.handle import DetectError
from rlbackdoors.io import LinkError, atomic_write_text
from rlbackdoors.zoo.job import is_locked
from rlbackdoors.zoo.plan import plan
from rlbackdoors.zoo.run import run
from rlbackdoors.zoo.spec import parse_spec
from rlbackdoors.zoo.verify import verify
from cli_helpers import cli
from test_zoo_verify import ALWAYS, CLI, error_line, spec


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    """Two converged models (clean and poisoned, multiplicative triggers)."""
    path = tmp_path_factory.mktemp("links") / "zoo"
    plan(parse_spec(spec(ALWAYS, triggers=("multiplicative",))), path)
    run(path, workers=2, progress_interval=60)
    return path


@pytest.fixture
def zoo(built, tmp_path) -> Path:
    return Path(shutil.copytree(built, tmp_path / "zoo", symlinks=True))


@pytest.fixture
def outside(tmp_path) -> Path:
    """A folder outside the zoo holding someone else's files."""
    out = tmp_path / "outside"
    out.mkdir()
    (out / "keep.txt").write_text("someone else's file")
    return out


def tree(path: Path) -> dict[str, str]:
    return {p.relative_to(path).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(path.rglob("*")) if p.is_file() and not p.is_symlink()}


def first_model(zoo: Path) -> Path:
    return sorted((zoo / "models").iterdir())[0]


def _replace_with_link(path: Path, target: Path) -> None:
    shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
    path.symlink_to(target, target_is_directory=target.is_dir())


def _fill(outside: Path, like: Path) -> Path:
    """``outside`` made to look like ``like`` (a copy), so following a link would find files."""
    copy_ = outside / like.name
    shutil.copytree(like, copy_, symlinks=True) if like.is_dir() else shutil.copy(like, copy_)
    return copy_


# (what is replaced by a link, where the link points, what verify names)
PLACES = {
    "models/": (lambda z: z / "models", lambda z, o: _fill(o, z / "models"), "models is a symbolic link"),
    "a model folder, to outside": (lambda z: first_model(z), lambda z, o: _fill(o, first_model(z)), "the model folder is a symbolic link"),
    "a model folder, to another model": (lambda z: first_model(z), lambda z, o: sorted((z / "models").iterdir())[1], "the model folder is a symbolic link"),
    "model.pt": (lambda z: first_model(z) / "model.pt", lambda z, o: _fill(o, first_model(z) / "model.pt"), "model.pt is a symbolic link"),
    "clean-example-data/": (
        lambda z: first_model(z) / "clean-example-data",
        lambda z, o: _fill(o, first_model(z) / "clean-example-data"),
        "clean-example-data is a symbolic link",
    ),
    "replay/": (lambda z: first_model(z) / "replay", lambda z, o: o, "replay is a symbolic link"),
    "report/": (lambda z: z / "report", lambda z, o: o, "report is a symbolic link"),
    "METADATA.csv": (lambda z: z / "METADATA.csv", lambda z, o: _fill(o, z / "METADATA.csv"), "METADATA.csv is a symbolic link"),
}


@pytest.mark.parametrize("place", list(PLACES))
def test_a_link_at_any_level_is_named_and_refused_and_nothing_outside_changes(zoo, outside, place, tmp_path):
    where, target, phrase = PLACES[place]
    path, to = where(zoo), target(zoo, outside)
    if path.exists() or path.is_symlink():
        _replace_with_link(path, to)
    else:
        path.symlink_to(to, target_is_directory=True)
    before = tree(outside)
    result = verify(zoo)
    assert result.links and any(phrase in p for found in result.problems.values() for p in found), result.problems
    line = error_line(cli("zoo", "verify", zoo))
    assert "symbolic link" in line
    for args in (
        ["status", zoo, "--skip-unverified"],
        ["report", zoo, "--skip-unverified"],
        ["split", zoo, "--train", "0.5", "--test", "0.5", "--out-train", tmp_path / "a", "--out-test", tmp_path / "b", "--skip-unverified"],
        ["run", zoo, "--retrain-tampered", "--workers", "1"],
        ["detect", "fit", "--detector", "constant", "--zoo", zoo, "--out", tmp_path / "det"],
    ):
        assert "symbolic link" in error_line(cli(args[0] if args[0] == "detect" else "zoo", *(args[1:] if args[0] == "detect" else args)))
    with pytest.raises(DetectError, match="symbolic link"):
        list_models(zoo)
    assert tree(outside) == before and (outside / "keep.txt").read_text() == "someone else's file"
    assert not (tmp_path / "a").exists() and not (tmp_path / "det").exists()


def test_a_planned_folder_replaced_by_a_link_is_never_trained_into(tmp_path, outside):
    zoo = tmp_path / "zoo"
    plan(parse_spec(spec(ALWAYS, triggers=("multiplicative",))), zoo)
    victim = first_model(zoo)
    _replace_with_link(victim, outside)
    line = error_line(cli("zoo", "run", zoo, "--workers", "1"))
    assert victim.name in line and "symbolic link" in line
    assert sorted(p.name for p in outside.iterdir()) == ["keep.txt"]


def test_a_link_swapped_in_while_zoo_run_trains_is_never_followed(tmp_path, outside):
    """One worker, two models training 3 evaluations each: while the first trains, its folder is
    moved aside and replaced by a link to ``outside``, and so is the second (not started) one.
    The running job keeps writing into its own folder (opened once, link by link); the run
    stops with one line naming the link; nothing lands outside."""
    zoo = tmp_path / "zoo"
    slow = copy.deepcopy(ALWAYS)
    slow["train"].update(max_frames=40_000, eval_interval=8000, checkpoint_minutes=0)
    plan(parse_spec(spec(slow, triggers=("multiplicative",))), zoo)
    folders = sorted((zoo / "models").iterdir())
    proc = subprocess.Popen([*CLI, "zoo", "run", str(zoo), "--workers", "1"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 300
        while not any(is_locked(f) for f in folders):
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read() if proc.poll() is not None else "no job started"
            time.sleep(0.2)
        running = next(f for f in folders if is_locked(f))
        waiting = next(f for f in folders if f != running)
        moved = zoo / "models" / f".{running.name}.moved"
        os.rename(running, moved)
        running.symlink_to(outside, target_is_directory=True)
        shutil.rmtree(waiting)
        waiting.symlink_to(outside, target_is_directory=True)
        _, err = proc.communicate(timeout=600)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 2 and "symbolic link" in err.strip().splitlines()[-1]
    assert sorted(p.name for p in outside.iterdir()) == ["keep.txt"]
    assert (moved / "config.json").is_file()  # the job wrote into its own folder, wherever it went


def test_temp_files_are_never_written_through_a_planted_link(tmp_path, outside):
    target = tmp_path / "folder" / "data.json"
    target.parent.mkdir()
    planted = target.with_name(f".{target.name}.{os.getpid()}.rlbtmp")
    planted.symlink_to(outside / "keep.txt")
    atomic_write_text(target, "mine\n")
    assert target.read_text() == "mine\n" and (outside / "keep.txt").read_text() == "someone else's file"
    assert not planted.exists() and not planted.is_symlink()


def test_open_beneath_refuses_a_link_at_every_step(tmp_path, outside):
    from rlbackdoors.io import open_beneath

    root = tmp_path / "z"
    (root / "models" / "id-1").mkdir(parents=True)
    os.close(open_beneath(root, root / "models" / "id-1"))
    shutil.rmtree(root / "models")
    (root / "models").symlink_to(outside, target_is_directory=True)
    (outside / "id-1").mkdir()
    with pytest.raises(LinkError, match="models"):
        open_beneath(root, root / "models" / "id-1")
