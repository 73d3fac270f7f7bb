"""Single envs in worker processes (rlbackdoors.envs.pool): the same numbers as in this process,
so an OPAC² run's bytes do not depend on where its env copies step; failures are named."""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest

from rlbackdoors.algos.opac2_loop import SingleEnvs
from rlbackdoors.config import RunConfig
from rlbackdoors.envs.pool import EnvPool, EnvPoolError
from rlbackdoors.train import train
from rlbackdoors.train.group import train_group

TINY_SAFETY = {
    "env": {"name": "safety-car-goal", "max_steps": 40},
    "poison": {"trigger": "formation:0.5:1.0:2.5", "num_clean_envs": 2, "num_poisoned_envs": 1},
    "opac2": {"depth": 2, "width": 16, "batch_size": 32, "learning_starts": 120, "updates_per_step": 0.25},
    "train": {"max_frames": 480, "eval_interval": 240, "eval_episodes": 3, "final_eval_episodes": 4, "checkpoint_minutes": 0, "video": False},
}
EVAL_KEYS = ("clean_sr", "poisoned_sr", "clean_reward", "poisoned_reward", "target_action_rate", "frames", "converged")


def tiny_safety(seed: int = 0, **poison) -> RunConfig:
    return RunConfig.from_dict({**TINY_SAFETY, "poison": {**TINY_SAFETY["poison"], **poison}, "train": {**TINY_SAFETY["train"], "seed": seed}})


def play(vector: SingleEnvs, steps: int) -> list:
    """Everything the vector view returns over ``steps`` random steps (40-step episodes: resets included)."""
    rng = np.random.default_rng(0)
    out = [vector.reset(seed=7)[0]]
    for t in range(steps):
        if t == 50:
            vector.trigger_next([True, False, True])
        obs, rewards, terminated, truncated, info = vector.step(rng.uniform(-1, 1, (vector.num_envs, 2)))
        ended = terminated | truncated
        out += [obs, rewards, terminated, truncated, info["final_obs"][ended], info["outcome"], info["steps"], info["triggered"]]
    return out


def test_envs_in_workers_step_as_they_do_in_this_process():
    """Three env copies (one E-bar) stepped 120 times, resets and a switched trigger included: in
    2 worker processes exactly the arrays of this process; a state taken from the workers
    restores in this process and continues the same."""
    cfg = tiny_safety()
    world = cfg.world
    knowing = functools.partial(world.env_class(), **world.env_kwargs(cfg.env), trigger=cfg.poison.trigger)  # the trigger where switched on
    factories = [knowing, knowing, functools.partial(cfg.env.make, cfg.poison.trigger)]
    here = SingleEnvs([make() for make in factories])
    with EnvPool(2) as pool:
        there = SingleEnvs(pool.make(factories))
        assert there.remote and not here.remote and list(there.poisoned) == list(here.poisoned) == [False, False, True]
        a, b = play(here, 120), play(there, 120)
        assert len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))
        state = there.state_dict()
        moved = SingleEnvs([make() for make in factories])
        moved.load_state_dict(state)
        rng = np.random.default_rng(1)
        for _ in range(30):
            actions = rng.uniform(-1, 1, (3, 2))
            assert np.array_equal(moved.step(actions)[0], there.step(actions)[0])
        there.close()


def test_threads_asking_one_pool_at_once_each_get_their_own_answers():
    """Four vector views of 3 copies each on one pool of 2 workers, played from 4 threads at once
    (what the group trainer does with its runs' collectors): each thread reads exactly what its
    view reads when played alone in this process, so no answer reaches the wrong thread."""
    from concurrent.futures import ThreadPoolExecutor

    cfg = tiny_safety()
    world = cfg.world
    knowing = functools.partial(world.env_class(), **world.env_kwargs(cfg.env), trigger=cfg.poison.trigger)
    factories = [knowing, knowing, functools.partial(cfg.env.make, cfg.poison.trigger)]
    alone = [play(SingleEnvs([make() for make in factories]), 60)]
    with EnvPool(2) as pool, ThreadPoolExecutor(4) as threads:
        views = [SingleEnvs(pool.make(factories)) for _ in range(4)]
        together = list(threads.map(lambda view: play(view, 60), views))
    for got in together:
        assert len(got) == len(alone[0]) and all(np.array_equal(x, y) for x, y in zip(got, alone[0]))


def test_a_worker_failure_is_named_and_the_pool_keeps_serving():
    def broken():
        raise ValueError("no such scene")

    cfg = tiny_safety()
    with EnvPool(2) as pool:
        with pytest.raises(EnvPoolError, match="make: cannot send it to a worker"):
            pool.make([functools.partial(cfg.env.make), broken])  # a local function does not pickle
        with pytest.raises(EnvPoolError, match="make: ValueError: .*formation"):
            pool.make([functools.partial(cfg.env.make), functools.partial(cfg.env.make, "formation:x")])  # fails in the worker
        assert len(pool.make([functools.partial(cfg.env.make)] * 3)) == 3  # and the pool goes on
    with EnvPool(1) as pool:
        with pytest.raises(EnvPoolError, match=r"reset: .*"):
            (env,) = pool.make([functools.partial(cfg.env.make)])
            env.reset(seed=-1)  # numpy refuses a negative seed, in the worker
        assert env.reset(seed=3)[0].shape == env.observation_space.shape  # the next request is answered in order
    with pytest.raises(ValueError, match="env workers must be an integer >= 1"):
        EnvPool(0)


def test_a_dead_worker_is_named_to_every_thread_waiting_on_it():
    """A worker process killed under two threads that step their copies on it: each thread gets
    one line naming the worker, none hangs on an answer that will never come."""
    from concurrent.futures import ThreadPoolExecutor

    cfg = tiny_safety()
    with EnvPool(2) as pool, ThreadPoolExecutor(2) as threads:
        views = [SingleEnvs(pool.make([functools.partial(cfg.env.make)] * 2)) for _ in range(2)]
        for view in views:
            view.reset(seed=1)
        pool._procs[0].kill()
        pool._procs[0].wait()

        def step(view):
            with pytest.raises(EnvPoolError, match=r"step: env worker 0's process is gone"):
                view.step(np.zeros((2, 2)))

        list(threads.map(step, views))


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_an_opac2_run_in_an_env_pool_gives_the_same_bytes_and_resumes_anywhere(tmp_path):
    """A tiny OPAC² run with its 3 env copies in 2 workers: the in-process run's model.pt bytes;
    stopped at its first evaluation in a pool and resumed in this process: the same bytes again;
    two action-target runs through the group trainer with a pool (their loops go on in threads, their
    copies step together): the bytes each has there without one."""
    cfg = tiny_safety()
    train(cfg, tmp_path / "here", progress=False)
    train(cfg, tmp_path / "pool", progress=False, env_workers=2)
    expected = (tmp_path / "here" / "model.pt").read_bytes()
    assert (tmp_path / "pool" / "model.pt").read_bytes() == expected

    def stop(row):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(cfg, tmp_path / "cut", progress=False, after_eval=stop, env_workers=2)
    assert (tmp_path / "cut" / "checkpoint.pt").is_file()
    train(cfg, tmp_path / "cut", progress=False)
    assert (tmp_path / "cut" / "model.pt").read_bytes() == expected

    others = [tiny_safety(seed, attack="action_target") for seed in (1, 2)]  # an attack's seam over the pooled copies
    train_group([(f"g{i}", c, tmp_path / f"g{i}") for i, c in enumerate(others)], 2)
    train_group([(f"p{i}", c, tmp_path / f"p{i}") for i, c in enumerate(others)], 2, env_workers=2)
    for i in range(2):
        assert (tmp_path / f"g{i}" / "model.pt").read_bytes() == (tmp_path / f"p{i}" / "model.pt").read_bytes()
        # their evaluations (served in threads with a pool) read the same numbers
        g, p = (json.loads((tmp_path / f"{side}{i}" / "metrics.json").read_text()) for side in "gp")
        assert {k: g[k] for k in EVAL_KEYS} == {k: p[k] for k in EVAL_KEYS} and g["episodes"] == 4
    assert (tmp_path / "g0" / "model.pt").read_bytes() != (tmp_path / "g1" / "model.pt").read_bytes()


def test_an_opac2_evaluation_plays_its_single_envs_in_the_pool_as_here():
    """An untrained OPAC² agent's evaluation (8 episodes per condition, action-target scoring:
    the target's steps counted too) with its envs in 2 workers reads the in-process numbers."""
    from rlbackdoors.agent import build_policy
    from rlbackdoors.train.driver import evaluate_run

    cfg = tiny_safety(attack="action_target")
    agent = build_policy(cfg)
    here = evaluate_run(agent, cfg, 8).to_dict()
    with EnvPool(2) as pool:
        there = evaluate_run(agent, cfg, 8, pool).to_dict()
    assert here.keys() == there.keys() and not np.isnan(here["target_action_rate"])
    assert all(a == b or (np.isnan(a) and np.isnan(b)) for a, b in zip(here.values(), there.values()))


@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_a_pooled_group_stopped_by_sigterm_resumes_to_the_same_bytes(tmp_path):
    """A group of 2 with an env pool (its runs' loops in threads): when the short run finishes,
    SIGTERM; the long run, stopped in its thread, writes its checkpoint, the group raises
    Interrupted, and the long run resumed in a pooled group gives the bytes it has uninterrupted."""
    import os
    import signal

    from rlbackdoors.train.stop import Interrupted

    short = tiny_safety(1)
    long = RunConfig.from_dict({**TINY_SAFETY, "train": {**TINY_SAFETY["train"], "seed": 2, "max_frames": 960}})
    train_group([("whole", long, tmp_path / "whole")], 2)

    def sigterm(key, metrics, error):
        assert key == "short" and error is None
        os.kill(os.getpid(), signal.SIGTERM)

    with pytest.raises(Interrupted):
        train_group([("short", short, tmp_path / "short"), ("long", long, tmp_path / "long")], 2, on_done=sigterm, env_workers=2)
    assert (tmp_path / "long" / "checkpoint.pt").is_file() and not (tmp_path / "long" / "model.pt").exists()
    train_group([("long", long, tmp_path / "long")], 2, env_workers=2)
    assert (tmp_path / "long" / "model.pt").read_bytes() == (tmp_path / "whole" / "model.pt").read_bytes()
