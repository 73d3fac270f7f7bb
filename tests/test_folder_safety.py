"""Zoo-grade safety of model folders: loading never runs code, one trainer per folder, same
weights give the same bytes, kills leave no temp files, checkpoints are plain data."""

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from rlbackdoors.config import RunConfig
from rlbackdoors.io import FolderLock, LockedError, UnsafeFileError, atomic_write_text, load_torch, remove_stale_temp_files
from rlbackdoors.train import train
from rlbackdoors.train.folder import FolderError, ModelFolder
from cli_helpers import cli as run_cli

PY = [sys.executable, "-m", "rlbackdoors.cli"]


class Payload:
    """Pickles to a call that creates ``marker``: if a loader ever unpickles it, the file appears."""

    def __init__(self, marker: Path, then=None):
        self.marker, self.then = str(marker), then

    def __reduce__(self):
        return (_touch_and_return, (self.marker, self.then))


def _touch_and_return(marker, then):
    Path(marker).write_text("payload ran")
    return then


def tiny_cfg(tiny_run_dict, **train_fields) -> RunConfig:
    tiny_run_dict["train"].update(train_fields)
    return RunConfig.from_dict(tiny_run_dict)


@pytest.fixture
def finished(tmp_path, tiny_run_dict) -> Path:
    out = tmp_path / "model"
    train(tiny_cfg(tiny_run_dict), out, progress=False)
    return out


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def cli(*argv, cwd=None):
    """The CLI in this process (cli_helpers); the kills below use real processes."""
    return run_cli(*argv, cwd=cwd)


def one_error_line(proc) -> str:
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and len(lines) == 1 and lines[0].startswith("rlbackdoors: error:"), proc.stderr
    return lines[0]


# ----- loading never runs code -----------------------------------------------------------------
def test_payload_in_model_pt_is_refused_by_evaluate_folder_and_weights(tmp_path, finished):
    """A model.pt whose pickle would also return real weights: before, it ran and exited 0."""
    marker = tmp_path / "ran"
    weights = torch.load(finished / "model.pt", weights_only=True)
    torch.save(Payload(marker, weights), finished / "model.pt")
    for argv in (["evaluate", finished, "--episodes", "2"], ["evaluate", "--weights", finished / "model.pt", "--arch", "fc", "--episodes", "2"]):
        line = one_error_line(cli(*argv))
        assert "refused to load weights file" in line and "holds Python objects" in line
    assert not marker.exists()


def test_payload_in_checkpoint_is_refused_on_resume(tmp_path, tiny_run_dict):
    cfg = tiny_cfg(tiny_run_dict)
    out = tmp_path / "run"
    folder = ModelFolder(out)
    folder.path.mkdir()
    folder.write_config(cfg)
    marker = tmp_path / "ran"
    torch.save({"format": 2, "model": Payload(marker, {})}, out / "checkpoint.pt")
    with pytest.raises(FolderError, match="holds Python objects"):
        train(cfg, out, progress=False)
    assert not marker.exists()
    cfg_path = tmp_path / "cfg.json"
    cfg_path.write_text(cfg.to_json())
    assert "holds Python objects" in one_error_line(cli("train", "--config", cfg_path, "--out", out, "--quiet"))
    assert not marker.exists() and (out / "checkpoint.pt").is_file()  # refused, not deleted: --overwrite is the user's call


def test_payload_in_safety_model_and_checkpoint_is_refused(tmp_path):
    from rlbackdoors import load as load_agent
    from rlbackdoors.train import train as train_safety
    from test_safety_train import tiny

    out = tmp_path / "safety"
    train_safety(tiny(max_frames=240), out, progress=False)
    marker = tmp_path / "ran"
    weights = torch.load(out / "model.pt", weights_only=True)
    torch.save(Payload(marker, weights), out / "model.pt")
    with pytest.raises(FolderError, match="holds Python objects"):
        load_agent(out)
    assert "holds Python objects" in one_error_line(cli("evaluate", out))
    # A checkpoint of an interrupted run that carries a payload: refused on resume.
    (out / "metrics.json").unlink()
    torch.save({"format": 2, "agent": Payload(marker, {})}, out / "checkpoint.pt")
    with pytest.raises(FolderError, match="holds Python objects"):
        train_safety(tiny(max_frames=240), out, progress=False)
    assert not marker.exists()


def test_replay_chunk_with_a_pickled_object_is_refused(tmp_path):
    """Replay chunks are .npz files read with allow_pickle=False: an object array cannot load."""
    from rlbackdoors.algos.opac2 import MultitaskReplay
    from rlbackdoors.train.replay_journal import ReplayJournal

    marker = tmp_path / "ran"
    (tmp_path / "replay").mkdir()
    name = "clean-000000000000-000000000002.npz"
    arrays = {k: np.zeros((2, 3), np.float32) for k in ("obs", "act")}
    np.savez(
        tmp_path / "replay" / name,
        **arrays,
        rew=np.array([Payload(marker), 1], dtype=object),
        done=np.zeros(2, np.float32),
        next_obs_same=np.zeros(2, bool),
        next_obs_rest=np.zeros((2, 3), np.float32),
    )
    replay = MultitaskReplay.create({"clean": 1.0}, 10, 3, 3)
    manifest = {"format": 1, "added": {"clean": 2}, "chunks": {"clean": [name]}}
    with pytest.raises(ValueError, match="unreadable"):
        ReplayJournal(tmp_path / "replay", {"clean": 1}).load(replay, manifest)
    assert not marker.exists()


@pytest.mark.parametrize(
    "content, message",
    [
        (b"", "cannot read"),
        (b"random bytes, not a zip", "cannot read"),
        ("truncated", "cannot read"),
        ({"frames": 3}, "not a checkpoint of this version"),  # no format: an old or foreign file
        ([1, 2, 3], "not a checkpoint of this version"),
        ({"format": 2, "model": {"x": torch.zeros(1)}}, "does not fit this run"),
    ],
)
def test_checkpoint_that_holds_the_wrong_thing_gives_one_line(tmp_path, tiny_run_dict, finished, content, message):
    cfg = tiny_cfg(tiny_run_dict)
    out = tmp_path / "broken"
    shutil.copytree(finished, out)
    (out / "metrics.json").unlink()
    path = out / "checkpoint.pt"
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content == "truncated":
        path.write_bytes((finished / "model.pt").read_bytes()[:200])
    else:
        torch.save(content, path)
    with pytest.raises(FolderError, match=message):
        train(cfg, out, progress=False)
    assert path.is_file()  # never deleted without --overwrite
    train(cfg, out, overwrite=True, progress=False)  # --overwrite starts over
    assert (out / "metrics.json").is_file() and not path.exists()


def test_load_torch_refuses_a_payload_named_anything(tmp_path):
    marker = tmp_path / "ran"
    torch.save({"w": torch.ones(2), "extra": Payload(marker)}, tmp_path / "x.bin")
    with pytest.raises(UnsafeFileError):
        load_torch(tmp_path / "x.bin")
    assert not marker.exists()


# ----- one trainer per folder ------------------------------------------------------------------
def test_two_trainings_on_one_folder_the_second_is_refused_and_nothing_is_lost(tmp_path, tiny_run_dict):
    """Started half a second apart, the second command is refused naming the first's pid; the
    first finishes its model, which is the one in the folder."""
    cfg = tiny_cfg(tiny_run_dict, max_frames=20_480, eval_interval=5_120)
    cfg_path = tmp_path / "cfg.json"
    cfg_path.write_text(cfg.to_json())
    out = tmp_path / "shared"
    first = subprocess.Popen([*PY, "train", "--config", str(cfg_path), "--out", str(out), "--quiet"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 60
    while not (out / "config.json").exists() and time.time() < deadline:
        time.sleep(0.05)
    time.sleep(0.5)
    second = cli("train", "--config", cfg_path, "--seed", 7, "--out", out, "--quiet", "--overwrite")
    line = one_error_line(second)
    assert "is in use by process" in line and str(first.pid) in line
    stdout, stderr = first.communicate(timeout=300)
    assert first.returncode == 0, stderr
    assert RunConfig.load(out / "config.json").train.seed == cfg.train.seed  # the first run's model, whole
    assert json.loads((out / "metrics.json").read_text())["frames"] == 20_480


def test_a_killed_holders_lock_is_taken_over(tmp_path):
    """flock dies with its holder: after kill -9 the folder is free at once, no stale lock."""
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from rlbackdoors.io import FolderLock; FolderLock(sys.argv[1]).acquire(); print('held', flush=True); time.sleep(60)",
            str(tmp_path),
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    assert holder.stdout.readline().strip() == "held"
    with pytest.raises(LockedError, match=f"process {holder.pid} on"):
        FolderLock(tmp_path).acquire()
    holder.kill()
    holder.wait()
    with FolderLock(tmp_path) as lock:
        assert lock.held and json.loads((tmp_path / ".lock").read_text())["pid"] == os.getpid()


# ----- same weights, same bytes ----------------------------------------------------------------
def test_same_config_same_model_bytes(tmp_path, tiny_run_dict):
    cfg = tiny_cfg(tiny_run_dict)
    train(cfg, tmp_path / "a", progress=False)
    train(cfg, tmp_path / "b", progress=False)
    assert sha256(tmp_path / "a" / "model.pt") == sha256(tmp_path / "b" / "model.pt")
    for name in ("config.json", "ground_truth.csv"):
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()


# ----- temp files ------------------------------------------------------------------------------
def test_temp_files_of_a_killed_writer_are_removed_at_the_next_start(tmp_path, tiny_run_dict):
    cfg = tiny_cfg(tiny_run_dict)
    out = tmp_path / "m"
    out.mkdir()
    # What a writer killed mid-write leaves: a recognisable temp file per target.
    for name in (".config.json.4242.rlbtmp", ".checkpoint.pt.4242.rlbtmp", ".model.pt.99.rlbtmp"):
        (out / name).write_bytes(b"half a file")
    (out / "notes.txt").write_text("mine")  # the user's own files are left alone
    train(cfg, out, progress=False)
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == [".lock"]
    assert (out / "notes.txt").read_text() == "mine"
    (out / ".metrics.json.1.rlbtmp").write_bytes(b"x")
    train(cfg, out, overwrite=True, progress=False)
    assert not list(out.glob("*.rlbtmp")) and not list(out.glob(".*.rlbtmp"))


def test_atomic_write_leaves_no_temp_file_when_the_write_fails(tmp_path):
    target = tmp_path / "f.json"
    atomic_write_text(target, "old")

    def boom(tmp):
        Path(tmp).write_text("half")
        raise OSError("disk full")

    from rlbackdoors.io import atomic_write

    with pytest.raises(OSError):
        atomic_write(target, boom)
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["f.json"]
    (tmp_path / ".x.1.rlbtmp").write_text("")
    assert [p.name for p in remove_stale_temp_files(tmp_path)] == [".x.1.rlbtmp"]


# ----- failures leave no partial folder --------------------------------------------------------
@pytest.mark.parametrize(
    "argv, message",
    [
        (["--seed", "-5"], "train.seed"),
        (["--seed", str(2**70)], "train.seed"),
        (["--max-frame", "100"], "unrecognized arguments: --max-frame"),
        (["--env", "safety-car-goal", "--poisoned-weight", "1.5"], "opac2.poisoned_weight (--poisoned-weight) must be in [0, 1]"),
        (["--env", "safety-car-goal", "--seed", "-5"], "train.seed"),
        (["--env", "safety-car-goal", "--checkpoint-minutes", "-1"], "train.checkpoint_minutes"),
        (["--env", "lavaworld", "--action-samples", "3"], "--action-samples does not apply here: lavaworld trains with ppo, not opac2"),
    ],
)
def test_bad_flags_name_their_field_and_leave_no_folder(tmp_path, argv, message):
    out = tmp_path / "never"
    line = one_error_line(cli("train", "--out", out, "--quiet", *argv))
    assert message in line
    assert not out.exists()


def test_out_paths_that_cannot_be_written(tmp_path):
    (tmp_path / "file").write_text("x")
    assert "exists and is not a folder" in one_error_line(cli("train", "--out", tmp_path / "file", "--quiet"))
    assert "cannot write the model folder" in one_error_line(cli("train", "--out", tmp_path / "file" / "sub", "--quiet"))
    assert "cannot write the model folder" in one_error_line(cli("train", "--out", "/proc/rlbackdoors-model", "--quiet"))
    assert "--out must name a model folder" in one_error_line(cli("train", "--out", "", "--quiet", cwd=tmp_path))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]  # nothing written into the working directory


def test_evaluate_of_an_unfinished_folder_needs_allow_unfinished(tmp_path, finished):
    (finished / "metrics.json").unlink()
    assert "--allow-unfinished" in one_error_line(cli("evaluate", finished, "--episodes", "2"))
    proc = cli("evaluate", finished, "--episodes", "2", "--json", "--allow-unfinished")
    assert proc.returncode == 0 and json.loads(proc.stdout)["episodes"] == 2


# ----- Safety Car Goal faults -------------------------------------------------------------------
def safety_config(tmp_path, **train_fields) -> Path:
    from test_safety_train import tiny

    path = tmp_path / "safety.json"
    path.write_text(tiny(**train_fields).to_json())
    return path


def test_safety_short_eval_interval_below_warmup_trains_and_logs_every_column(tmp_path):
    """Evaluations before learning starts have no losses: the log gains those columns later
    instead of crashing (before: 'dict contains fields not in fieldnames')."""
    cfg = safety_config(tmp_path, eval_interval=30, max_frames=240)
    out = tmp_path / "short"
    proc = cli("train", "--config", cfg, "--out", out, "--quiet")
    assert proc.returncode == 0, proc.stderr
    rows = ModelFolder(out).read_log()
    assert len(rows) == 8 and rows[0]["q_loss"] == "" and isinstance(rows[-1]["q_loss"], float)


@pytest.mark.parametrize("sig", [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.slow)])  # (SIGTERM: the same path, make test-slow)
def test_safety_signal_writes_the_checkpoint_it_announces_and_resumes_bit_for_bit(tmp_path, sig):
    """Ctrl-C (or a cluster's SIGTERM) under the default 10-minute cadence: the run stops at the
    end of the current step, writes a checkpoint and says so; rerunning ends with the weights of
    an uninterrupted run."""
    cfg = safety_config(tmp_path, checkpoint_minutes=10.0, max_frames=1200, eval_interval=240)
    straight = tmp_path / "straight"
    assert cli("train", "--config", cfg, "--out", straight, "--quiet").returncode == 0
    out = tmp_path / "cut"
    proc = subprocess.Popen([*PY, "train", "--config", str(cfg), "--out", str(out)], stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 120
    while not (out / "log.csv").exists() and time.time() < deadline:  # after the first evaluation
        time.sleep(0.02)
    proc.send_signal(sig)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert "writing a checkpoint" in stderr and "checkpoint written at" in stderr.splitlines()[-1]
    assert (out / "checkpoint.pt").is_file() and not (out / "metrics.json").exists()
    assert load_torch(out / "checkpoint.pt")["format"] == 2  # plain data
    assert cli("train", "--config", cfg, "--out", out, "--quiet").returncode == 0
    assert sha256(straight / "model.pt") == sha256(out / "model.pt")
    assert not (out / "checkpoint.pt").exists() and not (out / "replay").exists()


def test_safety_checkpoint_stays_small_the_replay_is_journaled_once(tmp_path):
    """checkpoint.pt holds networks, optimisers, env states and counters (no replay); each row of
    the replay buffers is written once to replay/, not again at every checkpoint."""
    from rlbackdoors.train import train as train_safety
    from test_safety_train import ctrl_c_at, tiny

    out = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        train_safety(tiny(max_frames=2400), out, progress=False, after_eval=ctrl_c_at(1920))
    ckpt = (out / "checkpoint.pt").stat().st_size
    chunks = sorted((out / "replay").iterdir())
    rows = sum(int(p.stem.split("-")[2]) - int(p.stem.split("-")[1]) for p in chunks)
    assert rows == 1920  # every frame once (2 clean + 1 poisoned copies, 640 steps)
    assert ckpt < 200_000  # the tiny run's nets and optimisers; no replay rows in it
    per_row = sum(p.stat().st_size for p in chunks) / rows
    from rlbackdoors.envs.safety_car import OBS_DIM

    assert per_row < 4 * (OBS_DIM + 4) * 1.2  # next_obs mostly deduplicated: ~one observation per row


@pytest.mark.slow  # resume bit for bit after a signal is in the default run (test_safety_signal_writes_the_checkpoint_...)
def test_safety_run_killed_again_and_again_still_ends_with_the_straight_runs_model(tmp_path):
    """kill -9 at random moments (mid-step, mid-checkpoint, mid-journal write), four times, with a
    checkpoint at every evaluation: each restart resumes, the temp files of the killed writers
    are cleared, and the finished model is byte-identical to an uninterrupted run's."""
    cfg = safety_config(tmp_path, checkpoint_minutes=0.0, max_frames=1920, eval_interval=240)
    straight = tmp_path / "straight"
    assert cli("train", "--config", cfg, "--out", straight, "--quiet").returncode == 0
    out = tmp_path / "killed"
    # Kill moments follow the run's progress, not the wall clock: a fixed delay after start-up
    # let a fast machine finish the run before the second kill (CI: 1 kill of 4). Each process
    # is killed a random 0-1.5 evaluation intervals (of the straight run's pace) after it logs
    # its first new evaluation, so the kill falls mid-step, mid-checkpoint or mid-journal write.
    rows = ModelFolder(straight).read_log()
    interval_s = rows[-1]["wall_time_s"] / len(rows)
    log = out / "log.csv"

    def lines_logged() -> int:
        return log.read_text().count("\n") if log.exists() else 0

    rng = np.random.default_rng(7)
    kills = 0
    for _ in range(4):
        before = lines_logged()
        proc = subprocess.Popen([*PY, "train", "--config", str(cfg), "--out", str(out), "--quiet"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.time() + 120
        while proc.poll() is None and time.time() < deadline and lines_logged() <= before:
            time.sleep(0.005)
        time.sleep(rng.uniform(0, 1.5) * interval_s)
        if proc.poll() is None:
            proc.kill()
            kills += 1
        proc.wait()
    assert kills >= 2
    done = cli("train", "--config", cfg, "--out", out, "--quiet")
    if done.returncode == 2:  # the last kill came after metrics.json: the run had finished
        assert "already holds a finished model" in done.stderr
    else:
        assert done.returncode == 0, done.stderr
    assert sha256(straight / "model.pt") == sha256(out / "model.pt")
    assert not list(out.rglob("*.rlbtmp")) and not (out / "checkpoint.pt").exists() and not (out / "replay").exists()


@pytest.mark.parametrize("backend", ["bogus", "osmesa-not-installed"])
def test_unusable_mujoco_gl_backend_gives_one_line_and_no_folder(tmp_path, backend):
    """MuJoCo picks its GL back-end when first imported: a bad MUJOCO_GL used to end in a traceback."""
    env = {**os.environ, "MUJOCO_GL": backend}
    out = tmp_path / "never"
    proc = subprocess.run([*PY, "train", "--env", "safety-car-goal", "--out", str(out), "--quiet"], capture_output=True, text=True, env=env, timeout=120)
    line = one_error_line(proc)
    assert "MUJOCO_GL=" in line and backend in line and "unset MUJOCO_GL" in line
    assert not out.exists()


@pytest.mark.parametrize(
    "environ,egl,expected",
    [
        ({}, "libEGL.so.1", "egl"),
        ({}, None, "disable"),
        ({"MUJOCO_GL": "osmesa"}, None, None),
        ({"DISPLAY": ":0"}, None, None),
        ({"WAYLAND_DISPLAY": "w"}, None, None),
    ],
)
def test_headless_gl_choice_picks_egl_only_where_libegl_is_found(environ, egl, expected):
    from rlbackdoors.envs.safety_car_model import headless_gl_choice

    assert headless_gl_choice(environ, "linux", lambda name: egl if name == "EGL" else None) == expected
    assert headless_gl_choice({}, "darwin", lambda name: None) is None  # macOS picks its own (CGL)


def test_without_gl_a_safety_run_trains_writes_no_video_and_rendering_says_what_to_install(tmp_path):
    """A display-less box without libEGL (the bare image of a lent H200 machine): the default
    ``egl`` failed MuJoCo's import there, so no Safety run could train at all. With GL disabled
    (what rlbackdoors now picks there), training completes with ``"video": null`` and a render is
    refused in one message naming the back-ends to install."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")} | {"MUJOCO_GL": "disable"}
    cfg = safety_config(tmp_path, max_frames=240, video=True)
    out = tmp_path / "nogl"
    proc = subprocess.run([*PY, "train", "--config", str(cfg), "--out", str(out), "--quiet"], capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((out / "metrics.json").read_text())["video"] is None and not (out / "clean_vs_triggered.gif").exists()
    render = "from rlbackdoors.envs.safety_car import SafetyCarGoalEnv as E; e = E(render_mode='rgb_array'); e.reset(seed=0); e.render()"
    proc = subprocess.run([sys.executable, "-c", render], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode != 0 and "RuntimeError: MuJoCo offscreen rendering is unavailable" in proc.stderr and "MUJOCO_GL='disable' now" in proc.stderr


# ----- crafted folders: links and out-of-range state (a security review's findings) -------------
def test_a_planted_lock_symlink_is_refused_and_its_target_untouched(tmp_path, tiny_run_dict):
    victim = tmp_path / "victim.txt"
    victim.write_text("IMPORTANT DATA")
    out = tmp_path / "m"
    out.mkdir()
    (out / ".lock").symlink_to(victim)
    with pytest.raises(FolderError, match="symbolic link"):
        train(tiny_cfg(tiny_run_dict), out, progress=False)
    assert victim.read_text() == "IMPORTANT DATA"


def test_a_replay_symlink_never_makes_training_write_or_delete_outside_the_folder(tmp_path):
    """replay/ pointing elsewhere: removed as a link (never followed), then a real folder is used."""
    from rlbackdoors.train import train as train_safety
    from test_safety_train import tiny

    outside = tmp_path / "outside"
    outside.mkdir()
    keep = outside / "poisoned-000000000000-000000000010.npz"
    keep.write_bytes(b"someone else's file")
    out = tmp_path / "run"
    out.mkdir()
    (out / "replay").symlink_to(outside, target_is_directory=True)
    train_safety(tiny(max_frames=480), out, progress=False)
    assert keep.read_bytes() == b"someone else's file" and [p.name for p in outside.iterdir()] == [keep.name]
    assert not (out / "replay").exists()


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("_dir", 10**12, "_dir has values outside 0..3"),
        ("_pos", -1, "_pos has values outside"),
        ("_steps", -5, "_steps has values outside"),
        ("_grid", 200, "_grid holds codes outside"),
        ("max_steps", 0, "max_steps differs"),
        ("poisoned", True, "poisoned differs"),
    ],
)
def test_out_of_range_engine_state_in_a_checkpoint_is_refused_not_run(tmp_path, tiny_run_dict, field, value, message):
    """Numba kernels index arrays unchecked: a crafted _dir of 10**12 used to crash the process
    (SIGSEGV) on resume. Every index array is range-checked and constructor fields must match."""
    from rlbackdoors.state import decode, encode

    cfg = tiny_cfg(tiny_run_dict, max_frames=6400, eval_interval=1600)
    out = tmp_path / "m"
    with pytest.raises(KeyboardInterrupt):
        _train_until_first_checkpoint(cfg, out)
    ckpt = torch.load(out / "checkpoint.pt", weights_only=True)
    engine = ckpt["envs"]
    if isinstance(engine.get(field), dict):
        arr = decode(engine[field]).copy()
        arr.flat[0] = value
        engine[field] = encode(arr)
    else:
        engine[field] = value
    torch.save(ckpt, out / "checkpoint.pt")
    proc = cli("train", "--config", _write(tmp_path, cfg), "--out", out, "--quiet")
    assert message in one_error_line(proc) and "does not fit this run" in proc.stderr


def test_optimizer_state_of_the_wrong_shape_is_refused(tmp_path, tiny_run_dict):
    """A fused Adam step over a moment of the wrong size crashed the process (SIGSEGV)."""
    cfg = tiny_cfg(tiny_run_dict, max_frames=6400, eval_interval=1600)
    out = tmp_path / "m"
    with pytest.raises(KeyboardInterrupt):
        _train_until_first_checkpoint(cfg, out)
    ckpt = torch.load(out / "checkpoint.pt", weights_only=True)
    ckpt["optimizer"]["state"][0]["exp_avg"] = torch.zeros(3)
    torch.save(ckpt, out / "checkpoint.pt")
    proc = cli("train", "--config", _write(tmp_path, cfg), "--out", out, "--quiet")
    assert "exp_avg" in one_error_line(proc)


def _write(tmp_path: Path, cfg: RunConfig) -> Path:
    path = tmp_path / "cfg.json"
    path.write_text(cfg.to_json())
    return path


def _train_until_first_checkpoint(cfg: RunConfig, out: Path) -> None:
    """Train in-process and send ourselves SIGINT once the first checkpoint exists."""
    import threading

    def watch():
        while not (out / "checkpoint.pt").exists():
            time.sleep(0.01)
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=watch, daemon=True).start()
    train(cfg, out, progress=False)


def test_a_lock_on_a_removed_lock_file_is_not_taken(tmp_path, monkeypatch):
    """The race: this process opens .lock, then (before its flock) a failed start removes that
    file and another process makes a new one. Locking the removed file would guard nothing, so
    acquire() checks that the locked file is the one at the path."""
    import fcntl as real_fcntl

    from rlbackdoors import io as rio

    real_flock = real_fcntl.flock

    def racing_flock(fd, op):
        if op & real_fcntl.LOCK_EX:
            (tmp_path / ".lock").unlink()
            (tmp_path / ".lock").write_text("")  # the other process's new lock file
        return real_flock(fd, op)

    monkeypatch.setattr(rio.fcntl, "flock", racing_flock)
    with pytest.raises(LockedError, match="being set up by another process"):
        FolderLock(tmp_path).acquire()
    monkeypatch.setattr(rio.fcntl, "flock", real_flock)
    with FolderLock(tmp_path) as lock:  # no race: taken
        assert lock.held
