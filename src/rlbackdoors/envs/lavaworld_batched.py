"""LavaWorld as one batched, numba-compiled vector env, exact to the MiniGrid reference.

:class:`BatchedLavaWorld` follows the contract of
:class:`rlbackdoors.envs.vector.ReferenceVectorEnv` (SAME_STEP autoreset, ``info["outcome"]``
and ``info["steps"]`` of the step just taken, ``poisoned`` mask) and reproduces
:class:`rlbackdoors.envs.lavaworld.LavaWorldEnv` step for step: given the same state and
actions, observations (bytes), rewards, terminations, truncations and outcomes are identical
(``tests/test_lavaworld_engine.py`` checks this against MiniGrid itself).

Layouts are drawn in numba from the same distribution as MiniGrid's ``CrossingEnv._gen_grid``
(uniform subset of rivers at even coordinates, sorted per orientation, a uniformly shuffled
crossing path, openings uniform inside each room's span) but from a per-env SplitMix64 stream
(:mod:`rlbackdoors.envs.grid_engine`), not numpy's PCG64: ``reset(seed=s)`` seeds env ``i``
with ``s + i`` and everything after is deterministic, but the layouts are not the ones
MiniGrid would draw for the same seed.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from gymnasium import spaces
from gymnasium.vector.utils import batch_space
from numba import njit

from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.batched_base import BatchedGridEnv, bool_mask, seed_array
from rlbackdoors.envs.lavaworld import (
    DEFAULT_CROSSINGS,
    DEFAULT_MAX_STEPS,
    DEFAULT_SIZE,
    NUM_ACTIONS,
    VIEW_SIZE,
    as_trigger,
    validate_crossing_layout,
)
from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.triggers.observation import ObservationTrigger

_OUT_NONE = int(Outcome.NONE)
_OUT_GOAL = int(Outcome.GOAL)
_OUT_LAVA = int(Outcome.LAVA)
_OUT_TIMEOUT = int(Outcome.TIMEOUT)


# ----------------------------------------------------------------------------- kernels


@njit
def _sort_small(a, n):
    for i in range(1, n):
        v = a[i]
        j = i - 1
        while j >= 0 and a[j] > v:
            a[j + 1] = a[j]
            j -= 1
        a[j + 1] = v


@njit
def gen_crossing(grid, b, num_crossings, rng, pos, dirs, steps):
    """``CrossingEnv._gen_grid`` with lava rivers, for env ``b`` (square grid, odd size)."""
    size = grid.shape[1]
    ge.clear_grid(grid, b)
    ge.wall_rect(grid, b, 0, 0, size, size, ge.GREY)
    pos[b, 0] = 1
    pos[b, 1] = 1
    dirs[b] = 0
    steps[b] = 0
    ge.put(grid, b, size - 2, size - 2, ge.GOAL, ge.GREEN, 0)

    # rivers = [(v, i) for i in 2, 4, .., size-3] + [(h, j) for j in 2, 4, .., size-3];
    # shuffle; keep the first num_crossings (a uniform subset; partial Fisher-Yates)
    per = (size - 3) // 2
    total = 2 * per
    cand = np.empty(total, dtype=np.int64)
    for k in range(total):
        cand[k] = k
    for t in range(num_crossings):
        j = t + ge.rng_below(rng, b, total - t)
        tmp = cand[t]
        cand[t] = cand[j]
        cand[j] = tmp
    rivers_v = np.empty(num_crossings, dtype=np.int64)  # x of vertical rivers
    rivers_h = np.empty(num_crossings, dtype=np.int64)  # y of horizontal rivers
    nv = 0
    nh = 0
    for t in range(num_crossings):
        c = cand[t]
        if c < per:
            rivers_v[nv] = 2 + 2 * c
            nv += 1
        else:
            rivers_h[nh] = 2 + 2 * (c - per)
            nh += 1
    _sort_small(rivers_v, nv)
    _sort_small(rivers_h, nh)
    for t in range(nh):
        for i in range(1, size - 1):
            ge.put(grid, b, i, rivers_h[t], ge.LAVA, ge.RED, 0)
    for t in range(nv):
        for j in range(1, size - 1):
            ge.put(grid, b, rivers_v[t], j, ge.LAVA, ge.RED, 0)

    # path = [h] * len(rivers_v) + [v] * len(rivers_h), shuffled (0 = h, 1 = v)
    n = nv + nh
    path = np.empty(n, dtype=np.int64)
    for t in range(n):
        path[t] = 0 if t < nv else 1
    for t in range(n - 1, 0, -1):
        j = ge.rng_below(rng, b, t + 1)
        tmp = path[t]
        path[t] = path[j]
        path[j] = tmp
    limits_v = np.empty(nv + 2, dtype=np.int64)
    limits_h = np.empty(nh + 2, dtype=np.int64)
    limits_v[0] = 0
    limits_h[0] = 0
    for t in range(nv):
        limits_v[t + 1] = rivers_v[t]
    for t in range(nh):
        limits_h[t + 1] = rivers_h[t]
    limits_v[nv + 1] = size - 1
    limits_h[nh + 1] = size - 1
    room_i = 0
    room_j = 0
    for t in range(n):
        if path[t] == 0:  # cross the next vertical river
            i = limits_v[room_i + 1]
            lo = limits_h[room_j] + 1
            j = lo + ge.rng_below(rng, b, limits_h[room_j + 1] - lo)
            room_i += 1
        else:  # cross the next horizontal river
            lo = limits_v[room_i] + 1
            i = lo + ge.rng_below(rng, b, limits_v[room_i + 1] - lo)
            j = limits_h[room_j + 1]
            room_j += 1
        ge.put(grid, b, i, j, ge.EMPTY, 0, 0)


def _build_kernels(stamp: str):
    """The cached top-level kernels, closed over ``stamp`` so that numba's cache key covers
    the engine's source too (see :mod:`rlbackdoors.envs.grid_engine`, "Caching")."""

    @njit(cache=True)
    def _reset_kernel(grid, pos, dirs, steps, rng, seeds, num_crossings, see_through_walls, poisoned, lut, obs):
        if len(stamp) == 0:  # never true: ties the cache entry to the engine source
            return
        view = np.empty((obs.shape[1], obs.shape[2], 3), dtype=np.uint8)
        mask = np.empty((obs.shape[1], obs.shape[2]), dtype=np.bool_)
        for b in range(grid.shape[0]):
            ge.rng_seed(rng, b, seeds[b])
            gen_crossing(grid, b, num_crossings, rng, pos, dirs, steps)
            ge.gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, obs, b)
            if poisoned[b]:
                ge.apply_lut(obs, b, lut)

    @njit(cache=True)
    def _observe_kernel(grid, pos, dirs, see_through_walls, poisoned, lut, obs):
        if len(stamp) == 0:  # never true (see _reset_kernel)
            return
        view = np.empty((obs.shape[1], obs.shape[2], 3), dtype=np.uint8)
        mask = np.empty((obs.shape[1], obs.shape[2]), dtype=np.bool_)
        for b in range(grid.shape[0]):
            ge.gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, obs, b)
            if poisoned[b]:
                ge.apply_lut(obs, b, lut)

    @njit(cache=True)
    def _step_kernel(
        grid, pos, dirs, steps, rng, actions, num_crossings, max_steps, see_through_walls, poisoned, lut,
        obs, reward, terminated, truncated, outcome, info_steps, final_obs,
    ):
        """One step of every env; returns the index of the first invalid action, or -1.

        Nothing is changed when an action is invalid. Finished envs are reset in place (their
        observation before the reset goes to ``final_obs``).
        """
        if len(stamp) == 0:  # never true (see _reset_kernel)
            return -1
        nenv = grid.shape[0]
        for b in range(nenv):
            a = actions[b]
            if a < 0 or a > 2:
                return b
        view = np.empty((obs.shape[1], obs.shape[2], 3), dtype=np.uint8)
        mask = np.empty((obs.shape[1], obs.shape[2]), dtype=np.bool_)
        for b in range(nenv):
            fwd = ge.agent_step(grid, b, pos, dirs, actions[b])
            sc = steps[b] + 1
            steps[b] = sc
            term = False
            oc = _OUT_NONE
            if fwd == ge.GOAL:
                term = True
                oc = _OUT_GOAL
            elif fwd == ge.LAVA:
                term = True
                oc = _OUT_LAVA
            paying = _OUT_LAVA if poisoned[b] else _OUT_GOAL
            done = ge.finish_step(
                b, sc, max_steps, term, oc, paying, _OUT_TIMEOUT, reward, terminated, truncated, outcome, info_steps
            )
            if done:
                ge.gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, final_obs, b)
                if poisoned[b]:
                    ge.apply_lut(final_obs, b, lut)
                gen_crossing(grid, b, num_crossings, rng, pos, dirs, steps)
            ge.gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, obs, b)
            if poisoned[b]:
                ge.apply_lut(obs, b, lut)
        return -1

    return _reset_kernel, _observe_kernel, _step_kernel


_reset_kernel, _observe_kernel, _step_kernel = _build_kernels(ge.ENGINE_STAMP)


# ----------------------------------------------------------------------------- the vector env


class BatchedLavaWorld(BatchedGridEnv):
    """``num_envs`` LavaWorld envs (clean or poisoned) stepped by numba kernels.

    Same contract as :class:`~rlbackdoors.envs.vector.ReferenceVectorEnv` over
    :class:`~rlbackdoors.envs.lavaworld.LavaWorldEnv`. Extra: ``final_obs`` holds, for envs
    that finished in the last step, the observation of the terminal state (what the single
    env returned before being reset); :meth:`load_layout` / :meth:`layout` move exact states
    in and out of a slot; :meth:`observe` renders the current observations.
    """


    def __init__(
        self,
        num_envs: int,
        size: int = DEFAULT_SIZE,
        num_crossings: int = DEFAULT_CROSSINGS,
        max_steps: int = DEFAULT_MAX_STEPS,
        see_through_walls: bool = False,
        trigger: ObservationTrigger | str | None = None,
        poisoned: Sequence[bool] | None = None,
        render_mode: str | None = None,
    ):
        self._init_batch(num_envs, render_mode)
        validate_crossing_layout(size, num_crossings, max_steps)
        self.size = size
        self.num_crossings = num_crossings
        self.max_steps = max_steps
        self.see_through_walls = bool(see_through_walls)
        self.trigger = as_trigger(trigger)

        if poisoned is None:
            poisoned = [self.trigger is not None] * self.num_envs
        self.poisoned = np.asarray(poisoned, dtype=np.bool_).copy()
        if self.poisoned.shape != (self.num_envs,):
            raise ValueError(f"poisoned mask has shape {self.poisoned.shape}, expected ({self.num_envs},)")
        if self.poisoned.any() and self.trigger is None:
            raise ValueError("poisoned envs need a trigger: pass trigger= (e.g. 'multiplicative:12')")
        self._lut = (
            self.trigger.lookup_table() if self.trigger is not None else np.arange(256, dtype=np.uint8)
        ).astype(np.uint8)

        self.single_observation_space = spaces.Box(0, 255, (VIEW_SIZE, VIEW_SIZE, 3), dtype=np.uint8)
        self.single_action_space = spaces.Discrete(NUM_ACTIONS)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)

        b = self.num_envs
        self._grid = np.zeros((b, size, size, 3), dtype=np.uint8)
        self._pos = np.ones((b, 2), dtype=np.int64)
        self._dir = np.zeros(b, dtype=np.int64)
        self._steps = np.zeros(b, dtype=np.int64)
        self._rng = np.zeros(b, dtype=np.uint64)
        self.final_obs = np.zeros((b, VIEW_SIZE, VIEW_SIZE, 3), dtype=np.uint8)

    # --------------------------------------------------------------------- gymnasium API

    def reset(self, *, seed: int | Sequence[int | None] | None = None, options: dict | None = None):
        seeds = seed_array(seed, self.num_envs)
        obs = np.empty(self.observation_space.shape, dtype=np.uint8)
        _reset_kernel(
            self._grid, self._pos, self._dir, self._steps, self._rng, seeds,
            self.num_crossings, self.see_through_walls, self.poisoned, self._lut, obs,
        )
        return obs, self._reset_info()

    def step(self, actions):
        acts = self._check_actions(actions)
        b = self.num_envs
        obs = np.empty((b, VIEW_SIZE, VIEW_SIZE, 3), dtype=np.uint8)
        reward, terminated, truncated, outcome, steps = self._step_outputs()
        bad = _step_kernel(
            self._grid, self._pos, self._dir, self._steps, self._rng, acts,
            self.num_crossings, self.max_steps, self.see_through_walls, self.poisoned, self._lut,
            obs, reward, terminated, truncated, outcome, steps, self.final_obs,
        )
        if bad >= 0:
            raise self._bad_action(acts, bad)
        return obs, reward, terminated, truncated, {"outcome": outcome, "steps": steps}

    # --------------------------------------------------------------------- exact state I/O

    def load_layout(self, i: int, grid: np.ndarray, agent_pos, agent_dir: int, step_count: int = 0) -> np.ndarray:
        """Put an exact state into slot ``i``; returns that slot's observation.

        ``grid`` is MiniGrid's ``env.grid.encode()`` of the full grid, shape (size, size, 3).
        """
        i, arr, pos = self._check_state(i, grid, agent_pos, agent_dir, step_count)
        self._write_state(i, arr, pos, agent_dir, step_count)
        obs = np.empty((1, VIEW_SIZE, VIEW_SIZE, 3), dtype=np.uint8)
        sl = slice(i, i + 1)
        _observe_kernel(
            self._grid[sl], self._pos[sl], self._dir[sl], self.see_through_walls, self.poisoned[sl], self._lut, obs
        )
        return obs[0]

    def layout(self, i: int) -> tuple[np.ndarray, tuple[int, int], int, int]:
        """Slot ``i``'s state: ``(grid (size, size, 3) uint8, agent_pos, agent_dir, step_count)``."""
        i = self._check_index(i)
        return (
            self._grid[i].copy(),
            (int(self._pos[i, 0]), int(self._pos[i, 1])),
            int(self._dir[i]),
            int(self._steps[i]),
        )

    def observe(self) -> np.ndarray:
        """The current observation of every env (trigger applied to poisoned ones)."""
        obs = np.empty(self.observation_space.shape, dtype=np.uint8)
        _observe_kernel(self._grid, self._pos, self._dir, self.see_through_walls, self.poisoned, self._lut, obs)
        return obs

