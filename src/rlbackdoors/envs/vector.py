"""The vector-env contract the trainer and evaluator rely on, and its MiniGrid-backed implementation.

Every engine (this reference one, the batched one) returns, per step:
``obs`` (B, ...) with finished envs already reset (SAME_STEP autoreset, as torch-ac),
``reward``, ``terminated``, ``truncated`` of the step just taken, and
``info = {"outcome": int[B], "steps": int[B]}`` describing that same step (not the
reset), so a finished episode's outcome is read directly off ``info["outcome"]``.
``poisoned`` (bool[B]) says which envs are E-bar copies of the poisoning mix.
"""

from __future__ import annotations

from typing import Callable, Sequence

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space


class ReferenceVectorEnv(VectorEnv):
    """Steps a list of single (MiniGrid-based) envs in this process, one after another.

    Deliberately simple: it is the ground truth the batched engine is tested against,
    and the ``--engine minigrid`` path of training.
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]], poisoned: Sequence[bool] | None = None):
        self.envs = [fn() for fn in env_fns]
        self.num_envs = len(self.envs)
        if self.num_envs == 0:
            raise ValueError("a vector env needs at least one env")
        self.single_observation_space = self.envs[0].observation_space
        self.single_action_space = self.envs[0].action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        if poisoned is None:
            poisoned = [bool(getattr(e.unwrapped, "poisoned", False)) for e in self.envs]
        self.poisoned = np.asarray(poisoned, dtype=bool)
        if self.poisoned.shape != (self.num_envs,):
            raise ValueError(f"poisoned mask has shape {self.poisoned.shape}, expected ({self.num_envs},)")

    @property
    def memory_target_classes(self) -> int | None:
        """Worlds whose envs say what a recurrent agent must remember (``memory_target``)."""
        return getattr(self.envs[0].unwrapped, "memory_target_classes", None)

    def memory_targets(self) -> np.ndarray:
        return np.array([getattr(env.unwrapped, "memory_target")() for env in self.envs], dtype=np.int64)

    def reset(self, *, seed: int | Sequence[int] | None = None, options: dict | None = None):
        if seed is None or isinstance(seed, (int, np.integer)):
            seeds = [None if seed is None else int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"got {len(seeds)} seeds for {self.num_envs} envs")
        pairs = [env.reset(seed=seeds[i], options=options) for i, env in enumerate(self.envs)]
        return stack_obs([o for o, _ in pairs]), stack_info([i for _, i in pairs])

    def step(self, actions):
        actions = np.asarray(actions)
        rewards = np.zeros(self.num_envs, dtype=np.float64)
        terminated = np.zeros(self.num_envs, dtype=bool)
        truncated = np.zeros(self.num_envs, dtype=bool)
        observations, infos = [], []
        for i, env in enumerate(self.envs):
            obs, rewards[i], terminated[i], truncated[i], info = env.step(actions[i])
            if terminated[i] or truncated[i]:
                obs, _ = env.reset()
            observations.append(obs)
            infos.append(info)
        return stack_obs(observations), rewards, terminated, truncated, stack_info(infos)

    def state_dict(self) -> dict:
        """Every env's changing state (grid, agent, step count, RNG) as plain data: a checkpoint."""
        from rlbackdoors.state import snapshot

        return {"vector": snapshot(self), "envs": [snapshot(env.unwrapped) for env in self.envs]}

    def load_state_dict(self, state: dict) -> None:
        """Put a :meth:`state_dict` of a vector env built with the same arguments back."""
        from rlbackdoors.state import StateError, restore

        if not isinstance(state, dict) or not isinstance(state.get("envs"), list) or len(state["envs"]) != self.num_envs:
            raise StateError(f"vector env state does not hold {self.num_envs} envs")
        restore(self, state.get("vector"))
        for i, (env, env_state) in enumerate(zip(self.envs, state["envs"])):
            restore(env.unwrapped, env_state, f"env {i}")

    def close_extras(self, **kwargs):
        for env in self.envs:
            env.close()


def stack_obs(observations: list):
    """Batch single-env observations: arrays stack, dict observations stack per key."""
    if isinstance(observations[0], dict):
        return {k: np.stack([np.asarray(o[k]) for o in observations]) for k in observations[0]}
    return np.stack(observations)


def stack_info(infos: list[dict]) -> dict:
    """Batch the scalar info entries (outcome, steps and any per-env flag) into arrays."""
    keys = [k for k, v in infos[0].items() if np.isscalar(v) or isinstance(v, (bool, np.bool_))]
    out = {k: np.asarray([info.get(k, 0) for info in infos]) for k in keys}
    for k in ("outcome", "steps"):
        out[k] = np.asarray([int(info.get(k, 0)) for info in infos], dtype=np.int64)
    return out
