"""Run state as plain data (rlbackdoors.state): every engine of every grid world round-trips through
torch's weights-only loader and then steps exactly like the original; bad state is refused."""

import io
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from rlbackdoors.config import RunConfig
from rlbackdoors.io import torch_bytes
from rlbackdoors.poison.mix import make_env_mix
from rlbackdoors.state import StateError, decode, encode, restore, snapshot

WORLDS = ["lavaworld", "randomized-lavaworld", "colorful-memory"]


def through_checkpoint(obj):
    """What a checkpoint does to a value: torch.save, then torch.load(weights_only=True)."""
    return torch.load(io.BytesIO(torch_bytes(obj)), weights_only=True)


def same(a, b) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    return np.array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("engine", ["batched", "minigrid"])
@pytest.mark.parametrize("world", WORLDS)
def test_vector_env_state_round_trips_and_steps_identically(world, engine):
    """300 random steps (episodes end and reset on the way), save, load into a fresh mix of the same
    config, then 300 more steps of both: identical observations, rewards, ends and infos."""
    cfg = RunConfig.from_dict({"env": {"name": world, "engine": engine, "max_steps": 40}})
    env = make_env_mix(cfg.env, cfg.poison)
    rng = np.random.default_rng(0)
    env.reset(seed=5)
    for _ in range(300):
        env.step(rng.integers(0, 3, env.num_envs))
    fresh = make_env_mix(cfg.env, cfg.poison)
    fresh.reset(seed=999)  # a different state, wholly replaced by the load
    fresh.load_state_dict(through_checkpoint(env.state_dict()))
    ends = 0
    for _ in range(300):
        actions = rng.integers(0, 3, env.num_envs)
        a, b = env.step(actions), fresh.step(actions)
        for x, y in zip(a, b):
            assert same(x, y)
        ends += int(np.sum(a[2] | a[3]))
    assert ends > 0  # the comparison crossed episode ends: the envs' RNGs were restored too


def test_state_of_another_world_or_size_is_refused():
    lava = make_env_mix(RunConfig().env, RunConfig().poison)
    lava.reset(seed=0)
    cfg = RunConfig.from_dict({"env": {"name": "lavaworld", "size": 11}})
    bigger = make_env_mix(cfg.env, cfg.poison)
    with pytest.raises(StateError, match="expected an array|size"):
        bigger.load_state_dict(through_checkpoint(lava.state_dict()))
    rlw = RunConfig.from_dict({"env": {"name": "randomized-lavaworld"}})
    other = make_env_mix(rlw.env, rlw.poison)
    with pytest.raises(StateError):
        other.load_state_dict(through_checkpoint(lava.state_dict()))


class Thing:
    def __init__(self):
        self.count = 3
        self.arr = np.arange(4, dtype=np.int64)
        self.view = self.arr[1:]
        self.rng = np.random.default_rng(1)
        self.cells = frozenset({(1, 2), (3, 4)})
        self.callback = print  # not data: never stored, never restored

    def method(self):
        return self.count


def test_snapshot_restore_rules():
    a = Thing()
    a.count, a.arr[:] = 7, [9, 8, 7, 6]
    a.rng.random()
    state = through_checkpoint(snapshot(a))
    assert "callback" not in state
    b = Thing()
    view = b.view
    restore(b, state)
    assert b.count == 7 and b.arr.tolist() == [9, 8, 7, 6] and view.tolist() == [8, 7, 6]  # copied in place: views stay valid
    assert b.rng.random() == a.rng.random() and b.cells == a.cells
    for bad, match in (
        ({**state, "count": encode("seven")}, "expected int"),
        ({**state, "arr": encode(np.zeros(4, np.float32))}, "expected an array of int64"),
        ({**state, "arr": encode(np.zeros(5, np.int64))}, r"with shape \(4,\)"),
        ({**state, "method": 3}, "expected method|has no attribute"),
        ({**state, "__class__": 3}, "has no attribute"),
        ({k: v for k, v in state.items() if k != "count"}, "lacks count"),
        ({**state, "arr": {"__ndarray__": "|O", "shape": (1,), "data": b"\0" * 8}}, "bad array"),
    ):
        with pytest.raises(StateError, match=match):
            restore(Thing(), bad)
    assert decode(encode({"t": (1, 2.5, "x", None, b"\1")})) == {"t": (1, 2.5, "x", None, b"\1")}
    scalar = decode(through_checkpoint(encode(np.int64(3))))  # numpy scalars stay 0-d (MiniGrid positions)
    assert scalar.shape == () and scalar.dtype == np.int64 and scalar == 3
    with pytest.raises(TypeError, match="not plain data"):
        encode(Thing())


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_ppo_run_stopped_by_sigterm_between_evaluations_resumes_bit_for_bit(tmp_path, tiny_run_dict):
    """SIGTERM lands between evaluations: the run finishes its update, checkpoints that state
    (not the last evaluation's) and exits 130; rerunning gives the uninterrupted model."""
    tiny_run_dict["train"].update(max_frames=20_480, eval_interval=5_120)
    cfg_path = tmp_path / "cfg.json"
    cfg_path.write_text(RunConfig.from_dict(tiny_run_dict).to_json())
    cmd = [sys.executable, "-m", "rlbackdoors.cli", "train", "--config", str(cfg_path), "--out"]
    from rlbackdoors.train import train

    train(RunConfig.from_dict(tiny_run_dict), tmp_path / "whole", progress=False)  # the reference, in this process: same bytes as the CLI's
    proc = subprocess.Popen(cmd + [str(tmp_path / "cut")], stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 60
    while not (tmp_path / "cut" / "log.csv").exists() and time.time() < deadline:  # the first evaluation
        time.sleep(0.01)
    time.sleep(0.3)  # a few updates past it
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "stopped by SIGTERM: checkpoint written at" in err, err
    frames = torch.load(tmp_path / "cut" / "checkpoint.pt", weights_only=True)["frames"]
    assert frames >= 5_120 and frames % 320 == 0  # an update boundary (10 envs x rollout 32)
    subprocess.run(cmd + [str(tmp_path / "cut"), "--quiet"], check=True, capture_output=True)
    assert (tmp_path / "whole" / "model.pt").read_bytes() == (tmp_path / "cut" / "model.pt").read_bytes()
