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
from numba import njit

from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.batched_base import BatchedGridEnv, EngineGroup, bool_mask
from rlbackdoors.envs.lavaworld import DEFAULT_CROSSINGS, DEFAULT_MAX_STEPS, DEFAULT_SIZE, VIEW_SIZE
from rlbackdoors.envs.lavaworld import as_trigger, validate_crossing_layout
from rlbackdoors.triggers.observation import ObservationTrigger


# ----------------------------------------------------------------------------- layouts


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


# ----------------------------------------------------------------------------- hooks (grid_engine.bind_kernels)
# world = (num_crossings, poisoned, luts (B, 256): each slot's trigger table); no scratch, no extra outputs


@ge.hook
def _scratch(grid, world):
    return ()


@ge.hook
def _layout(grid, b, pos, dirs, steps, rng, world, scratch):
    gen_crossing(grid, b, world[0], rng, pos, dirs, steps)
    return True


@ge.hook
def _outcome(b, pos, fwd, world):
    """MiniGrid's LavaEnv: walking onto the goal or into lava ends the episode."""
    if fwd == ge.GOAL:
        return ge.OUT_GOAL
    if fwd == ge.LAVA:
        return ge.OUT_LAVA
    return ge.OUT_NONE


@ge.hook
def _seen(phase, b, ob, pos, dirs, img, world, outs):
    """Poisoned envs see every view through their trigger's lookup table (a table per slot: the
    slots of one engine call may be several agents', each with its own trigger)."""
    if world[1][b]:
        ge.apply_lut(img, ob, world[2][b])


_KERNELS = ge.bind_kernels("lavaworld", scratch=_scratch, layout=_layout, outcome=_outcome, seen=_seen, trojan=ge.OUT_LAVA)


# ----------------------------------------------------------------------------- the vector env


class BatchedLavaWorld(BatchedGridEnv):
    """``num_envs`` LavaWorld envs (clean or poisoned) stepped by numba kernels.

    Same contract as :class:`~rlbackdoors.envs.vector.ReferenceVectorEnv` over
    :class:`~rlbackdoors.envs.lavaworld.LavaWorldEnv`. Extra: ``final_obs`` holds, for envs
    that finished in the last step, the observation of the terminal state (what the single
    env returned before being reset); :meth:`load_layout` / :meth:`layout` move exact states
    in and out of a slot; :meth:`observe` renders the current observations.
    """

    _kernels = _KERNELS
    view_size = VIEW_SIZE
    device_engine = "rlbackdoors.envs.lavaworld_device:DeviceLavaWorld"

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
        self.poisoned = bool_mask(poisoned, self.num_envs, "poisoned")
        if self.poisoned.any() and self.trigger is None:
            raise ValueError("poisoned envs need a trigger: pass trigger= (e.g. 'multiplicative:12')")
        self._lut = (self.trigger.lookup_table() if self.trigger is not None else np.arange(256, dtype=np.uint8)).astype(np.uint8)

        self._init_spaces(spaces.Box(0, 255, (VIEW_SIZE, VIEW_SIZE, 3), dtype=np.uint8))
        self._init_state()
        self.final_obs = np.zeros((self.num_envs, VIEW_SIZE, VIEW_SIZE, 3), dtype=np.uint8)

    def _world(self) -> tuple:
        return self.num_crossings, self.poisoned, np.broadcast_to(self._lut, (self.num_envs, 256))

    def _group_world(self, engines: list[BatchedGridEnv], group: EngineGroup) -> tuple | None:
        if any(e.num_crossings != self.num_crossings for e in engines):  # type: ignore[attr-defined]  # same class: checked by EngineGroup
            return None
        return self.num_crossings, group.poisoned, np.concatenate([np.broadcast_to(e._lut, (e.num_envs, 256)) for e in engines])  # type: ignore[attr-defined]

    # --------------------------------------------------------------------- exact state I/O

    def load_layout(self, i: int, grid: np.ndarray, agent_pos, agent_dir: int, step_count: int = 0) -> np.ndarray:
        """Put an exact state into slot ``i``; returns that slot's observation.

        ``grid`` is MiniGrid's ``env.grid.encode()`` of the full grid, shape (size, size, 3).
        """
        i, arr, pos = self._check_state(i, grid, agent_pos, agent_dir, step_count)
        self._write_state(i, arr, pos, agent_dir, step_count)
        return self._views(i, 1)[0][0]

    def layout(self, i: int) -> tuple[np.ndarray, tuple[int, int], int, int]:
        """Slot ``i``'s state: ``(grid (size, size, 3) uint8, agent_pos, agent_dir, step_count)``."""
        return self._slot_state(i)
