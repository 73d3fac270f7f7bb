"""Experience collection for OPAC²: step env copies of several kinds into their replay buffers.

Plain single envs stepped in a Python loop (:class:`SingleEnvs`) rather than a gymnasium vector
env: the kinds (clean, poisoned) must land in separate buffers, and an env's own autoreset would
hide the true last observation of a truncated episode, which the Q target needs (a timeout is not
a terminal state, so ``done`` is ``terminated`` only and ``next_obs`` is the real next state).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from rlbackdoors.algos.opac2 import MultitaskReplay
from rlbackdoors.envs.pool import RemoteEnv, each

ActFn = Callable[[np.ndarray], np.ndarray]  # observations (n, O) -> actions (n, A)


@dataclass
class Episode:
    """One finished episode: which kind of env, its return, length and ``info["outcome"]``."""

    kind: str
    ret: float
    length: int
    outcome: int
    triggered: bool


class SingleEnvs:
    """Single envs seen as one vector env (SAME_STEP autoreset) that keeps each episode's true last
    observation in ``info["final_obs"]``: what an attack's collection seam
    (:class:`~rlbackdoors.attacks.seam.AttackSeam`) wraps, so OPAC² is poisoned by the same seam as PPO.

    Env ``i`` is reset once with ``seed + i``; later resets continue that env's own random stream.
    """

    def __init__(self, envs: Sequence):
        self.envs = list(envs)
        self.num_envs = len(self.envs)
        self.single_observation_space = self.envs[0].observation_space
        self.single_action_space = self.envs[0].action_space
        # copies held by an env pool's workers (rlbackdoors.envs.pool) are asked all at once
        self.remote = all(isinstance(env, RemoteEnv) for env in self.envs)

    def _each(self, name: str, args: Sequence) -> list:
        """``env.name(*args[i])`` for every env i: in parallel where the pool's workers hold them."""
        return each(self.envs, "call", [(name, a) for a in args])

    def reset(self, *, seed: int = 0, options=None):
        return np.stack(each(self.envs, "reset", [seed + i for i in range(self.num_envs)])), {}

    def step(self, actions: np.ndarray):
        n = self.num_envs
        obs = np.empty((n, *self.single_observation_space.shape), dtype=self.single_observation_space.dtype)
        final = np.empty_like(obs)
        rewards, terminated, truncated = np.empty(n), np.zeros(n, bool), np.zeros(n, bool)
        outcome, steps, triggered = np.zeros(n, np.int64), np.zeros(n, np.int64), np.zeros(n, bool)
        for i, (o, r, term, trunc, last, out, length, trig) in enumerate(each(self.envs, "step", list(actions))):
            obs[i], rewards[i], terminated[i], truncated[i] = o, r, term, trunc
            if last is not None:
                final[i], outcome[i], steps[i], triggered[i] = last, out, length, trig
        return obs, rewards, terminated, truncated, {"final_obs": final, "outcome": outcome, "steps": steps, "triggered": triggered}

    def trigger_next(self, mask) -> None:
        self._each("trigger_next", [(bool(on),) for on in mask])

    def near_next(self, mask) -> None:
        self._each("near_next", [(bool(on),) for on in mask])

    @property
    def poisoned(self) -> np.ndarray:
        """The copies that pay R-bar themselves (the env mix's E-bar copies)."""
        return np.array([bool(getattr(env, "poisoned", False)) for env in self.envs])

    def state_dict(self) -> dict:
        return {"envs": self._each("state_dict", [()] * self.num_envs)}

    def load_state_dict(self, state: dict) -> None:
        from rlbackdoors.state import StateError

        if not isinstance(state, dict) or not isinstance(state.get("envs"), list) or len(state["envs"]) != self.num_envs:
            raise StateError(f"collector state does not hold {self.num_envs} envs")
        self._each("load_state_dict", [(env_state,) for env_state in state["envs"]])

    def close(self) -> None:
        for env in self.envs:
            env.close()


class Collector:
    """Steps ``envs`` in lockstep; env ``i`` writes into ``replay[kinds[i]]`` and resets itself.

    Env ``i`` is reset once with ``seed + i``; later resets continue that env's own random
    stream, so a collector is reproducible from one seed. ``seam``: wraps the envs' vector view
    (:class:`SingleEnvs`) in an attack's collection seam, whose rewards (and the actions it says
    ran) are what the replay stores.
    """

    def __init__(self, envs: Sequence, kinds: Sequence[str], seed: int, seam: Callable | None = None):
        if len(envs) != len(kinds) or not envs:
            raise ValueError(f"need one kind per env and at least one env, got {len(envs)} envs and {len(kinds)} kinds")
        self.envs, self.kinds = list(envs), list(kinds)
        self.vector = SingleEnvs(self.envs) if seam is None else seam(SingleEnvs(self.envs))
        self.obs = self.vector.reset(seed=seed)[0]
        self.returns = np.zeros(len(self.envs))
        self.frames = 0  # transitions collected, all envs together
        self._rows = {kind: np.flatnonzero(np.asarray(self.kinds) == kind) for kind in dict.fromkeys(self.kinds)}

    def state_dict(self) -> dict:
        """Observations, running returns, frame count and every env's state (and the seam's), as plain data."""
        from rlbackdoors.state import snapshot

        mine = snapshot(self, skip=("envs", "vector"))
        if isinstance(self.vector, SingleEnvs):
            return {"collector": mine, **self.vector.state_dict()}
        return {"collector": mine, "seam": self.vector.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        from rlbackdoors.state import StateError, restore

        if not isinstance(state, dict):
            raise StateError("collector state is not a dict")
        if isinstance(self.vector, SingleEnvs):
            self.vector.load_state_dict(state)
        elif "seam" not in state:
            raise StateError("the collector state was not written by this attack's collection")
        else:
            self.vector.load_state_dict(state["seam"])
        restore(self, state["collector"], "Collector", skip=("envs", "vector"))

    def collect(self, replay: MultitaskReplay, act_fn: ActFn, steps: int) -> list[Episode]:
        """``steps`` steps of every env (``steps * len(envs)`` frames); the episodes that ended."""
        from rlbackdoors.attacks.seam import EXECUTED_ACTIONS

        unknown = sorted(set(self.kinds) - set(replay.buffers))
        if unknown:
            raise ValueError(f"env kind {unknown[0]!r} has no replay buffer (buffers: {sorted(replay.buffers)})")
        finished = []
        n = len(self.envs)
        for _ in range(steps):
            actions = np.asarray(act_fn(self.obs))
            obs, rewards, term, trunc, info = self.vector.step(actions)
            actions = np.asarray(info.get(EXECUTED_ACTIONS, actions))
            rewards, terminated = np.asarray(rewards, np.float32), np.asarray(term, np.float32)
            ended = np.asarray(term | trunc, bool)
            next_obs = np.where(ended[:, None], info["final_obs"], obs)  # the true next state, also of a finished episode
            self.returns += rewards
            for i in np.flatnonzero(ended):
                finished.append(Episode(self.kinds[i], float(self.returns[i]), int(info["steps"][i]), int(info["outcome"][i]), bool(info["triggered"][i])))
                self.returns[i] = 0.0
            for kind, rows in self._rows.items():
                replay[kind].add_batch(self.obs[rows], actions[rows], rewards[rows], next_obs[rows], terminated[rows])
            self.obs = obs
            self.frames += n
        return finished
