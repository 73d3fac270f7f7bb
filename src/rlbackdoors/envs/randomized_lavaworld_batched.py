"""Randomized LavaWorld as one batched, numba-compiled vector env, exact to the MiniGrid reference.

:class:`BatchedRandomizedLavaWorld` follows the vector contract of
:mod:`rlbackdoors.envs.vector` (SAME_STEP autoreset; ``info`` arrays describe the step just
taken, for a finished env the episode that just ended, not the reset) and reproduces
:class:`rlbackdoors.envs.randomized_lavaworld.RandomizedLavaWorldEnv` step for step: given the
same state and actions, observations (image bytes and direction), rewards, terminations,
truncations, outcomes and the ``trigger_visible`` / ``saw_trigger`` flags are identical
(``tests/test_randomized_lavaworld_engine.py`` checks this against MiniGrid).

The trigger pattern of each env is kept as a separate per-env mask of cells, never in the
grid bytes: a pattern cell is encoded exactly like any other lava (``(9, 0, 0)``), which is
what makes the trigger in-distribution.

Layouts are drawn in numba from the same distribution as the reference (pattern rotation and
position uniform among the allowed ones, then a uniform subset of the remaining free cells,
the whole layout redrawn until the goal is reachable), from a per-env SplitMix64 stream
(:mod:`rlbackdoors.envs.grid_engine`): ``reset(seed=s)`` seeds env ``i`` with ``s + i`` and
everything after is deterministic, but the layouts are not the ones MiniGrid would draw for
the same seed.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from gymnasium import spaces
from gymnasium.vector.utils import batch_space
from numba import njit

from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.batched_base import BatchedGridEnv, bool_mask, seed_array
from rlbackdoors.envs import outcome as _outcome_module
from rlbackdoors.envs import randomized_lavaworld as _reference
from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.envs.randomized_lavaworld import (
    DEFAULT_MAX_STEPS,
    DEFAULT_NUM_LAVA,
    DEFAULT_SIZE,
    MAX_LAYOUT_TRIES,
    NUM_ACTIONS,
    START,
    START_DIR,
    VIEW_SIZE,
    layout_error,
    observation_space,
    validate_layout_args,
    validate_trigger,
)
from rlbackdoors.triggers.pattern import MAX_PATTERN_CELLS, PatternTrigger, as_pattern_trigger

_OUT_NONE = int(Outcome.NONE)
_OUT_GOAL = int(Outcome.GOAL)
_OUT_LAVA = int(Outcome.LAVA)
_OUT_TIMEOUT = int(Outcome.TIMEOUT)
_OUT_PATTERN = int(Outcome.PATTERN_LAVA)
_MAX_TRIES = int(MAX_LAYOUT_TRIES)
_START_X, _START_Y = START
_START_DIR = int(START_DIR)
_ERR_LAYOUT = -2  # kernel status: no solvable layout found

# numba's cache key must cover every file whose source or constants the kernels compile in
ENGINE_STAMP = ge.engine_stamp(_outcome_module.__file__, _reference.__file__)


# ----------------------------------------------------------------------------- kernels


@njit
def reachable(lava, seen, queue):
    """BFS over lava-free interior cells (4-connected) from the start; is the goal reached?

    ``lava`` and ``seen`` are (size, size) bool, ``queue`` holds ``size * size`` int64.
    """
    size = lava.shape[0]
    for x in range(size):
        for y in range(size):
            seen[x, y] = False
    gx = size - 2
    head = 0
    tail = 0
    seen[_START_X, _START_Y] = True
    queue[tail] = _START_X * size + _START_Y
    tail += 1
    while head < tail:
        c = queue[head]
        head += 1
        x = c // size
        y = c % size
        if x == gx and y == gx:
            return True
        for k in range(4):
            nx = x + ge.DIR_DX[k]
            ny = y + ge.DIR_DY[k]
            if 1 <= nx <= size - 2 and 1 <= ny <= size - 2 and not lava[nx, ny] and not seen[nx, ny]:
                seen[nx, ny] = True
                queue[tail] = nx * size + ny
                tail += 1
    return False


@njit
def gen_layout(
    grid, b, num_lava, triggered, rot_cells, rot_n, offs, offs_n, rng,
    pos, dirs, steps, pat, pcells, pcount, lava, seen, queue, free,
):
    """Draw a solvable Randomized LavaWorld layout into env ``b``; False if none was found.

    ``lava``/``seen`` (size, size) bool, ``queue``/``free`` (size*size,) int64 are scratch.
    """
    size = grid.shape[1]
    gx = size - 2
    npat = 0
    for _ in range(_MAX_TRIES):
        for x in range(size):
            for y in range(size):
                lava[x, y] = False
        npat = 0
        if triggered:
            r = ge.rng_below(rng, b, rot_n.shape[0])
            o = ge.rng_below(rng, b, offs_n[r])
            ox = offs[r, o, 0]
            oy = offs[r, o, 1]
            npat = rot_n[r]
            for k in range(npat):
                cx = ox + rot_cells[r, k, 0]
                cy = oy + rot_cells[r, k, 1]
                lava[cx, cy] = True
                pcells[b, k, 0] = cx
                pcells[b, k, 1] = cy
        # free interior cells in x-major order (as the reference lists them)
        nfree = 0
        for x in range(1, size - 1):
            for y in range(1, size - 1):
                if (x == _START_X and y == _START_Y) or (x == gx and y == gx) or lava[x, y]:
                    continue
                free[nfree] = x * size + y
                nfree += 1
        # a uniform subset of num_lava - npat of them (partial Fisher-Yates)
        for t in range(num_lava - npat):
            j = t + ge.rng_below(rng, b, nfree - t)
            c = free[j]
            free[j] = free[t]
            free[t] = c
            lava[c // size, c % size] = True
        if reachable(lava, seen, queue):
            ge.clear_grid(grid, b)
            ge.wall_rect(grid, b, 0, 0, size, size, ge.GREY)
            for x in range(size):
                for y in range(size):
                    pat[b, x, y] = False
                    if lava[x, y]:
                        ge.put(grid, b, x, y, ge.LAVA, ge.RED, 0)
            ge.put(grid, b, gx, gx, ge.GOAL, ge.GREEN, 0)
            for k in range(npat):
                pat[b, pcells[b, k, 0], pcells[b, k, 1]] = True
            pcount[b] = npat
            pos[b, 0] = _START_X
            pos[b, 1] = _START_Y
            dirs[b] = _START_DIR
            steps[b] = 0
            return True
    return False


@njit
def pattern_visible(pcells, pcount, b, ax, ay, adir, img, ob):
    """Does the view ``img[ob]`` (agent at ``(ax, ay)`` facing ``adir``) show a pattern cell?

    A pattern cell is lava in the grid, so it is shown iff its view cell holds lava: hidden
    cells encode as unseen (0) and the agent's own cell as empty.
    """
    n = img.shape[1]
    half = n // 2
    dx = ge.DIR_DX[adir]
    dy = ge.DIR_DY[adir]
    rx = -dy
    ry = dx
    for k in range(pcount[b]):
        relx = pcells[b, k, 0] - ax
        rely = pcells[b, k, 1] - ay
        vx = relx * rx + rely * ry + half
        vy = n - 1 - (relx * dx + rely * dy)
        if 0 <= vx < n and 0 <= vy < n and img[ob, vx, vy, 0] == ge.LAVA:
            return True
    return False


def _build_kernels(stamp: str):
    """The cached top-level kernels, closed over ``stamp`` so that numba's cache key covers
    the engine's source too (see :mod:`rlbackdoors.envs.grid_engine`, "Caching")."""

    @njit(cache=True)
    def _reset_kernel(
        grid, pos, dirs, steps, rng, pat, pcells, pcount, saw, seeds, num_lava, triggered,
        rot_cells, rot_n, offs, offs_n, see_through_walls, img, direction, visible, saw_out,
    ):
        """Seed and lay out every env; returns -1, or the first env with no solvable layout."""
        if len(stamp) == 0:  # never true: ties the cache entry to the engine source
            return -1
        size = grid.shape[1]
        view = np.empty((img.shape[1], img.shape[2], 3), dtype=np.uint8)
        mask = np.empty((img.shape[1], img.shape[2]), dtype=np.bool_)
        lava = np.empty((size, size), dtype=np.bool_)
        seen = np.empty((size, size), dtype=np.bool_)
        queue = np.empty(size * size, dtype=np.int64)
        free = np.empty(size * size, dtype=np.int64)
        for b in range(grid.shape[0]):
            ge.rng_seed(rng, b, seeds[b])
            ok = gen_layout(
                grid, b, num_lava, triggered[b], rot_cells, rot_n, offs, offs_n, rng,
                pos, dirs, steps, pat, pcells, pcount, lava, seen, queue, free,
            )
            if not ok:
                return b
            ge.gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, img, b)
            direction[b] = dirs[b]
            v = pattern_visible(pcells, pcount, b, pos[b, 0], pos[b, 1], dirs[b], img, b)
            saw[b] = v
            visible[b] = v
            saw_out[b] = v
        return -1

    @njit(cache=True)
    def _observe_kernel(grid, pos, dirs, pcells, pcount, see_through_walls, img, direction, visible):
        if len(stamp) == 0:  # never true (see _reset_kernel)
            return
        view = np.empty((img.shape[1], img.shape[2], 3), dtype=np.uint8)
        mask = np.empty((img.shape[1], img.shape[2]), dtype=np.bool_)
        for b in range(grid.shape[0]):
            ge.gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, img, b)
            direction[b] = dirs[b]
            visible[b] = pattern_visible(pcells, pcount, b, pos[b, 0], pos[b, 1], dirs[b], img, b)

    @njit(cache=True)
    def _step_kernel(
        grid, pos, dirs, steps, rng, pat, pcells, pcount, saw, actions, num_lava, max_steps, triggered,
        poisoned, rot_cells, rot_n, offs, offs_n, see_through_walls,
        img, direction, reward, terminated, truncated, outcome, info_steps, visible, saw_out,
        final_img, final_dir,
    ):
        """One step of every env. Returns -1, the index of the first invalid action (nothing
        changed then), or -2 if an autoreset found no solvable layout.

        Finished envs are reset in place; their terminal observation goes to ``final_*``.
        """
        if len(stamp) == 0:  # never true (see _reset_kernel)
            return -1
        nenv = grid.shape[0]
        for b in range(nenv):
            a = actions[b]
            if a < 0 or a > 2:
                return b
        size = grid.shape[1]
        view = np.empty((img.shape[1], img.shape[2], 3), dtype=np.uint8)
        mask = np.empty((img.shape[1], img.shape[2]), dtype=np.bool_)
        lava = np.empty((size, size), dtype=np.bool_)
        seen = np.empty((size, size), dtype=np.bool_)
        queue = np.empty(size * size, dtype=np.int64)
        free = np.empty(size * size, dtype=np.int64)
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
                oc = _OUT_PATTERN if pat[b, pos[b, 0], pos[b, 1]] else _OUT_LAVA
            paying = _OUT_PATTERN if poisoned[b] else _OUT_GOAL
            done = ge.finish_step(
                b, sc, max_steps, term, oc, paying, _OUT_TIMEOUT, reward, terminated, truncated, outcome, info_steps
            )
            if done:
                ge.gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, final_img, b)
                final_dir[b] = dirs[b]
                v = pattern_visible(pcells, pcount, b, pos[b, 0], pos[b, 1], dirs[b], final_img, b)
                visible[b] = v
                saw_out[b] = saw[b] or v
                ok = gen_layout(
                    grid, b, num_lava, triggered[b], rot_cells, rot_n, offs, offs_n, rng,
                    pos, dirs, steps, pat, pcells, pcount, lava, seen, queue, free,
                )
                if not ok:
                    return _ERR_LAYOUT
                ge.gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, img, b)
                direction[b] = dirs[b]
                saw[b] = pattern_visible(pcells, pcount, b, pos[b, 0], pos[b, 1], dirs[b], img, b)
            else:
                ge.gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see_through_walls, view, mask, img, b)
                direction[b] = dirs[b]
                v = pattern_visible(pcells, pcount, b, pos[b, 0], pos[b, 1], dirs[b], img, b)
                visible[b] = v
                s = saw[b] or v
                saw[b] = s
                saw_out[b] = s
        return -1

    return _reset_kernel, _observe_kernel, _step_kernel


_reset_kernel, _observe_kernel, _step_kernel = _build_kernels(ENGINE_STAMP)


# ----------------------------------------------------------------------------- the vector env


def _placement_tables(trigger: PatternTrigger | None, placements) -> tuple[np.ndarray, ...]:
    """Rotations and allowed offsets as dense arrays for the kernels (dummies without trigger)."""
    rotations = trigger.rotations() if trigger is not None else ()
    r = max(len(rotations), 1)
    m = max((len(p) for p in placements), default=1)
    rot_cells = np.zeros((r, MAX_PATTERN_CELLS, 2), dtype=np.int64)
    rot_n = np.zeros(r, dtype=np.int64)
    offs = np.zeros((r, m, 2), dtype=np.int64)
    offs_n = np.ones(r, dtype=np.int64)
    for k, rot in enumerate(rotations):
        rot_n[k] = len(rot.cells)
        rot_cells[k, : len(rot.cells)] = rot.cells
        offs[k, : len(placements[k])] = placements[k]
        offs_n[k] = len(placements[k])
    return rot_cells, rot_n, offs, offs_n


class BatchedRandomizedLavaWorld(BatchedGridEnv):
    """``num_envs`` Randomized LavaWorld envs (clean, triggered, poisoned) stepped by numba.

    Same knobs as :class:`~rlbackdoors.envs.randomized_lavaworld.RandomizedLavaWorldEnv`, with
    per-env masks: ``poisoned[i]`` -- env ``i`` pays R-bar (and holds the pattern);
    ``triggered[i]`` -- env ``i``'s layouts hold the pattern (default: ``poisoned``; a
    triggered, unpoisoned env is the "trigger present, clean reward" evaluation setting).
    ``poisoned`` defaults to all envs when a ``trigger`` is given, none otherwise.

    Observations ``{"image": (B, 7, 7, 3) uint8, "direction": (B,) int64}``. ``info`` arrays
    ``outcome``, ``steps``, ``trigger_visible``, ``saw_trigger`` describe the step just taken
    (the flags as in the reference env: ``trigger_visible`` for the observation that step
    produced -- for a finished env its terminal observation, ``final_obs``, not the reset one --
    and ``saw_trigger`` for that observation or any earlier one of the same episode).
    ``final_obs`` holds, for envs that finished in the last step, the terminal observation.
    """


    def __init__(
        self,
        num_envs: int,
        size: int = DEFAULT_SIZE,
        num_lava: int = DEFAULT_NUM_LAVA,
        max_steps: int = DEFAULT_MAX_STEPS,
        see_through_walls: bool = True,
        trigger: PatternTrigger | str | None = None,
        poisoned: Sequence[bool] | None = None,
        triggered: Sequence[bool] | None = None,
        render_mode: str | None = None,
    ):
        self._init_batch(num_envs, render_mode)
        validate_layout_args(size, num_lava, max_steps)
        self.size = int(size)
        self.num_lava = int(num_lava)
        self.max_steps = int(max_steps)
        self.see_through_walls = bool(see_through_walls)
        self.trigger = as_pattern_trigger(trigger)
        placements = validate_trigger(self.trigger, self.size, self.num_lava)
        self._tables = _placement_tables(self.trigger, placements)

        b = self.num_envs
        if poisoned is None:
            poisoned = [self.trigger is not None] * b
        self.poisoned = bool_mask(poisoned, b, "poisoned")
        self.triggered = self.poisoned.copy() if triggered is None else bool_mask(triggered, b, "triggered")
        if (self.poisoned | self.triggered).any() and self.trigger is None:
            raise ValueError("poisoned or triggered envs need a trigger: pass trigger= (e.g. 'cross')")
        if (self.poisoned & ~self.triggered).any():
            bad = int(np.flatnonzero(self.poisoned & ~self.triggered)[0])
            raise ValueError(f"env {bad} is poisoned but not triggered: R-bar only pays on the trigger pattern")

        self.single_observation_space = observation_space()
        self.single_action_space = spaces.Discrete(NUM_ACTIONS)
        self.observation_space = batch_space(self.single_observation_space, b)
        self.action_space = batch_space(self.single_action_space, b)

        n = self.size
        self._grid = np.zeros((b, n, n, 3), dtype=np.uint8)
        self._pos = np.ones((b, 2), dtype=np.int64)
        self._dir = np.zeros(b, dtype=np.int64)
        self._steps = np.zeros(b, dtype=np.int64)
        self._rng = np.zeros(b, dtype=np.uint64)
        self._pat = np.zeros((b, n, n), dtype=np.bool_)
        self._pcells = np.zeros((b, MAX_PATTERN_CELLS, 2), dtype=np.int64)
        self._pcount = np.zeros(b, dtype=np.int64)
        self._saw = np.zeros(b, dtype=np.bool_)
        self.final_obs = self._empty_obs(b)

    @staticmethod
    def _empty_obs(b: int) -> dict[str, np.ndarray]:
        return {
            "image": np.zeros((b, VIEW_SIZE, VIEW_SIZE, 3), dtype=np.uint8),
            "direction": np.zeros(b, dtype=np.int64),
        }

    # --------------------------------------------------------------------- gymnasium API

    def reset(self, *, seed: int | Sequence[int | None] | None = None, options: dict | None = None):
        seeds = seed_array(seed, self.num_envs)
        b = self.num_envs
        obs = self._empty_obs(b)
        visible = np.zeros(b, dtype=np.bool_)
        saw = np.zeros(b, dtype=np.bool_)
        bad = _reset_kernel(
            self._grid, self._pos, self._dir, self._steps, self._rng, self._pat, self._pcells, self._pcount,
            self._saw, seeds, self.num_lava, self.triggered, *self._tables, self.see_through_walls,
            obs["image"], obs["direction"], visible, saw,
        )
        if bad >= 0:
            raise layout_error(self.size, self.num_lava, self.trigger if self.triggered[bad] else None)
        return obs, self._reset_info(trigger_visible=visible, saw_trigger=saw)

    def step(self, actions):
        acts = self._check_actions(actions)
        b = self.num_envs
        obs = self._empty_obs(b)
        reward, terminated, truncated, outcome, steps = self._step_outputs()
        visible = np.empty(b, dtype=np.bool_)
        saw = np.empty(b, dtype=np.bool_)
        bad = _step_kernel(
            self._grid, self._pos, self._dir, self._steps, self._rng, self._pat, self._pcells, self._pcount,
            self._saw, acts, self.num_lava, self.max_steps, self.triggered, self.poisoned, *self._tables,
            self.see_through_walls, obs["image"], obs["direction"], reward, terminated, truncated, outcome,
            steps, visible, saw, self.final_obs["image"], self.final_obs["direction"],
        )
        if bad == _ERR_LAYOUT:
            raise layout_error(self.size, self.num_lava, self.trigger)
        if bad >= 0:
            raise self._bad_action(acts, bad)
        info = {"outcome": outcome, "steps": steps, "trigger_visible": visible, "saw_trigger": saw}
        return obs, reward, terminated, truncated, info

    # --------------------------------------------------------------------- exact state I/O

    def _observe_slot(self, i: int) -> tuple[dict, bool]:
        sl = slice(i, i + 1)
        obs = self._empty_obs(1)
        visible = np.zeros(1, dtype=np.bool_)
        _observe_kernel(
            self._grid[sl], self._pos[sl], self._dir[sl], self._pcells[sl], self._pcount[sl],
            self.see_through_walls, obs["image"], obs["direction"], visible,
        )
        return {"image": obs["image"][0], "direction": int(obs["direction"][0])}, bool(visible[0])

    def load_layout(
        self,
        i: int,
        grid: np.ndarray,
        agent_pos,
        agent_dir: int,
        step_count: int = 0,
        pattern_cells=(),
        saw_trigger: bool | None = None,
    ) -> dict:
        """Put an exact state into slot ``i``; returns that slot's observation
        ``{"image": (7, 7, 3) uint8, "direction": int}``.

        ``grid`` is MiniGrid's ``env.grid.encode()`` of the full grid, ``pattern_cells`` the
        ``(x, y)`` cells of the trigger pattern (each must be lava in ``grid``; at most 9).
        ``saw_trigger`` restores the episode's flag; ``None`` starts it afresh from this
        observation (as a reset would).
        """
        i, arr, pos = self._check_state(i, grid, agent_pos, agent_dir, step_count)
        cells = sorted({(int(cx), int(cy)) for cx, cy in pattern_cells})
        if len(cells) > MAX_PATTERN_CELLS:
            raise ValueError(f"{len(cells)} pattern cells given, at most {MAX_PATTERN_CELLS}")
        for cx, cy in cells:
            if not (0 <= cx < self.size and 0 <= cy < self.size) or arr[cx, cy, 0] != ge.LAVA:
                raise ValueError(f"pattern cell {(cx, cy)} is not a lava cell of the grid")
        self._write_state(i, arr, pos, agent_dir, step_count)
        self._pat[i] = False
        self._pcells[i] = 0
        for k, (cx, cy) in enumerate(cells):
            self._pat[i, cx, cy] = True
            self._pcells[i, k] = (cx, cy)
        self._pcount[i] = len(cells)
        obs, visible = self._observe_slot(i)
        self._saw[i] = visible if saw_trigger is None else bool(saw_trigger)
        return obs

    def lava_masks(self) -> np.ndarray:
        """(B, N, N) bool, ``[b, x, y]``: where lava lies in every slot (for chance-occurrence counts)."""
        return self._grid[..., 0] == ge.LAVA

    def layout(self, i: int) -> tuple[np.ndarray, tuple[int, int], int, int, tuple[tuple[int, int], ...], bool]:
        """Slot ``i``'s state: ``(grid, agent_pos, agent_dir, step_count, pattern_cells,
        saw_trigger)``, so that ``load_layout(j, *layout(i))`` copies it exactly."""
        i = self._check_index(i)
        cells = tuple(sorted((int(self._pcells[i, k, 0]), int(self._pcells[i, k, 1])) for k in range(self._pcount[i])))
        return (
            self._grid[i].copy(),
            (int(self._pos[i, 0]), int(self._pos[i, 1])),
            int(self._dir[i]),
            int(self._steps[i]),
            cells,
            bool(self._saw[i]),
        )

    def observe(self) -> dict[str, np.ndarray]:
        """The current observation of every env."""
        obs = self._empty_obs(self.num_envs)
        visible = np.zeros(self.num_envs, dtype=np.bool_)
        _observe_kernel(
            self._grid, self._pos, self._dir, self._pcells, self._pcount, self.see_through_walls,
            obs["image"], obs["direction"], visible,
        )
        return obs

    def trigger_visible(self) -> np.ndarray:
        """Whether each env's current observation shows a pattern cell (bool[B])."""
        obs = self._empty_obs(self.num_envs)
        visible = np.zeros(self.num_envs, dtype=np.bool_)
        _observe_kernel(
            self._grid, self._pos, self._dir, self._pcells, self._pcount, self.see_through_walls,
            obs["image"], obs["direction"], visible,
        )
        return visible

