"""Env-speed benchmark of Safety Car Goal against its own physics floor, in one process."""

from __future__ import annotations

import time

import numpy as np

from rlbackdoors.bench.machine import machine_info
from rlbackdoors.bench.timing import steps_per_second


def _bench_env(seconds: float, num_cubes: int, seed: int) -> tuple[float, int, float]:
    from rlbackdoors.envs.safety_car import SafetyCarGoalEnv

    env = SafetyCarGoalEnv(num_cubes=num_cubes)
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    env.step(rng.uniform(-1.0, 1.0, 2))  # load the numba cache outside the clock
    return steps_per_second(env, lambda: rng.uniform(-1.0, 1.0, 2), seconds)


def _bench_physics(seconds: float, num_cubes: int, seed: int) -> tuple[float, int, float]:
    """``mj_step`` with the env's frame skip on the same compiled model: what no env can beat."""
    import mujoco

    from rlbackdoors.envs.safety_car import SafetyCarGoalEnv

    env = SafetyCarGoalEnv(num_cubes=num_cubes)
    env.reset(seed=seed)  # a placed scene, so contacts and solver work match the env's
    model, data, substeps = env.model, env.data, env.substeps
    rng = np.random.default_rng(seed)
    steps = 0
    start = time.perf_counter()
    while True:
        for _ in range(64):
            data.ctrl[:] = rng.uniform(-1.0, 1.0, 2)
            mujoco.mj_step(model, data, substeps)
        steps += 64
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            return steps / elapsed, steps, elapsed


def bench_safety(seconds: float = 3.0, num_envs: int = 1, num_cubes: int = 2) -> dict:  # World.bench of this world
    """Env steps per second of :class:`SafetyCarGoalEnv` vs a bare ``mj_step`` loop of its model.

    Both run about ``seconds`` of wall time in this process on one thread, with uniform random
    actions drawn with numpy each step (counted in both). The env is the class itself, not
    ``gymnasium.make`` (whose checker wrappers add their own overhead); finished episodes
    reset. The floor steps the same compiled model with the same frame skip and nothing else:
    no wander, no forward pass for the sensors, no lidar, no reward.
    """
    if seconds <= 0:
        raise ValueError(f"seconds={seconds!r} must be positive")
    seed = 0
    env_sps, env_steps, env_time = _bench_env(seconds, num_cubes, seed)
    floor_sps, floor_steps, floor_time = _bench_physics(seconds, num_cubes, seed)
    from rlbackdoors.envs.safety_car_model import CONTROL_DT, DEFAULT_SUBSTEPS

    return {
        "summary": f"{num_cubes} cubes: env {env_sps:,.0f} steps/s, plain mujoco loop {floor_sps:,.0f} steps/s, ratio {env_sps / floor_sps:.2f}",
        "env_steps_per_s": env_sps,
        "physics_steps_per_s": floor_sps,
        "ratio_to_physics": env_sps / floor_sps,
        "num_cubes": int(num_cubes),
        "substeps": DEFAULT_SUBSTEPS,
        "timestep": CONTROL_DT / DEFAULT_SUBSTEPS,
        "env_steps": env_steps,
        "env_seconds": env_time,
        "physics_steps": floor_steps,
        "physics_seconds": floor_time,
        "machine": machine_info(),
    }
