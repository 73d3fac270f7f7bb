"""Experience collection for OPAC²: step env copies of several kinds into their replay buffers.

Plain single envs stepped in a Python loop rather than a gymnasium vector env: the kinds
(clean, poisoned) must land in separate buffers, and an env's own autoreset would hide the
true last observation of a truncated episode, which the Q target needs (a timeout is not a
terminal state, so ``done`` is ``terminated`` only and ``next_obs`` is the real next state).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from rlbackdoors.algos.opac2 import MultitaskReplay

ActFn = Callable[[np.ndarray], np.ndarray]  # observations (n, O) -> actions (n, A)


@dataclass
class Episode:
    """One finished episode: which kind of env, its return, length and ``info["outcome"]``."""

    kind: str
    ret: float
    length: int
    outcome: int
    triggered: bool


class Collector:
    """Steps ``envs`` in lockstep; env ``i`` writes into ``replay[kinds[i]]`` and resets itself.

    Env ``i`` is reset once with ``seed + i``; later resets continue that env's own random
    stream, so a collector is reproducible from one seed.
    """

    def __init__(self, envs: Sequence, kinds: Sequence[str], seed: int):
        if len(envs) != len(kinds) or not envs:
            raise ValueError(f"need one kind per env and at least one env, got {len(envs)} envs and {len(kinds)} kinds")
        self.envs, self.kinds = list(envs), list(kinds)
        self.obs = np.stack([env.reset(seed=seed + i)[0] for i, env in enumerate(self.envs)])
        self.returns = np.zeros(len(self.envs))
        self.frames = 0  # transitions collected, all envs together
        self._rows = {kind: np.flatnonzero(np.asarray(self.kinds) == kind) for kind in dict.fromkeys(self.kinds)}

    def state_dict(self) -> dict:
        """Observations, running returns, frame count and every env's state, as plain data."""
        from rlbackdoors.state import snapshot

        return {"collector": snapshot(self, skip=("envs",)), "envs": [env.state_dict() for env in self.envs]}

    def load_state_dict(self, state: dict) -> None:
        from rlbackdoors.state import StateError, restore

        if not isinstance(state.get("envs"), list) or len(state["envs"]) != len(self.envs):
            raise StateError(f"collector state does not hold {len(self.envs)} envs")
        restore(self, state["collector"], "Collector", skip=("envs",))
        for env, env_state in zip(self.envs, state["envs"]):
            env.load_state_dict(env_state)

    def collect(self, replay: MultitaskReplay, act_fn: ActFn, steps: int) -> list[Episode]:
        """``steps`` steps of every env (``steps * len(envs)`` frames); the episodes that ended."""
        unknown = sorted(set(self.kinds) - set(replay.buffers))
        if unknown:
            raise ValueError(f"env kind {unknown[0]!r} has no replay buffer (buffers: {sorted(replay.buffers)})")
        finished = []
        n = len(self.envs)
        for _ in range(steps):
            actions = np.asarray(act_fn(self.obs))
            next_obs = np.empty_like(self.obs)
            rewards, terminated = np.empty(n, np.float32), np.empty(n, np.float32)
            ended = np.zeros(n, bool)
            for i, env in enumerate(self.envs):
                next_obs[i], rewards[i], term, trunc, info = env.step(actions[i])
                terminated[i], ended[i] = term, term or trunc
                self.returns[i] += rewards[i]
                if ended[i]:
                    ret, length, outcome = float(self.returns[i]), int(info["steps"]), int(info["outcome"])
                    finished.append(Episode(self.kinds[i], ret, length, outcome, bool(info["triggered"])))
                    self.returns[i] = 0.0
            for kind, rows in self._rows.items():
                replay[kind].add_batch(self.obs[rows], actions[rows], rewards[rows], next_obs[rows], terminated[rows])
            for j in np.flatnonzero(ended):  # next_obs is stored: only now swap in the new episode
                next_obs[j] = self.envs[j].reset()[0]
            self.obs = next_obs
            self.frames += n
        return finished
