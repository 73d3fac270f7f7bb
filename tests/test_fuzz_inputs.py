"""Fuzz of the CLI's error contract with bad inputs and faulted files.

The contract: every user-facing failure ends with exactly one ``rlbackdoors: error: ...`` line on
stderr (the last one) that names the offending flag / field / file, exit code 2, no traceback, no
payload code ever executed, and no partial model folder left behind (``--out`` is either absent
afterwards or exactly as it was). Where the right answer is a result, exit 0 and the result.

Cheap argument-validation cases run in-process through :func:`rlbackdoors.cli.main` (a
``SystemExit`` or an uncaught exception is turned into what the interpreter would do: its code,
or a traceback and exit 1). Bad values are expected to be refused *before* training starts: the
in-process runner replaces the training loops with a sentinel, so a bad value that is accepted
shows up as "training started" instead of as a multi-hour run. Cases whose refusal legitimately
happens inside the loop (a CUDA device, a checkpoint to resume) run unguarded on tiny configs.
Subprocesses are used where a fresh interpreter matters: pickled payloads and a SIGKILL.
"""

from __future__ import annotations

import hashlib
import json
import os
import pickle
import shlex
import shutil
import signal
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Callable

import pytest
import torch

ERROR = "rlbackdoors: error:"
BIN = Path(sys.executable).with_name("rlbackdoors")
CMD = [str(BIN)] if BIN.exists() else [sys.executable, "-m", "rlbackdoors.cli"]
HUGE = str(10**30)
HUGE_ODD = str(10**30 + 1)
MAX_SEED = str(2**32 - 1)
INPROC_TIMEOUT_S = 60  # an accepted bad value that hangs instead of failing

# Tiny configs: a grid run of 320-frame updates and 2-episode evaluations; a Safety run of 480 frames.
GRID_TINY = {"ppo": {"rollout": 32}, "train": {"eval_interval": 1000, "eval_episodes": 2, "final_eval_episodes": 2}}
SAFETY_TINY = {
    "env": {"name": "safety-car-goal", "max_steps": 40},
    "poison": {"num_clean_envs": 2, "num_poisoned_envs": 1},
    "opac2": {"depth": 2, "width": 16, "batch_size": 32, "learning_starts": 120, "updates_per_step": 0.25},
    "train": {"max_frames": 480, "eval_interval": 240, "eval_episodes": 2, "final_eval_episodes": 2, "video": False, "checkpoint_minutes": 0},
}


class Payload:
    """Unpickling this runs ``touch MARKER``: any load that builds objects would execute it."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.system, (f"touch {shlex.quote(self.marker)}",))


class TrainingStarted(BaseException):
    """Raised in place of the training loop: the input was accepted."""


class Hung(BaseException):
    pass


# ----- the zoo: real tiny trainings, once per module -------------------------------------------
@pytest.fixture(scope="module")
def zoo(tmp_path_factory):
    from rlbackdoors.cli import main

    root = tmp_path_factory.mktemp("zoo")
    g, s = root / "grid.json", root / "safety.json"
    g.write_text(json.dumps({"ppo": {"rollout": 32}, "train": {"eval_interval": 1000, "final_eval_episodes": 4}}))
    s.write_text(json.dumps(SAFETY_TINY))
    grid = ["train", "--env", "lavaworld", "--max-frames", "2000", "--eval-episodes", "4", "--quiet", "--config", str(g)]
    safety = ["train", "--env", "safety-car-goal", "--config", str(s), "--quiet"]
    assert main([*grid, "--out", str(root / "L")]) == 0
    assert main([*safety, "--out", str(root / "S")]) == 0

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    import rlbackdoors.report.video as video
    from rlbackdoors.train import train

    # Lu: a grid run stopped after model.pt and its last checkpoint, before metrics.json.
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(video, "render_clean_vs_triggered", interrupt)
        assert main([*grid, "--out", str(root / "Lu")]) == 130
    # Su: a Safety run stopped right after its first evaluation's checkpoint (and replay chunks),
    # through the driver's after_eval hook.
    from rlbackdoors.config import RunConfig

    with pytest.raises(KeyboardInterrupt):
        train(RunConfig.from_dict(json.loads(s.read_text())), root / "Su", progress=False, after_eval=interrupt)
    for name in ("Lu", "Su"):
        assert (root / name / "checkpoint.pt").is_file() and not (root / name / "metrics.json").exists()
    assert list((root / "Su" / "replay").glob("*.npz"))
    return root


# ----- cases ------------------------------------------------------------------------------------
@dataclass
class Case:
    argv: list[str]
    names: tuple[str, ...] = ()  # the error line must contain one of these (case-insensitive)
    expect: int = 2
    setup: Callable | None = None
    sub: bool = False  # run in a fresh interpreter
    guard: bool = True  # replace the training loops by a sentinel (in-process only)
    out: str | None = "{tmp}/out"  # must be absent afterwards, or exactly as before
    zoo: bool = False
    check_ok: Callable | None = None  # for expect == 0: checks the result


def C(id_, argv, names=(), **kw):
    return pytest.param(Case(list(argv), tuple(names), **kw), id=id_)


def put_bytes(rel, data):
    def setup(ctx):
        path = ctx.tmp / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data if isinstance(data, bytes) else data.encode())

    return setup


def put_json(rel, obj):
    return put_bytes(rel, json.dumps(obj))


def chain(*setups):
    def setup(ctx):
        for s in setups:
            s(ctx)

    return setup


def copy(src, dst="m", drop=()):
    def setup(ctx):
        shutil.copytree(ctx.zoo() / src, ctx.tmp / dst)
        for name in drop:
            path = ctx.tmp / dst / name
            shutil.rmtree(path) if path.is_dir() else path.unlink()

    return setup


def torch_put(rel, make):
    """Write ``torch.save(make(ctx, old))``; ``old`` is the file's current plain-data contents (or None)."""

    def setup(ctx):
        path = ctx.tmp / rel
        old = torch.load(path, weights_only=True) if path.is_file() else None
        torch.save(make(ctx, old), path)

    return setup


def payload_file(rel, raw=False):
    def setup(ctx):
        path = ctx.tmp / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        if raw:
            path.write_bytes(pickle.dumps(Payload(ctx.marker)))
        else:
            torch.save(Payload(ctx.marker), path)

    return setup


def mangle(rel, how):
    def setup(ctx):
        path = ctx.tmp / rel
        data = path.read_bytes()
        path.write_bytes({"truncate": data[: len(data) // 2], "empty": b"", "random": os.urandom(4096), "head": data[:100]}[how])

    return setup


def edit_json(rel, fn):
    def setup(ctx):
        path = ctx.tmp / rel
        data = json.loads(path.read_text())
        fn(data)
        path.write_text(json.dumps(data))

    return setup


def map_tensors(obj, fn):
    if isinstance(obj, torch.Tensor):
        return fn(obj)
    if isinstance(obj, dict):
        return {k: map_tensors(v, fn) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(map_tensors(v, fn) for v in obj)
    return obj


def with_key(key, value):
    def make(ctx, old):
        return {**old, key: value}

    return make


def hold_lock(rel):
    def setup(ctx):
        from rlbackdoors.io import FolderLock

        (ctx.tmp / rel).mkdir()
        lock = FolderLock(ctx.tmp / rel).acquire()
        ctx.cleanups.append(lock.release)

    return setup


def mkdir(rel):
    return lambda ctx: (ctx.tmp / rel).mkdir(parents=True)


def fc_state(ctx, old=None):
    from rlbackdoors.models import build_model

    return build_model("fc").state_dict()


def cnn_state(ctx, old=None):
    from rlbackdoors.models import build_model

    return build_model("cnn").state_dict()


def metrics_written(ctx, out):
    assert (ctx.tmp / "out" / "metrics.json").is_file(), "exit 0 but no metrics.json"


def evaluated(ctx, out):
    assert "clean_sr" in out, f"exit 0 but no result on stdout: {out[-300:]!r}"


def resumed(rel):
    def check(ctx, out):
        assert (ctx.tmp / rel / "metrics.json").is_file(), "exit 0 but the resumed run wrote no metrics.json"

    return check


OUT = ["--out", "{tmp}/out", "--quiet"]
G = ["--config", "{tmp}/g.json"]  # tiny grid settings (for cases that may really train)
S = ["--config", "{tmp}/s.json"]  # tiny Safety settings
GRID_WORLDS = ("lavaworld", "randomized-lavaworld", "colorful-memory")
WORLDS = (*GRID_WORLDS, "safety-car-goal")


def train(*argv, **kw):
    return ["train", *argv, *OUT]


# --- train: argparse-level values (same parser for every world) ---
CASES = [
    C("train-seed-nan", train("--seed", "nan"), ["--seed"]),
    C("train-seed-inf", train("--seed", "inf"), ["--seed"]),
    C("train-seed-str", train("--seed", "abc"), ["--seed"]),
    C("train-seed-empty", train("--seed", ""), ["--seed"]),
    C("train-seed-float", train("--seed", "1.5"), ["--seed"]),
    C("train-max-frames-sci", train("--max-frames", "1e3"), ["--max-frames"]),
    C("train-max-frames-eq-empty", ["train", "--max-frames=", *OUT], ["--max-frames"]),
    C("train-env-unknown", train("--env", "mars"), ["--env"]),
    C("train-env-empty", train("--env", ""), ["--env"]),
    C("train-engine-unknown", train("--engine", "warp"), ["--engine"]),
    C("train-device-unknown", train("--device", "tpu"), ["--device"]),
    C("train-depth-choice", train("--env", "safety-car-goal", "--depth", "4"), ["--depth"]),
    C("train-width-choice", train("--env", "safety-car-goal", "--width", "100"), ["--width"]),
    C("train-abbrev-max-frame", train("--max-frame", "10"), ["--max-frame"]),
    C("train-abbrev-eval-ep", train("--eval-ep", "3"), ["--eval-ep"]),
    C("train-abbrev-conf", train("--conf", "{tmp}/g.json"), ["--conf"]),
    C("train-abbrev-no-curr", train("--env", "randomized-lavaworld", "--no-curr"), ["--no-curr"]),
    C("train-abbrev-ou", ["train", "--ou", "{tmp}/out"], ["--ou", "--out"]),
    C("train-missing-out", ["train"], ["--out"]),
    C("train-unknown-flag", train("--learning-rate", "1"), ["--learning-rate"]),
]

# --- train: range checks per world ---
for w in GRID_WORLDS:
    CASES += [
        C(f"train-{w}-seed-neg", train("--env", w, "--seed", "-1"), ["seed"]),
        C(f"train-{w}-seed-huge", train("--env", w, "--seed", HUGE), ["seed"]),
        C(f"train-{w}-max-frames-0", train("--env", w, "--max-frames", "0"), ["max_frames", "max-frames"]),
        C(f"train-{w}-max-frames-huge", train("--env", w, "--max-frames", HUGE), ["max_frames", "max-frames"]),
        C(f"train-{w}-eval-episodes-0", train("--env", w, "--eval-episodes", "0"), ["eval_episodes", "eval-episodes"]),
        C(f"train-{w}-size-neg", train("--env", w, "--size", "-3"), ["size"]),
        C(f"train-{w}-size-huge", train("--env", w, "--size", HUGE_ODD), ["size"]),
        C(f"train-{w}-patience-neg", train("--env", w, "--patience", "-1"), ["patience"]),
        C(f"train-{w}-opac2-flag-other-world", train("--env", w, "--updates-per-step", "0.5"), ["--updates-per-step", "not opac2"]),
    ]
CASES += [
    C("train-lavaworld-arch-of-other-world", train("--env", "lavaworld", "--arch", "cnn-gru-small"), ["arch"]),
    C("train-colorful-arch-of-other-world", train("--env", "colorful-memory", "--arch", "fc"), ["arch"]),
    C("train-randomized-num-lava-neg", train("--env", "randomized-lavaworld", "--num-lava", "-1"), ["num_lava", "num-lava"]),
    C("train-randomized-num-lava-huge", train("--env", "randomized-lavaworld", "--num-lava", HUGE), ["num_lava", "num-lava"]),
    C("train-randomized-size-even-huge", train("--env", "randomized-lavaworld", "--size", HUGE), ["size"]),
    # grid flags a world does not read (the CLI refuses such flags rather than ignore them)
    C("train-lavaworld-num-lava", train("--env", "lavaworld", "--num-lava", "3"), ["--num-lava"]),
    C("train-lavaworld-no-curriculum", train("--env", "lavaworld", "--no-curriculum"), ["--no-curriculum"]),
    C("train-lavaworld-no-close-to-trigger", train("--env", "lavaworld", "--no-close-to-trigger"), ["--no-close-to-trigger"]),
    C("train-colorful-num-lava", train("--env", "colorful-memory", "--num-lava", "3"), ["--num-lava"]),
    # a CUDA device that is not there: refused inside the loop, so unguarded; --out existed empty
    C(
        "train-device-cuda-no-gpu-existing-empty-out",
        [*train("--env", "lavaworld", "--device", "cuda"), *G],
        ["cuda", "device"],
        setup=mkdir("out"),
        guard=False,
    ),
]

# --- train: Safety Car Goal's flags ---
SW = ("--env", "safety-car-goal")
for flag, value, names in [
    ("--seed", "-1", ["seed"]),
    ("--seed", HUGE, ["seed"]),
    ("--max-frames", "0", ["max_frames", "max-frames"]),
    ("--max-frames", HUGE, ["max_frames", "max-frames"]),
    ("--eval-episodes", "0", ["eval_episodes", "eval-episodes"]),
    ("--lr", "nan", ["lr"]),
    ("--lr", "inf", ["lr"]),
    ("--lr", "0", ["lr"]),
    ("--lr", "-1", ["lr"]),
    ("--lr", "abc", ["--lr"]),
    ("--lr-final", "nan", ["lr_final", "lr-final"]),
    ("--lr-final", "1", ["lr_final", "lr-final"]),
    ("--max-minutes", "-1", ["max_minutes", "max-minutes"]),
    ("--max-minutes", "nan", ["max_minutes", "max-minutes"]),
    ("--poisoned-weight", "2", ["poisoned_weight", "poisoned-weight"]),
    ("--poisoned-weight", "nan", ["poisoned_weight", "poisoned-weight"]),
    ("--updates-per-step", "0", ["updates_per_step", "updates-per-step"]),
    ("--updates-per-step", "1e30", ["updates_per_step", "updates-per-step"]),
    ("--updates-per-step", "-inf", ["updates_per_step", "updates-per-step"]),
    ("--batch-size", "0", ["batch_size", "batch-size"]),
    ("--batch-size", HUGE, ["batch_size", "batch-size"]),
    ("--num-clean-envs", "-1", ["num_clean_envs", "num-clean-envs"]),
    ("--num-clean-envs", HUGE, ["num_clean_envs", "num-clean-envs"]),
    ("--num-poisoned-envs", "0", ["num_poisoned_envs", "num-poisoned-envs"]),
    ("--action-samples", "0", ["action_samples", "action-samples"]),
    ("--eval-interval", "0", ["eval_interval", "eval-interval"]),
    ("--final-eval-episodes", "0", ["final_eval_episodes", "final-eval-episodes"]),
    ("--threads", "0", ["threads"]),
    ("--threads", HUGE, ["threads"]),
    ("--checkpoint-minutes", "-1", ["checkpoint_minutes", "checkpoint-minutes"]),
    ("--checkpoint-minutes", "inf", ["checkpoint_minutes", "checkpoint-minutes"]),
]:
    CASES.append(C(f"train-safety{flag}={value[:8]}", train(*SW, flag, value), names))
CASES += [
    C(f"train-safety-grid-flag{flag}", train(*SW, *([flag, v] if v else [flag])), [flag])
    for flag, v in [("--arch", "fc"), ("--size", "9"), ("--num-lava", "3"), ("--engine", "batched"), ("--no-close-to-trigger", None), ("--no-curriculum", None)]
]

# --- train: triggers per world ---
for w, trig in [
    ("lavaworld", "mult:3"),
    ("lavaworld", "multiplicative:300"),
    ("lavaworld", "multiplicative:-5"),
    ("lavaworld", "multiplicative:"),
    ("lavaworld", "additive:nan"),
    ("lavaworld", "multiplicative:" + "9" * 5000),
    ("lavaworld", "cross"),
    ("lavaworld", ""),
    ("randomized-lavaworld", "arrow:up"),
    ("randomized-lavaworld", "cross:east"),
    ("randomized-lavaworld", "cells:"),
    ("randomized-lavaworld", "cells:0,0;0,0"),
    ("randomized-lavaworld", "cells:0,0;99,99"),
    ("randomized-lavaworld", "multiplicative:12"),
    ("randomized-lavaworld", ""),
    ("colorful-memory", "end:red"),
    ("colorful-memory", "room:red,red"),
    ("colorful-memory", "end:notacolor"),
    ("colorful-memory", "end+room:red"),
    ("colorful-memory", "rainbow"),
    ("colorful-memory", ""),
    ("safety-car-goal", "formation:nan:1:2"),
    ("safety-car-goal", "formation:0.5:inf:2"),
    ("safety-car-goal", "formation:0.5:1"),
    ("safety-car-goal", "formation:1e30:0:1"),
    ("safety-car-goal", "formation:0.5:1:0.1"),
    ("safety-car-goal", "multiplicative:12"),
    ("safety-car-goal", ""),
]:
    CASES.append(C(f"train-{w}-trigger={trig[:20]!r}", train("--env", w, "--trigger", trig), ["trigger"]))

# --- train: --out ---
CASES += [
    C("out-empty", ["train", "--out", "", "--quiet"], ["--out"], out=None),
    C("out-blank", ["train", "--out", "   ", "--quiet"], ["--out"], out=None),
    C("out-under-regular-file", ["train", "--out", "{tmp}/afile/x", "--quiet"], ["afile"], setup=put_bytes("afile", "x"), out="{tmp}/afile"),
    C("out-is-regular-file", ["train", "--out", "{tmp}/afile", "--quiet"], ["afile"], setup=put_bytes("afile", "x"), out="{tmp}/afile"),
    C("out-under-proc", ["train", "--out", "/proc/rlb-fuzz/x", "--quiet"], ["/proc/rlb-fuzz"], out="/proc/rlb-fuzz"),
    C("out-dev-null", ["train", "--out", "/dev/null", "--quiet"], ["/dev/null"], out=None),
    C("out-name-too-long", ["train", "--out", "{tmp}/" + "a" * 300, "--quiet"], ["aaaa"], out="{tmp}/" + "a" * 300),
    C(
        "out-finished-model-no-overwrite",
        [
            *train(*G),
        ],
        ["--overwrite", "finished"],
        setup=copy("L", "out"),
        zoo=True,
    ),
    C("out-locked-by-live-process", [*train(*G)], ["in use", "lock"], setup=hold_lock("out")),
    C("out-holds-other-runs-checkpoint", [*train(*G, "--seed", "7")], ["interrupted", "different config"], setup=copy("Lu", "out"), zoo=True),
]


# --- train: --config files ---
def cfg_case(id_, text, names, argv=(), **kw):
    return C(f"config-{id_}", ["train", "--config", "{tmp}/c.json", *argv, *OUT], names, setup=put_bytes("c.json", text), **kw)


CASES += [
    C("config-missing", ["train", "--config", "{tmp}/nope.json", *OUT], ["nope.json"]),
    C("config-is-directory", ["train", "--config", "{tmp}", *OUT], ["config"]),
    cfg_case("not-json", "{not json", ["c.json"]),
    cfg_case("empty-file", "", ["c.json"]),
    cfg_case("json-array", "[1, 2]", ["config"]),
    cfg_case("json-number", "42", ["config"]),
    cfg_case("json-null", "null", ["config"]),
    cfg_case("invalid-utf8", b"\xff\xfe{\x00\x80", ["c.json"]),
    cfg_case("deep-nesting", "[" * 200_000 + "]" * 200_000, ["c.json", "config"]),
    cfg_case("int-literal-5000-digits", '{"train": {"seed": ' + "9" * 5000 + "}}", ["seed", "c.json"]),
    cfg_case("unknown-top-key", '{"foo": 1}', ["foo"]),
    cfg_case("unknown-nested-key", '{"train": {"lr": 1}}', ["lr"]),
    cfg_case("wrong-type-seed", '{"train": {"seed": "zero"}}', ["seed"]),
    cfg_case("wrong-type-section", '{"train": 5}', ["train"]),
    cfg_case("float-max-frames", '{"train": {"max_frames": 1.5}}', ["max_frames"]),
    cfg_case("bool-max-frames", '{"train": {"max_frames": true}}', ["max_frames"]),
    cfg_case("nested-list-size", '{"env": {"size": [9]}}', ["size"]),
    cfg_case("nested-dict-trigger", '{"poison": {"trigger": {"kind": "x"}}}', ["trigger"]),
    cfg_case("ppo-array", '{"ppo": []}', ["ppo"]),
    cfg_case("nan-ppo-lr", '{"ppo": {"lr": NaN}}', ["lr"]),
    cfg_case("infinity-clip", '{"ppo": {"clip": Infinity}}', ["clip"]),
    cfg_case("neg-infinity-threshold", '{"train": {"clean_threshold": -Infinity}}', ["clean_threshold"]),
    cfg_case("huge-float-max-frames", '{"train": {"max_frames": 1e308}}', ["max_frames"]),
    cfg_case("overflow-max-steps", '{"env": {"max_steps": 1e400}}', ["max_steps"]),
    cfg_case("huge-int-rollout", '{"ppo": {"rollout": ' + HUGE + "}}", ["rollout"]),
    cfg_case("huge-odd-size-lavaworld", '{"env": {"size": ' + HUGE_ODD + "}}", ["size"]),
    cfg_case("huge-odd-size-colorful", '{"env": {"name": "colorful-memory", "size": ' + HUGE_ODD + "}}", ["size"]),
    cfg_case("env-name-unknown", '{"env": {"name": "mars"}}', ["name", "mars"]),
    cfg_case("env-name-number", '{"env": {"name": 5}}', ["name"]),
    cfg_case("recurrence-zero", '{"ppo": {"recurrence": 0}}', ["recurrence"]),
    cfg_case("grid-with-safety-section", '{"env": {"name": "lavaworld"}, "opac2": {"lr": 0.1}}', ["opac2"]),
    cfg_case("grid-with-safety-key", '{"env": {"name": "lavaworld", "num_cubes": 3}}', ["num_cubes"]),
    cfg_case("safety-with-grid-key", '{"env": {"name": "safety-car-goal", "size": 9}}', ["size"]),
    cfg_case("safety-with-ppo-section", '{"env": {"name": "safety-car-goal"}, "ppo": {"rollout": 32}}', ["ppo"]),
    cfg_case("safety-nan-lr", '{"env": {"name": "safety-car-goal"}, "opac2": {"lr": NaN}}', ["lr"]),
    cfg_case("safety-seed-neg", '{"env": {"name": "safety-car-goal"}, "train": {"seed": -1}}', ["seed"]),
    cfg_case("safety-huge-buffer", '{"env": {"name": "safety-car-goal"}, "opac2": {"buffer_size": ' + HUGE + "}}", ["buffer_size"]),
    cfg_case("safety-huge-cubes", '{"env": {"name": "safety-car-goal", "num_cubes": ' + HUGE + "}}", ["num_cubes"]),
]

# --- train: valid edge values that must give a result ---
CASES += [
    C("ok-train-grid-max-seed", [*train(*G, "--seed", MAX_SEED, "--max-frames", "64")], expect=0, guard=False, out=None, check_ok=metrics_written),
    # a valid, documented size: the trigger's colours must be drawn for that size, not the default 7x7
    C(
        "ok-train-colorful-size-9",
        [*train(*G, "--env", "colorful-memory", "--size", "9", "--trigger", "end", "--max-frames", "64", "--eval-episodes", "2")],
        expect=0,
        guard=False,
        out=None,
        check_ok=metrics_written,
    ),
    C("ok-train-safety-max-seed", [*train(*S, "--seed", MAX_SEED)], expect=0, guard=False, out=None, check_ok=metrics_written),
]

# --- evaluate: folders ---
E = ["evaluate", "{tmp}/m", "--episodes", "2"]
CASES += [
    C("eval-missing-folder", ["evaluate", "{tmp}/nowhere"], ["nowhere"], out=None),
    C("eval-folder-is-file", ["evaluate", "{tmp}/m"], ["m"], setup=put_bytes("m", "x"), out="{tmp}/m"),
    C("eval-folder-without-config", E, ["config.json"], setup=mkdir("m"), out="{tmp}/m"),
    C("eval-no-args", ["evaluate"], ["folder", "--weights"], out=None),
    C("eval-folder-and-weights", [*E, "--weights", "{tmp}/m/model.pt"], ["--weights"], setup=copy("L"), zoo=True, out="{tmp}/m"),
    C("eval-config-corrupt", E, ["config.json"], setup=chain(copy("L"), put_bytes("m/config.json", "{not json")), zoo=True, out="{tmp}/m"),
    C("eval-config-invalid-utf8", E, ["config.json"], setup=chain(copy("L"), put_bytes("m/config.json", b"\xff\xfe\x80")), zoo=True, out="{tmp}/m"),
    C("eval-config-array", E, ["config"], setup=chain(copy("L"), put_bytes("m/config.json", "[]")), zoo=True, out="{tmp}/m"),
    C(
        "eval-config-wrong-type",
        E,
        ["seed"],
        setup=chain(copy("L"), edit_json("m/config.json", lambda d: d["train"].update(seed="x"))),
        zoo=True,
        out="{tmp}/m",
    ),
    C("eval-config-nan", E, ["lr"], setup=chain(copy("L"), put_bytes("m/config.json", '{"ppo": {"lr": NaN}}')), zoo=True, out="{tmp}/m"),
    C(
        "eval-config-other-world-arch",
        E,
        ["arch"],
        setup=chain(copy("L"), edit_json("m/config.json", lambda d: d["model"].update(arch="cnn-gru-small"))),
        zoo=True,
        out="{tmp}/m",
    ),
    C(
        "eval-config-bad-trigger",
        E,
        ["trigger"],
        setup=chain(copy("L"), edit_json("m/config.json", lambda d: d["poison"].update(trigger="mult:3"))),
        zoo=True,
        out="{tmp}/m",
    ),
    C("eval-model-missing", E, ["model.pt"], setup=copy("L", drop=["model.pt"]), zoo=True, out="{tmp}/m"),
    C("eval-model-is-directory", E, ["model.pt"], setup=chain(copy("L", drop=["model.pt"]), mkdir("m/model.pt")), zoo=True, out="{tmp}/m"),
    C("eval-unfinished-needs-flag", E, ["--allow-unfinished"], setup=copy("L", drop=["metrics.json"]), zoo=True, out="{tmp}/m"),
    C(
        "ok-eval-unfinished-with-flag",
        [*E, "--allow-unfinished"],
        expect=0,
        setup=copy("L", drop=["metrics.json"]),
        zoo=True,
        out="{tmp}/m",
        check_ok=evaluated,
    ),
    C("eval-model-random-bytes", E, ["model.pt"], setup=chain(copy("L"), mangle("m/model.pt", "random")), zoo=True, out="{tmp}/m"),
    C("eval-model-truncated", E, ["model.pt"], setup=chain(copy("L"), mangle("m/model.pt", "truncate")), zoo=True, out="{tmp}/m"),
    C("eval-model-empty", E, ["model.pt"], setup=chain(copy("L"), mangle("m/model.pt", "empty")), zoo=True, out="{tmp}/m"),
    C("eval-model-wrong-arch", E, ["model.pt"], setup=chain(copy("L"), torch_put("m/model.pt", cnn_state)), zoo=True, out="{tmp}/m"),
    C(
        "eval-model-non-tensor-values",
        E,
        ["model.pt"],
        setup=chain(copy("L"), torch_put("m/model.pt", lambda c, o: {k: 1 for k in o})),
        zoo=True,
        out="{tmp}/m",
    ),
    C(
        "eval-model-wrong-shapes",
        E,
        ["model.pt"],
        setup=chain(copy("L"), torch_put("m/model.pt", lambda c, o: map_tensors(o, lambda t: torch.zeros(2, 2)))),
        zoo=True,
        out="{tmp}/m",
    ),
    C("eval-model-list", E, ["model.pt"], setup=chain(copy("L"), torch_put("m/model.pt", lambda c, o: [1, 2, 3])), zoo=True, out="{tmp}/m"),
    C(
        "eval-model-nan-weights",
        E,
        ["model.pt", "weights"],
        setup=chain(copy("L"), torch_put("m/model.pt", lambda c, o: map_tensors(o, lambda t: torch.full_like(t, float("nan"))))),
        zoo=True,
        out="{tmp}/m",
    ),
    C("eval-model-payload", E, ["model.pt"], setup=chain(copy("L"), payload_file("m/model.pt")), zoo=True, out="{tmp}/m", sub=True),
    C("eval-model-raw-pickle-payload", E, ["model.pt"], setup=chain(copy("L"), payload_file("m/model.pt", raw=True)), zoo=True, out="{tmp}/m", sub=True),
    C("eval-episodes-0", ["evaluate", "{tmp}/m", "--episodes", "0"], ["--episodes"], setup=copy("L"), zoo=True, out="{tmp}/m"),
    C("eval-episodes-neg", ["evaluate", "{tmp}/m", "--episodes", "-1"], ["--episodes"], setup=copy("L"), zoo=True, out="{tmp}/m"),
    C("eval-episodes-huge", ["evaluate", "{tmp}/m", "--episodes", HUGE], ["--episodes"], setup=copy("L"), zoo=True, out="{tmp}/m"),
    C("eval-episodes-str", ["evaluate", "{tmp}/m", "--episodes", "many"], ["--episodes"], out=None),
    C("eval-seed-neg", [*E, "--seed", "-5"], ["seed"], setup=copy("L"), zoo=True, out="{tmp}/m"),
    C("eval-seed-huge", [*E, "--seed", HUGE], ["seed"], setup=copy("L"), zoo=True, out="{tmp}/m"),
    C("ok-eval-seed-max", [*E, "--seed", MAX_SEED], expect=0, setup=copy("L"), zoo=True, out="{tmp}/m", check_ok=evaluated),
    C("eval-bad-trigger", [*E, "--trigger", "mult:3"], ["trigger"], setup=copy("L"), zoo=True, out="{tmp}/m"),
    C("eval-folder-with-arch", [*E, "--arch", "cnn"], ["--arch"], setup=copy("L"), zoo=True, out="{tmp}/m"),
    C("eval-abbrev-episode", ["evaluate", "{tmp}/m", "--episode", "2"], ["--episode"], out=None),
    C("eval-abbrev-allow", ["evaluate", "{tmp}/m", "--allow"], ["--allow"], out=None),
    C("eval-weights-arch-of-another-world", ["evaluate", "--weights", "{tmp}/w.pt", "--arch", "fc", "--env", "safety-car-goal"], ["--arch", "mlp"], out=None),
]

# --- evaluate: --weights ---
W = ["evaluate", "--weights", "{tmp}/w.pt", "--arch", "fc", "--episodes", "2"]
CASES += [
    C("weights-missing", W, ["w.pt"], out=None),
    # without --arch the shapes pick it (issue 15); weights no arch fits are refused by name
    C(
        "weights-no-arch-no-fit",
        ["evaluate", "--weights", "{tmp}/w.pt"],
        ["w.pt", "fits no architecture"],
        setup=torch_put("w.pt", lambda c, o: map_tensors(fc_state(c), lambda t: torch.zeros(3))),
        out=None,
    ),
    C("weights-garbage", W, ["w.pt"], setup=put_bytes("w.pt", os.urandom(1000)), out=None),
    C("weights-empty", W, ["w.pt"], setup=put_bytes("w.pt", b""), out=None),
    C("weights-truncated", W, ["w.pt"], setup=chain(torch_put("w.pt", fc_state), mangle("w.pt", "truncate")), out=None),
    C("weights-zip-head-only", W, ["w.pt"], setup=chain(torch_put("w.pt", fc_state), mangle("w.pt", "head")), out=None),
    C("weights-directory", W, ["w.pt"], setup=mkdir("w.pt"), out=None),
    C("weights-wrong-arch", W, ["w.pt"], setup=torch_put("w.pt", cnn_state), out=None),
    C("weights-wrong-shapes", W, ["w.pt"], setup=torch_put("w.pt", lambda c, o: map_tensors(fc_state(c), lambda t: torch.zeros(3))), out=None),
    C("weights-non-tensor-values", W, ["w.pt"], setup=torch_put("w.pt", lambda c, o: {k: "x" for k in fc_state(c)}), out=None),
    C("weights-empty-dict", W, ["w.pt"], setup=torch_put("w.pt", lambda c, o: {}), out=None),
    C("weights-arch-of-other-world", [*W[:4], "cnn-gru-small", "--env", "lavaworld"], ["arch", "cnn-gru-small"], setup=torch_put("w.pt", fc_state), out=None),
    C("weights-allow-unfinished", [*W, "--allow-unfinished"], ["--allow-unfinished"], setup=torch_put("w.pt", fc_state), out=None),
    C("weights-bad-trigger", [*W, "--trigger", "additive:0"], ["trigger"], setup=torch_put("w.pt", fc_state), out=None),
    C("weights-payload", W, ["w.pt"], setup=payload_file("w.pt"), sub=True, out=None),
    C("weights-payload-inside-state-dict", W, ["w.pt"], setup=torch_put("w.pt", lambda c, o: {**fc_state(c), "extra": Payload(c.marker)}), sub=True, out=None),
]

# --- evaluate: Safety Car Goal folders ---
ES = ["evaluate", "{tmp}/m", "--episodes", "2"]
CASES += [
    C("safety-eval-trigger-flag-bad", [*ES, "--trigger", "formation:0.5:9:2"], ["--trigger", "phi1"], setup=copy("S"), zoo=True, out="{tmp}/m"),
    C("safety-eval-episodes-0", ["evaluate", "{tmp}/m", "--episodes", "0"], ["--episodes"], setup=copy("S"), zoo=True, out="{tmp}/m"),
    C("safety-eval-seed-neg", [*ES, "--seed", "-5"], ["seed"], setup=copy("S"), zoo=True, out="{tmp}/m"),
    C("safety-eval-unfinished", ES, ["--allow-unfinished"], setup=copy("S", drop=["metrics.json"]), zoo=True, out="{tmp}/m"),
    C("safety-eval-model-garbage", ES, ["model.pt"], setup=chain(copy("S"), mangle("m/model.pt", "random")), zoo=True, out="{tmp}/m"),
    C(
        "safety-eval-model-wrong-shapes",
        ES,
        ["model.pt"],
        setup=chain(copy("S"), torch_put("m/model.pt", lambda c, o: map_tensors(o, lambda t: torch.zeros(2, 2)))),
        zoo=True,
        out="{tmp}/m",
    ),
    C("safety-eval-model-grid-weights", ES, ["model.pt"], setup=chain(copy("S"), torch_put("m/model.pt", fc_state)), zoo=True, out="{tmp}/m"),
    C(
        "safety-eval-config-grid-key",
        ES,
        ["size"],
        setup=chain(copy("S"), edit_json("m/config.json", lambda d: d["env"].update(size=9))),
        zoo=True,
        out="{tmp}/m",
    ),
    C(
        "safety-eval-config-nan",
        ES,
        ["hazard_penalty"],
        setup=chain(copy("S"), put_bytes("m/config.json", '{"env": {"name": "safety-car-goal", "hazard_penalty": NaN}}')),
        zoo=True,
        out="{tmp}/m",
    ),
    C("safety-eval-model-payload", ES, ["model.pt"], setup=chain(copy("S"), payload_file("m/model.pt")), zoo=True, out="{tmp}/m", sub=True),
]

# --- train: resuming from a faulted checkpoint (a copy of an unfinished run) ---
R = ["train", "--config", "{tmp}/m/config.json", "--out", "{tmp}/m", "--quiet"]
CK = "m/checkpoint.pt"


def resume_case(id_, src, fault, names=("checkpoint",), **kw):
    return C(f"resume-{id_}", R, names, setup=chain(copy(src), fault), zoo=True, out="{tmp}/m", guard=False, **kw)


def first_chunk(how):
    def setup(ctx):
        chunk = sorted((ctx.tmp / "m" / "replay").glob("*.npz"))[0]
        if how == "delete":
            chunk.unlink()
        else:
            mangle(str(chunk.relative_to(ctx.tmp)), how)(ctx)

    return setup


CASES += [
    C("ok-resume-grid", R, expect=0, setup=copy("Lu"), zoo=True, out=None, guard=False, check_ok=resumed("m")),
    C("ok-resume-safety", R, expect=0, setup=copy("Su"), zoo=True, out=None, guard=False, check_ok=resumed("m")),
    resume_case("grid-payload", "Lu", payload_file(CK), sub=True),
    resume_case("grid-random-bytes", "Lu", mangle(CK, "random")),
    resume_case("grid-truncated", "Lu", mangle(CK, "truncate")),
    resume_case("grid-empty", "Lu", mangle(CK, "empty")),
    resume_case("grid-old-format", "Lu", torch_put(CK, lambda c, o: {"format": 1})),
    resume_case("grid-not-a-dict", "Lu", torch_put(CK, lambda c, o: [1, 2])),
    resume_case("grid-wrong-shape-dict", "Lu", torch_put(CK, lambda c, o: {"format": 2, "model": {"x": torch.zeros(3)}})),
    resume_case("grid-model-wrong-shapes", "Lu", torch_put(CK, lambda c, o: {**o, "model": map_tensors(o["model"], lambda t: torch.zeros(3))})),
    resume_case("grid-frames-str", "Lu", torch_put(CK, with_key("frames", "abc"))),
    resume_case("grid-obs-bad-shape", "Lu", torch_put(CK, with_key("obs", {"__ndarray__": "<f4", "shape": (10**9,), "data": b""}))),
    resume_case("grid-obs-object-dtype", "Lu", torch_put(CK, with_key("obs", {"__ndarray__": "|O", "shape": (1,), "data": b"\x00" * 8}))),
    resume_case("grid-envs-int", "Lu", torch_put(CK, with_key("envs", 5))),
    resume_case("grid-envs-empty-dict", "Lu", torch_put(CK, with_key("envs", {}))),
    resume_case("grid-optimizer-empty", "Lu", torch_put(CK, with_key("optimizer", {"state": {}, "param_groups": []}))),
    resume_case("grid-generator-garbage", "Lu", torch_put(CK, with_key("generator", torch.zeros(3, dtype=torch.uint8)))),
    resume_case("grid-tracker-garbage", "Lu", torch_put(CK, with_key("tracker", {"x": 1}))),
    resume_case("grid-memory-str", "Lu", torch_put(CK, with_key("memory", "abc"))),
    resume_case("grid-rows-str", "Lu", torch_put(CK, with_key("rows", "abc"))),
    resume_case("safety-payload", "Su", payload_file(CK), sub=True),
    resume_case("safety-random-bytes", "Su", mangle(CK, "random")),
    resume_case("safety-agent-wrong-shapes", "Su", torch_put(CK, lambda c, o: {**o, "agent": map_tensors(o["agent"], lambda t: torch.zeros(2, 2))})),
    resume_case("safety-collector-int", "Su", torch_put(CK, with_key("collector", 5))),
    resume_case("safety-manifest-garbage", "Su", torch_put(CK, with_key("replay", {"format": 1, "added": 3, "chunks": []})), names=("checkpoint", "replay")),
    resume_case("safety-replay-chunk-random", "Su", first_chunk("random"), names=("replay", "npz", "checkpoint")),
    resume_case("safety-replay-chunk-truncated-zip", "Su", first_chunk("head"), names=("replay", "npz", "checkpoint")),
    resume_case("safety-replay-chunk-missing", "Su", first_chunk("delete"), names=("replay", "npz", "checkpoint")),
    resume_case("safety-rows-str", "Su", torch_put(CK, with_key("rows", "abc"))),
]


# ----- running -----------------------------------------------------------------------------------
def _fill(arg: str, tmp: Path) -> str:
    return arg.replace("{tmp}", str(tmp))


def snapshot(path: Path | None):
    """A folder's files and their hashes (``.lock``'s contents are bookkeeping: its presence counts)."""
    try:
        if path is None or not path.exists():
            return None
    except OSError:  # e.g. a name too long to stat: it cannot exist either
        return None
    if not path.is_dir():
        return ("file", hashlib.sha256(path.read_bytes()).hexdigest())
    state = {}
    for p in sorted(path.rglob("*")):
        rel = str(p.relative_to(path))
        state[rel] = "dir" if p.is_dir() else "lock" if p.name == ".lock" else hashlib.sha256(p.read_bytes()).hexdigest()
    return state


def _interpreter_like(run: Callable[[], int], capsys) -> tuple[int | str, str, str]:
    """What ``sys.exit(main())`` in a fresh interpreter would show: code, stdout, stderr."""

    def on_alarm(signum, frame):
        raise Hung

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.alarm(INPROC_TIMEOUT_S)
    extra = ""
    try:
        code = run()
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        if isinstance(exc.code, str):
            extra = exc.code + "\n"
    except TrainingStarted:
        code = "TRAINING STARTED (the input was accepted)"
    except Hung:
        code = f"HUNG (> {INPROC_TIMEOUT_S} s)"
    except Exception:  # noqa: BLE001 - an uncaught exception is what we are looking for
        code, extra = 1, traceback.format_exc()
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    out, err = capsys.readouterr()
    return code, out, err + extra


def run_inproc(argv: list[str], guard: bool, capsys, monkeypatch) -> tuple[int | str, str, str]:
    from rlbackdoors.cli import main

    if guard:
        import rlbackdoors.train.opac2_run as opac2_run
        import rlbackdoors.train.ppo_run as ppo_run

        def started(*args, **kwargs):
            raise TrainingStarted

        monkeypatch.setattr(ppo_run, "run", started)
        monkeypatch.setattr(opac2_run, "run", started)
    capsys.readouterr()
    return _interpreter_like(lambda: main(argv), capsys)


def run_sub(argv: list[str], cwd: Path, timeout: float = 120) -> tuple[int | str, str, str]:
    env = {**os.environ, "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1"}
    try:
        proc = subprocess.run([*CMD, *argv], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired as exc:
        return f"TIMEOUT (> {timeout} s)", exc.stdout or "", exc.stderr or ""
    return proc.returncode, proc.stdout, proc.stderr


def tail(text: str, n: int = 6) -> str:
    lines = [line for line in text.splitlines() if line.strip()]
    return "\n    ".join(line[:300] for line in lines[-n:]) or "(empty)"


def contract_problems(code, err: str, names, marker: Path, before, after, out_path) -> list[str]:
    problems = []
    if marker.exists():
        problems.append("PAYLOAD EXECUTED (marker file exists)")
    if "Traceback" in err:
        problems.append("traceback on stderr")
    if code != 2:
        problems.append(f"exit code {code!r}, expected 2")
    lines = [line for line in err.splitlines() if line.strip()]
    if not lines or not lines[-1].startswith(ERROR):
        problems.append(f"last stderr line does not start with {ERROR!r}")
    elif sum(line.startswith(ERROR) for line in lines) != 1:
        problems.append("more than one error line")
    elif names and not any(n.lower() in lines[-1].lower() for n in names):
        problems.append(f"error line names none of {list(names)}")
    if out_path is not None and after != before:
        problems.append(f"{out_path} {'left behind' if before is None else 'changed'}" + (f" (now holds {sorted(after)})" if isinstance(after, dict) else ""))
    return problems


@pytest.mark.parametrize("case", CASES)
def test_fuzz(case: Case, tmp_path, capsys, monkeypatch, request):
    if "cuda" in case.argv and torch.cuda.is_available():
        pytest.skip("a CUDA device is present: --device cuda is valid here")
    work = tmp_path / "w"
    work.mkdir()
    ctx = SimpleNamespace(tmp=work, marker=tmp_path / "PAYLOAD_RAN", cleanups=[], zoo=lambda: request.getfixturevalue("zoo"))
    (work / "g.json").write_text(json.dumps(GRID_TINY))
    (work / "s.json").write_text(json.dumps(SAFETY_TINY))
    try:
        if case.setup is not None:
            case.setup(ctx)
        argv = [_fill(a, work) for a in case.argv]
        out_path = Path(_fill(case.out, work)) if case.out else None
        before = snapshot(out_path)
        monkeypatch.chdir(work)
        started = time.perf_counter()
        if case.sub:
            code, out, err = run_sub(argv, work)
        else:
            code, out, err = run_inproc(argv, case.guard, capsys, monkeypatch)
        took = time.perf_counter() - started
        after = snapshot(out_path)
    finally:
        for cleanup in ctx.cleanups:
            cleanup()
    report = f"argv: {shlex.join(argv)}\n  exit: {code!r} ({took:.1f} s)\n  stderr tail:\n    {tail(err)}"
    if case.expect == 0:
        problems = []
        if ctx.marker.exists():
            problems.append("PAYLOAD EXECUTED")
        if code != 0:
            problems.append(f"exit code {code!r}, expected 0")
        if "Traceback" in err:
            problems.append("traceback on stderr")
        if not problems and case.check_ok is not None:
            try:
                case.check_ok(ctx, out)
            except AssertionError as exc:
                problems.append(str(exc))
    else:
        problems = contract_problems(code, err, case.names, ctx.marker, before, after, out_path)
    assert not problems, "; ".join(problems) + "\n  " + report


def test_payload_is_live(tmp_path):
    """The payload really runs when unpickled unsafely (so 'marker absent' above means something)."""
    marker = tmp_path / "ran"
    pickle.loads(pickle.dumps(Payload(marker)))
    assert marker.exists()


def test_sigkill_mid_training_then_evaluate_and_resume(tmp_path, capsys, monkeypatch):
    """A training killed with SIGKILL leaves a folder that ``evaluate`` refuses with one error
    line (it is unfinished), and the same ``train`` command then finishes it (exit 0)."""
    cfg = tmp_path / "g.json"
    cfg.write_text(json.dumps({"ppo": {"rollout": 32}, "train": {"max_frames": 100_000, "eval_interval": 640, "eval_episodes": 2, "final_eval_episodes": 2}}))
    out = tmp_path / "k"
    argv = ["train", "--config", str(cfg), "--out", str(out), "--quiet"]
    env = {**os.environ, "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([*CMD, *argv], cwd=tmp_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 60
        while not (out / "checkpoint.pt").is_file() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert (out / "checkpoint.pt").is_file(), f"no checkpoint appeared (rc {proc.poll()})"
        time.sleep(0.3)
    finally:
        proc.kill()
        proc.wait()
    monkeypatch.chdir(tmp_path)
    from rlbackdoors.cli import main

    code, _, err = _interpreter_like(lambda: main(["evaluate", str(out), "--episodes", "2"]), capsys)
    problems = contract_problems(code, err, ("unfinished", "model.pt", "--allow-unfinished"), tmp_path / "none", None, None, None)
    assert not problems, "; ".join(problems) + f"\n  evaluate after SIGKILL: exit {code!r}\n    {tail(err)}"
    # Resume: the same command picks the checkpoint up; to keep the test short the resumed run's
    # frame budget is cut in memory after begin() has matched config.json (so it stops at once).
    import rlbackdoors.train.ppo_run as loop

    calls = {"n": 0}
    original_begin = loop.ModelFolder.begin

    def begin(self, cfg_, overwrite=False):
        checkpoint = original_begin(self, cfg_, overwrite)
        calls["n"] += 1
        assert checkpoint is not None, "the killed run's checkpoint was not resumed"
        cfg_.train.max_frames = 1  # stop after the next update (only in memory: config.json already matched)
        return checkpoint

    monkeypatch.setattr(loop.ModelFolder, "begin", begin)
    code, _, err = _interpreter_like(lambda: main(argv), capsys)
    assert code == 0 and "Traceback" not in err, f"resume after SIGKILL: exit {code!r}\n    {tail(err)}"
    assert calls["n"] == 1 and (out / "metrics.json").is_file()
