"""Env-speed benchmark: the batched numba LavaWorld against Farama MiniGrid, in one process."""

from __future__ import annotations

import time

import numpy as np

from rlbackdoors.bench.machine import machine_info
from rlbackdoors.bench.timing import steps_per_second

MINIGRID_ID = "MiniGrid-LavaCrossingS9N1-v0"


def _bench_batched(seconds: float, num_envs: int, seed: int) -> tuple[float, int, float]:
    from rlbackdoors.envs.lavaworld_batched import BatchedLavaWorld

    env = BatchedLavaWorld(num_envs, size=9, num_crossings=1)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    env.step(rng.integers(0, 3, size=num_envs))  # compile / load the numba cache outside the clock
    steps = 0
    start = time.perf_counter()
    while True:
        for _ in range(16):
            env.step(rng.integers(0, 3, size=num_envs))
        steps += 16 * num_envs
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return steps / elapsed, steps, elapsed


def _bench_minigrid(seconds: float, seed: int) -> tuple[float, int, float]:
    import gymnasium as gym
    import minigrid  # noqa: F401  (registers the MiniGrid ids)

    env = gym.make(MINIGRID_ID)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    return steps_per_second(env, lambda: int(rng.integers(0, 3)), seconds)


def bench_env(seconds: float = 3.0, num_envs: int = 256) -> dict:  # World.bench of this world
    """Env steps per second of :class:`BatchedLavaWorld` vs MiniGrid's LavaCrossingS9N1.

    Each engine runs for about ``seconds`` of wall time (so the call takes about twice that,
    plus numba loading), random actions in 0..2, finished episodes reset: the batched engine
    steps ``num_envs`` envs per call (SAME_STEP autoreset, inside numba; the random actions
    are drawn with numpy each step and counted in its time), MiniGrid one env built by
    ``gymnasium.make`` (with gymnasium's default wrappers), reset by hand on done. Single
    thread, same process, so the ratio is a fair like-for-like on this machine.
    """
    if seconds <= 0:
        raise ValueError(f"seconds={seconds!r} must be positive")
    if num_envs < 1:
        raise ValueError(f"num_envs={num_envs!r} must be positive")
    seed = 0
    batched_sps, batched_steps, batched_time = _bench_batched(seconds, int(num_envs), seed)
    minigrid_sps, minigrid_steps, minigrid_time = _bench_minigrid(seconds, seed)
    return {
        "summary": f"env steps/s: batched {batched_sps:,.0f} (B={num_envs}), Farama MiniGrid {minigrid_sps:,.0f}, ratio {batched_sps / minigrid_sps:.0f}x",
        "batched_steps_per_s": batched_sps,
        "minigrid_steps_per_s": minigrid_sps,
        "ratio": batched_sps / minigrid_sps,
        "num_envs": int(num_envs),
        "batched_steps": batched_steps,
        "batched_seconds": batched_time,
        "minigrid_steps": minigrid_steps,
        "minigrid_seconds": minigrid_time,
        "minigrid_env": MINIGRID_ID,
        "machine": machine_info(),
    }
