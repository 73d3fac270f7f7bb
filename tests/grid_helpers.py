"""Helpers shared by the grid-world tests: the batched engines' differential harness against
their MiniGrid reference envs (:class:`Pairing`) and the checks every engine passes alike,
chi-square helpers for layout-distribution tests, and a scripted walk to the goal."""

from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any, Callable

import gymnasium as gym
import numpy as np
import pytest

from rlbackdoors.envs import grid_engine as ge

# ----------------------------------------------------------------------------- engine vs reference


def ref_state(env, *extra) -> tuple:
    """``load_layout``'s arguments read off a reference env: full grid, agent, step count, ``extra``."""
    u = env.unwrapped
    return (u.grid.encode(), tuple(int(v) for v in u.agent_pos), int(u.agent_dir), int(u.step_count), *extra)


def place_random(env, rng: np.random.Generator, kinds=(ge.EMPTY,)) -> None:
    """Put the reference agent on a random cell whose object is in ``kinds``, facing a random way."""
    arr = env.grid.encode()
    free = np.argwhere(np.isin(arr[:, :, 0], kinds))
    x, y = free[rng.integers(len(free))]
    env.agent_pos = (int(x), int(y))
    env.agent_dir = int(rng.integers(4))


def place_facing(env, rng: np.random.Generator, groups) -> bool:
    """Put the reference agent on an empty cell next to a target, facing it: a group of target
    cells uniformly, then a cell of it, then a neighbour. False (agent untouched) if it has none."""
    arr = env.grid.encode()
    size = arr.shape[0]
    group = groups[rng.integers(len(groups))]
    tx, ty = group[rng.integers(len(group))]
    nbrs = [(tx - ge.DIR_DX[d], ty - ge.DIR_DY[d], d) for d in range(4)]
    nbrs = [(x, y, d) for x, y, d in nbrs if 0 <= x < size and 0 <= y < size and arr[x, y, 0] == ge.EMPTY]
    if not nbrs:
        return False
    x, y, d = nbrs[rng.integers(len(nbrs))]
    env.agent_pos, env.agent_dir = (int(x), int(y)), int(d)
    return True


@dataclass(frozen=True)
class Pairing:
    """How one world's engine is compared, step for step, with its reference env.

    ``ref_state(env)``: ``load_layout``'s arguments; ``ref_obs(env)``: the observation the env
    would return now; ``teleport(env, rng)``: move its agent somewhere interesting;
    ``check_fresh(eng, i, ref)``: check the engine's own autoreset layout in slot ``i``;
    ``obs_at(obs, i)`` / ``same(a, b)``: one env's observation out of a batch, and equality of two;
    ``obs_dtype``: the dtype (or dict of dtypes) of a batched observation; ``flags``: boolean info
    keys compared besides ``outcome`` and ``steps``.
    """

    ref_state: Callable
    ref_obs: Callable
    teleport: Callable
    check_fresh: Callable
    obs_at: Callable = lambda obs, i: obs[i]
    same: Callable = np.array_equal
    obs_dtype: Any = np.uint8
    flags: tuple[str, ...] = ()

    def load(self, ref, eng, i: int):
        """Load the reference's exact state into slot ``i``; both must show the same observation."""
        got = eng.load_layout(i, *self.ref_state(ref))
        assert self.same(self.ref_obs(ref), got)
        return got

    def place(self, ref, eng, pos, d, step_count=0, i: int = 0):
        """Put the reference agent at ``pos`` facing ``d`` at ``step_count`` and load it into slot ``i``."""
        u = ref.unwrapped
        u.agent_pos, u.agent_dir, u.step_count = pos, d, step_count
        return self.load(ref, eng, i)

    def reset_pair(self, refs, eng, seed: int):
        """Reset the engine (seed + 10_000) and reference ``i`` (seed + i), and load each
        reference's layout into engine slot ``i``; returns ``(refs, eng)``."""
        eng.reset(seed=seed + 10_000)
        for i, ref in enumerate(refs):
            o, _ = ref.reset(seed=seed + i)
            assert self.same(o, self.load(ref, eng, i))
        return refs, eng

    def compare(self, eng, out: tuple, i: int, ref_out: tuple) -> bool:
        """Assert that the engine's step ``out`` matches, for env ``i``, the reference's step
        ``ref_out`` (observation, reward, flags, outcome, steps, ``flags`` info); returns whether
        the episode ended."""
        obs, rew, term, trunc, info = out
        dtypes = {k: v.dtype for k, v in obs.items()} if isinstance(obs, dict) else obs.dtype
        assert dtypes == self.obs_dtype and rew.dtype == np.float64
        assert term.dtype == trunc.dtype == np.bool_ and all(info[k].dtype == np.bool_ for k in self.flags)
        assert info["outcome"].dtype == info["steps"].dtype == np.int64
        o, r, t1, t2, inf = ref_out
        done = t1 or t2
        assert self.same(o, self.obs_at(eng.final_obs if done else obs, i)), f"env {i}: observation differs"
        assert r == rew[i], f"env {i}: reward {rew[i]} != {r}"
        assert (t1, t2) == (term[i], trunc[i]), f"env {i}: done flags differ"
        assert inf["outcome"] == info["outcome"][i] and inf["steps"] == info["steps"][i], f"env {i}"
        for k in self.flags:
            assert inf[k] == info[k][i], f"env {i}: {k} differs"
        return done

    def step_both(self, refs, eng, actions, totals: Counter | None = None):
        """Step the engine and each reference env with ``actions``; assert identical outputs.

        Finished reference envs are reset and their fresh state is loaded into the engine slot
        (after the engine's own fresh layout there is checked). Returns the outcomes of the step.
        """
        out = eng.step(np.asarray(actions))
        for i, ref in enumerate(refs):
            ref_out = ref.step(int(actions[i]))
            done = self.compare(eng, out, i, ref_out)
            if totals is not None:
                totals[ref_out[4]["outcome"]] += 1
            if done:
                # the engine reset the slot itself: a fresh episode, obs is its first observation
                self.check_fresh(eng, i, ref)
                assert self.same(self.obs_at(out[0], i), self.obs_at(eng.observe(), i))
                o, _ = ref.reset()
                assert self.same(o, self.load(ref, eng, i))
        return out[4]["outcome"]

    def play(self, ref, eng, rng, steps: int, p, after_step: Callable | None = None) -> list[dict]:
        """Up to ``steps`` random actions (probabilities ``p``) on a lone reference env and engine
        slot 0, until the episode ends, with the same outputs at every step; ``after_step()`` runs
        after each step that did not end it. Returns the reference's infos."""
        infos = []
        for _ in range(steps):
            a = int(rng.choice(3, p=p))
            ref_out = ref.step(a)
            infos.append(ref_out[4])
            if self.compare(eng, eng.step(np.array([a])), 0, ref_out):
                break
            if after_step is not None:
                after_step()
        return infos

    def drive_teleporting(self, refs, eng, rng, steps: int, every: int) -> Counter:
        """Step both sides with forward-biased random actions; every ``every`` steps every
        reference agent is teleported and its state loaded into its engine slot."""
        totals = Counter()
        for t in range(steps):
            if t % every == 0:
                for i, ref in enumerate(refs):
                    self.teleport(ref, rng)
                    self.load(ref, eng, i)
            self.step_both(refs, eng, rng.choice(3, size=len(refs), p=[0.25, 0.25, 0.5]), totals)
        return totals


# ----------------------------------------------------------------------------- what every engine does alike


def check_common_errors(eng, trigger: str, agent_pos, wrong_size: int) -> None:
    """The errors every engine raises alike; ``eng`` has 3 envs and has not been reset.

    Step before reset, invalid actions (a rejected step changes nothing), bad action arrays,
    poisoned envs without a trigger, bad masks, max_steps, num_envs, render_mode and seeds, a
    ``wrong_size`` grid or a bad direction (``agent_pos`` is a valid cell) for a slot, a bad slot.
    """
    make = type(eng)
    with pytest.raises(RuntimeError, match="before reset"):
        eng.step(np.zeros(3, dtype=int))
    eng.reset(seed=0)
    before = [eng.layout(i) for i in range(3)]
    for bad in ([0, 3, 1], [0, -1, 1]):
        with pytest.raises(ValueError, match=r"Discrete\(3\) \(0 left, 1 right, 2 forward\)"):
            eng.step(np.array(bad))
    for i in range(3):  # a rejected step changes nothing
        g, *rest = eng.layout(i)
        assert np.array_equal(g, before[i][0]) and rest == list(before[i][1:])
    with pytest.raises(ValueError, match="integers"):
        eng.step(np.array([0.0, 1.5, 2.0]))
    with pytest.raises(ValueError, match="shape"):
        eng.step(np.array([0, 1]))
    with pytest.raises(ValueError, match="need a trigger"):
        make(2, poisoned=[True, False])
    with pytest.raises(ValueError, match="poisoned mask"):
        make(2, trigger=trigger, poisoned=[True])
    with pytest.raises(ValueError, match="max_steps"):
        make(2, max_steps=0)
    with pytest.raises(ValueError, match="num_envs"):
        make(0)
    with pytest.raises(ValueError, match="render_mode"):
        make(1, render_mode="rgb_array")
    with pytest.raises(ValueError, match="2 seeds for 3 envs"):
        eng.reset(seed=[1, 2])
    with pytest.raises(ValueError, match="non-negative"):
        eng.reset(seed=-1)
    with pytest.raises(ValueError, match="expected"):
        eng.load_layout(0, np.zeros((wrong_size, wrong_size, 3), np.uint8), agent_pos, 0)
    with pytest.raises(ValueError, match="agent_dir"):
        eng.load_layout(0, eng.layout(0)[0], agent_pos, 4)
    with pytest.raises(IndexError):
        eng.layout(3)


def run_trajectory(make: Callable, seed: int, steps: int, num: int) -> list:
    """Every array an engine ``make(num)`` returns over ``steps`` random steps after ``reset(seed)``."""
    eng = make(num)
    obs, _ = eng.reset(seed=seed)
    rng = np.random.default_rng(99)
    flat = lambda o: list(o.values()) if isinstance(o, dict) else [o]  # noqa: E731
    out = flat(obs)
    for _ in range(steps):
        obs, rew, term, trunc, info = eng.step(rng.integers(0, 3, size=num))
        out += [*flat(obs), rew, term, trunc, *info.values()]
    return out


def check_same_seed_same_trajectory(make: Callable, steps: int, num: int) -> None:
    """The same seed gives the very same arrays, another seed others."""
    a = run_trajectory(make, 5, steps, num)
    b = run_trajectory(make, 5, steps, num)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    c = run_trajectory(make, 6, steps, num)
    assert not all(np.array_equal(x, y) for x, y in zip(a, c))


def check_seed_i_is_seed_plus_i(make: Callable) -> None:
    """``reset(seed=s)`` lays env ``i`` out as a one-env ``reset(seed=s + i)`` and as the seed list
    ``[s, s + 1, ..]``; unseeded resets differ (with overwhelming probability over 8 slots)."""
    wide = make(4)
    wide.reset(seed=20)
    lst = make(4)
    lst.reset(seed=[20, 21, 22, 23])
    for i in range(4):
        one = make(1)
        one.reset(seed=20 + i)
        assert np.array_equal(one.layout(0)[0], wide.layout(i)[0]) and one.layout(0)[1:] == wide.layout(i)[1:]
        assert np.array_equal(lst.layout(i)[0], wide.layout(i)[0])
    x, y = make(8), make(8)
    x.reset()
    y.reset()
    assert any(not np.array_equal(x.layout(i)[0], y.layout(i)[0]) for i in range(8))


def check_make_vec(reference: type, engine: type, **kwargs) -> str:
    """Register ``reference`` with ``engine`` as its vector entry point (once), then
    ``gym.make_vec`` 6 envs with ``kwargs``: the engine itself, every env poisoned, 6 first views.
    Returns the env id."""
    env_id = f"rlbackdoors_enginetest/{engine.__name__}-v0"
    if env_id not in gym.registry:
        entry, vector_entry = (f"{cls.__module__}:{cls.__name__}" for cls in (reference, engine))
        gym.register(id=env_id, entry_point=entry, vector_entry_point=vector_entry)
    env = gym.make_vec(env_id, num_envs=6, render_mode=None, **kwargs)
    assert isinstance(env.unwrapped, engine) and env.num_envs == 6 and env.poisoned.all()
    obs, _ = env.reset(seed=0)
    assert (obs["image"] if isinstance(obs, dict) else obs).shape == (6, 7, 7, 3)
    env.close()
    return env_id


def check_first_step(eng) -> None:
    """A first step forward after reset: observations in the space, float rewards, bool flags, step 1."""
    out = eng.step(np.array([2] * eng.num_envs))
    assert eng.observation_space.contains(out[0])
    assert [x.dtype for x in out[1:4]] == [np.float64, np.bool_, np.bool_]
    assert out[4]["steps"].tolist() == [1] * eng.num_envs
    eng.close()


def copy_slot(eng):
    """After ``reset(seed=2)`` and 7 random steps of ``eng`` (3 envs), copy slot 0's state into
    slot 2 with ``load_layout(2, *layout(0))``: the copy is exact. Returns the state and the
    observation ``load_layout`` returned."""
    eng.reset(seed=2)
    rng = np.random.default_rng(2)
    for _ in range(7):
        eng.step(rng.integers(0, 3, size=3))
    state = eng.layout(0)
    obs = eng.load_layout(2, *state)
    assert all(np.array_equal(a, b) for a, b in zip(eng.layout(2), state))
    return state, obs


# ----------------------------------------------------------------------------- statistics and walks


def chi2_homogeneity(a: Counter, b: Counter) -> tuple[float, int]:
    """Two-sample chi-square statistic (equal totals) and its degrees of freedom."""
    keys = set(a) | set(b)
    stat = sum((a[k] - b[k]) ** 2 / (a[k] + b[k]) for k in keys)
    return stat, len(keys) - 1


def chi2_critical(df: int, z: float = 3.719) -> float:
    """Upper quantile of chi-square(df) by Wilson-Hilferty; z=3.719 is the 1e-4 normal tail."""
    return df * (1 - 2 / (9 * df) + z * math.sqrt(2 / (9 * df))) ** 3


def walk_to_goal(env, right: int = 1, forward: int = 2):
    """Follow a BFS path (around lava and walls) to the goal at (W-2, H-2) with right/forward
    actions on a MiniGrid-based env; return the last step's result."""
    start = tuple(int(v) for v in env.agent_pos)
    prev, todo = {start: None}, deque([start])
    while todo:
        cell = todo.popleft()
        for dx, dy in ((1, 0), (0, 1), (-1, 0), (0, -1)):
            nxt = (cell[0] + dx, cell[1] + dy)
            c = env.grid.get(*nxt)
            if nxt not in prev and (c is None or c.type == "goal"):
                prev[nxt] = cell
                todo.append(nxt)
    path, cell = [], (env.width - 2, env.height - 2)
    while cell != start:
        path.append(cell)
        cell = prev[cell]
    vec_to_dir = {(1, 0): 0, (0, 1): 1, (-1, 0): 2, (0, -1): 3}
    result = None
    for target in reversed(path):
        want = vec_to_dir[(target[0] - env.agent_pos[0], target[1] - env.agent_pos[1])]
        while env.agent_dir != want:
            result = env.step(right)
        result = env.step(forward)
    return result


# ----------------------------------------------------------------------------- kill -9 mid-run


def kill_after_first_checkpoint(cmd: list[str], folder, timeout: float = 120) -> None:
    """Start ``cmd`` (an ``rlbackdoors train`` writing ``folder``) and SIGKILL it once its first
    checkpoint is on disk; fails if it finished or died before writing one."""
    import os
    import signal
    import subprocess
    import time

    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    checkpoint = folder / "checkpoint.pt"
    deadline = time.time() + timeout
    while not checkpoint.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert checkpoint.exists(), "the run finished or failed before writing a checkpoint"
    assert not (folder / "metrics.json").exists()


def assert_seam_resumes(a, b, actions, cut: int, *also: str) -> None:
    """Step seam ``a`` through ``actions[:cut]``, load its state into ``b`` (through torch's
    weights-only reader, as a checkpoint), then step both through the rest: the same frames,
    rewards and ``also`` attributes (``triggered``, ``in_near``) step for step, the same budget."""
    import io

    import numpy as np
    import torch

    for t in range(cut):
        a.step(actions[t])
    buffer = io.BytesIO()
    torch.save(a.state_dict(), buffer)
    buffer.seek(0)
    b.load_state_dict(torch.load(buffer, weights_only=True))
    for t in range(cut, len(actions)):
        oa, ra, *_ = a.step(actions[t])
        ob, rb, *_ = b.step(actions[t])
        np.testing.assert_array_equal(oa["image"], ob["image"])
        np.testing.assert_array_equal(ra, rb)
        for name in also:
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert a.budget_used() == b.budget_used()


def killed_run_matches_whole(tmp_path, cfg) -> tuple[dict, dict]:
    """Train ``cfg`` (a RunConfig) once uninterrupted, and once through the CLI SIGKILLed after its
    first checkpoint and then resumed: the same model.pt bytes. Returns both metrics.json. The
    uninterrupted run and the resume run in this process (the run's threads and generators come
    from its config, so the CLI gives the same bytes); only the killed run needs a process."""
    import json
    import sys

    from rlbackdoors.folder import ModelFolder
    from rlbackdoors.train import train

    cfg_path = tmp_path / "cfg.json"
    cfg_path.write_text(cfg.to_json())
    cmd = [sys.executable, "-m", "rlbackdoors.cli", "train", "--config", str(cfg_path), "--quiet"]
    train(cfg, tmp_path / "whole", progress=False)
    kill_after_first_checkpoint(cmd + ["--out", str(tmp_path / "cut")], tmp_path / "cut")
    assert 1 <= len(ModelFolder(tmp_path / "cut").read_log()) < 8
    train(cfg, tmp_path / "cut", progress=False)
    assert (tmp_path / "whole" / "model.pt").read_bytes() == (tmp_path / "cut" / "model.pt").read_bytes()
    whole, cut = (json.loads((tmp_path / d / "metrics.json").read_text()) for d in ("whole", "cut"))
    return whole, cut


def model_weights(folder) -> dict:
    """A model folder's model.pt, read as data."""
    import torch

    return torch.load(folder / "model.pt", weights_only=True)


def same_weights(a, b) -> bool:
    """Two model folders' model.pt hold the same tensors, bit for bit."""
    import torch

    wa, wb = model_weights(a), model_weights(b)
    return wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)


def stopped_and_resumed_matches(cfg, whole, cut) -> list:
    """Train ``cfg`` into ``cut``, stopped (KeyboardInterrupt) after its first evaluation, then
    run again: the model.pt and log (but its timings) of the uninterrupted run already in
    ``whole``, bit for bit. Returns the frames logged before the resume."""
    import json

    import pytest

    from rlbackdoors.folder import ModelFolder
    from rlbackdoors.train import train

    def stop_at_first(row):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(cfg, cut, progress=False, after_eval=stop_at_first)
    first = [r["frames"] for r in ModelFolder(cut).read_log()]
    train(cfg, cut, progress=False)
    assert same_weights(whole, cut)
    drop = ("wall_time_s", "fps")
    rows = [json.dumps([{k: v for k, v in r.items() if k not in drop} for r in ModelFolder(side).read_log()]) for side in (whole, cut)]
    assert rows[0] == rows[1]  # (as text: a NaN training return is no number)
    return first


def assert_step_matches(step, out, t: int, where: str, image=None) -> None:
    """A JAX grid step's outputs (``out``: a rollout's stacked :class:`StepOut`, step ``t``) are
    the numba engine's ``step`` (its 5-tuple) byte for byte: the view (``image``, where the
    observation is a dict), reward as float32, termination, truncation, outcome, episode step."""
    obs, reward, terminated, truncated, info = step
    pairs = {
        "obs": (obs if image is None else image, out.obs[t]),
        "reward": (reward.astype(np.float32), out.reward[t]),
        "terminated": (terminated, out.terminated[t]),
        "truncated": (truncated, out.truncated[t]),
        "outcome": (info["outcome"].astype(np.int32), out.outcome[t]),
        "steps": (info["steps"].astype(np.int32), out.steps[t]),
    }
    for name, (want, got) in pairs.items():
        got = np.asarray(got)
        assert got.dtype == want.dtype and np.array_equal(got, want), f"{where}: {name} differs at {np.argwhere(got != want)[:3].tolist()}"


def run_block(host, rollout, slots, params, acts, depth: int) -> tuple:
    """One compiled block of ``acts`` from ``slots`` through ``host.run`` (a starved queue runs
    again deeper): the slots after it, its stacked outputs, and how many times it ran again."""
    tries = []

    def run(layouts):
        tries.append(1)
        return rollout(slots, layouts, params, acts)

    after, out = host.run(run, depth)
    return after, out, len(tries) - 1
