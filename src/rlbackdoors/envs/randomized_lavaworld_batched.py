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
from numba import njit

from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs import randomized_lavaworld as _reference
from rlbackdoors.envs.batched_base import BatchedGridEnv, EngineGroup, bool_mask
from rlbackdoors.envs.randomized_lavaworld import DEFAULT_MAX_STEPS, DEFAULT_NUM_LAVA, DEFAULT_SIZE, VIEW_SIZE
from rlbackdoors.envs.randomized_lavaworld import layout_error, observation_space, validate_layout_args, validate_trigger
from rlbackdoors.triggers.pattern import MAX_PATTERN_CELLS, PatternTrigger, as_pattern_trigger

_MAX_TRIES = int(_reference.MAX_LAYOUT_TRIES)
_START_X, _START_Y = _reference.START
_START_DIR = int(_reference.START_DIR)


# ----------------------------------------------------------------------------- layouts


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
    grid,
    b,
    num_lava,
    which,
    rot_cells,
    rot_n,
    nrot,
    offs,
    offs_n,
    rng,
    pos,
    dirs,
    steps,
    pat,
    pcells,
    pcount,
    lava,
    seen,
    queue,
    free,
):
    """Draw a solvable Randomized LavaWorld layout into env ``b``; False if none was found.

    ``which``: the pattern inserted, -1 none, 0 the trigger, ``k`` > 0 the near-trigger pattern
    ``k`` (``poison.evasion.near``: ordinary lava, never marked as the pattern). The tables hold
    one row per pattern (row 0 the trigger's), ``nrot`` = rotations per pattern.
    ``lava``/``seen`` (size, size) bool, ``queue``/``free`` (size*size,) int64 are scratch.
    """
    size = grid.shape[1]
    gx = size - 2
    npat = 0
    nins = 0
    for _ in range(_MAX_TRIES):
        for x in range(size):
            for y in range(size):
                lava[x, y] = False
        npat = 0
        nins = 0
        if which >= 0:
            r = ge.rng_below(rng, b, nrot[which])
            o = ge.rng_below(rng, b, offs_n[which, r])
            ox = offs[which, r, o, 0]
            oy = offs[which, r, o, 1]
            nins = rot_n[which, r]
            for k in range(nins):
                cx = ox + rot_cells[which, r, k, 0]
                cy = oy + rot_cells[which, r, k, 1]
                lava[cx, cy] = True
                pcells[b, k, 0] = cx
                pcells[b, k, 1] = cy
            if which == 0:
                npat = nins
        # free interior cells in x-major order (as the reference lists them)
        nfree = 0
        for x in range(1, size - 1):
            for y in range(1, size - 1):
                if (x == _START_X and y == _START_Y) or (x == gx and y == gx) or lava[x, y]:
                    continue
                free[nfree] = x * size + y
                nfree += 1
        # a uniform subset of num_lava - npat of them (partial Fisher-Yates)
        for t in range(num_lava - nins):
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
    for k in range(pcount[b]):
        if ge.view_shows(img, ob, ax, ay, adir, pcells[b, k, 0], pcells[b, k, 1], ge.LAVA):
            return True
    return False


@njit
def pattern_whole_in_view(pcells, pcount, pos, dirs, img, out):
    """``out[b]``: env ``b``'s view ``img[b]`` shows every cell of its pattern (a pattern there at all).

    One cell of a pattern looks like any other lava; only the whole pattern is the trigger an
    agent can tell apart, so this is what the attacks that poison frames in sight of it ask.
    """
    for b in range(img.shape[0]):
        whole = pcount[b] > 0
        for k in range(pcount[b]):
            if not ge.view_shows(img, b, pos[b, 0], pos[b, 1], dirs[b], pcells[b, k, 0], pcells[b, k, 1], ge.LAVA):
                whole = False
                break
        out[b] = whole


# ----------------------------------------------------------------------------- hooks (grid_engine.bind_kernels)
# world = (pat, pcells, pcount, saw, num_lava, triggered, near, table, rot_cells, rot_n, nrot, offs,
# offs_n, npatterns): the placement tables (module _placement_tables) with a leading axis, one entry per
# engine of an EngineGroup (one alone), and ``table[b]`` slot b's entry;
# outs = (direction, trigger_visible, saw_trigger, final direction, and a fresh layout's pattern cells,
# their count and whether its first view shows one: drawn_cells, drawn_count, drawn_saw)


@ge.hook
def _scratch(grid, world):
    size = grid.shape[1]
    lava = np.empty((size, size), dtype=np.bool_)
    seen = np.empty((size, size), dtype=np.bool_)
    return lava, seen, np.empty(size * size, dtype=np.int64), np.empty(size * size, dtype=np.int64)


@ge.hook
def _layout(grid, b, pos, dirs, steps, rng, world, scratch):
    pat, pcells, pcount, _, num_lava, triggered, near, table, rot_cells, rot_n, nrot, offs, offs_n, npatterns = world
    lava, seen, queue, free = scratch
    t = table[b]
    which = -1
    if triggered[b]:
        which = 0
    elif near[b]:  # one of the near-trigger patterns, drawn from the slot's own stream
        which = 1 + ge.rng_below(rng, b, npatterns[t] - 1)
    return gen_layout(
        grid,
        b,
        num_lava,
        which,
        rot_cells[t],
        rot_n[t],
        nrot[t],
        offs[t],
        offs_n[t],
        rng,
        pos,
        dirs,
        steps,
        pat,
        pcells,
        pcount,
        lava,
        seen,
        queue,
        free,
    )


@ge.hook
def _outcome(b, pos, fwd, world):
    """Lava ends the episode as PATTERN_LAVA when it is a cell of the inserted pattern."""
    if fwd == ge.GOAL:
        return ge.OUT_GOAL
    if fwd == ge.LAVA:
        return ge.OUT_PATTERN if world[0][b, pos[b, 0], pos[b, 1]] else ge.OUT_LAVA
    return ge.OUT_NONE


@ge.hook
def _seen(phase, b, ob, pos, dirs, img, world, outs):
    """The direction, and the reference env's trigger flags: ``trigger_visible`` for the view
    just returned (a finished env's terminal one), ``saw_trigger`` for it or any earlier view of
    the episode (kept per env in ``saw``; a fresh episode starts from its first view)."""
    pcells, pcount, saw = world[1], world[2], world[3]
    direction, visible, saw_out, final_dir, drawn_cells, drawn_count, drawn_saw = outs
    if phase == ge.FINAL:
        final_dir[b] = dirs[b]
    else:
        direction[ob] = dirs[b]
    v = pattern_visible(pcells, pcount, b, pos[b, 0], pos[b, 1], dirs[b], img, ob)
    if phase == ge.FRESH:
        saw[b] = v
        # the fresh layout's pattern, by row: what an engine elsewhere that takes its layouts from
        # Kernels.layouts (envs.grid_jax) holds beside the grid (the whole row, as the slot holds it)
        for k in range(pcells.shape[1]):
            drawn_cells[ob, k, 0] = pcells[b, k, 0]
            drawn_cells[ob, k, 1] = pcells[b, k, 1]
        drawn_count[ob] = pcount[b]
        drawn_saw[ob] = v
        return
    visible[ob] = v
    if phase == ge.RESET:
        saw[b] = v
        saw_out[b] = v
    elif phase == ge.FINAL:
        saw_out[b] = saw[b] or v
    elif phase == ge.STEP:
        s = saw[b] or v
        saw[b] = s
        saw_out[b] = s


_KERNELS = ge.bind_kernels(
    "randomized_lavaworld",
    scratch=_scratch,
    layout=_layout,
    outcome=_outcome,
    seen=_seen,
    trojan=ge.OUT_PATTERN,
    constants_from=(_reference.__file__,),
)


# ----------------------------------------------------------------------------- the vector env


def _placement_tables(patterns: Sequence[PatternTrigger | None], placements: Sequence) -> tuple[np.ndarray, ...]:
    """Rotations and allowed offsets of each pattern (row 0 the trigger, then the near-trigger
    patterns) as dense arrays for the kernels (dummies without trigger): ``rot_cells`` (P, R, 9, 2),
    ``rot_n`` (P, R), ``nrot`` (P,) rotations per pattern, ``offs`` (P, R, M, 2), ``offs_n`` (P, R)."""
    rotations = [p.rotations() if p is not None else () for p in patterns]
    P = len(patterns)
    r = max((len(rots) for rots in rotations), default=1) or 1
    m = max((len(o) for per in placements for o in per), default=1)
    rot_cells = np.zeros((P, r, MAX_PATTERN_CELLS, 2), dtype=np.int64)
    rot_n = np.zeros((P, r), dtype=np.int64)
    nrot = np.ones(P, dtype=np.int64)
    offs = np.zeros((P, r, m, 2), dtype=np.int64)
    offs_n = np.ones((P, r), dtype=np.int64)
    for i, (rots, places) in enumerate(zip(rotations, placements)):
        nrot[i] = max(len(rots), 1)
        for k, rot in enumerate(rots):
            rot_n[i, k] = len(rot.cells)
            rot_cells[i, k, : len(rot.cells)] = rot.cells
            offs[i, k, : len(places[k])] = places[k]
            offs_n[i, k] = len(places[k])
    return rot_cells, rot_n, nrot, offs, offs_n


def _stacked_tables(tables: Sequence[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, ...]:
    """Several engines' :func:`_placement_tables` as one set with a leading engine axis (each
    zero-padded to the largest; the kernels read only the counted entries), and each entry's
    pattern count (``npatterns``), for one kernel call over their slots."""
    out = []
    for arrays in zip(*tables):
        shape = tuple(max(a.shape[d] for a in arrays) for d in range(arrays[0].ndim))
        stacked = np.zeros((len(arrays), *shape), dtype=np.int64)
        for e, a in enumerate(arrays):
            stacked[e][tuple(slice(0, n) for n in a.shape)] = a
        out.append(stacked)
    return (*out, np.array([len(t[2]) for t in tables], dtype=np.int64))


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

    _DYNAMIC = (*BatchedGridEnv._DYNAMIC, "triggered", "near", "_pat", "_pcells", "_pcount", "_saw")  # triggered / near: trigger_next / near_next

    def _bounds(self) -> dict[str, tuple[int, int]]:
        return {**super()._bounds(), "_pcells": (0, self.size - 1), "_pcount": (0, MAX_PATTERN_CELLS)}

    _kernels = _KERNELS
    view_size = VIEW_SIZE

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
        near_patterns: Sequence[PatternTrigger | str] = (),
    ):
        self._init_batch(num_envs, render_mode)
        validate_layout_args(size, num_lava, max_steps)
        self.size = int(size)
        self.num_lava = int(num_lava)
        self.max_steps = int(max_steps)
        self.see_through_walls = bool(see_through_walls)
        self.trigger = as_pattern_trigger(trigger)
        placements = validate_trigger(self.trigger, self.size, self.num_lava)
        # near-trigger patterns (poison.evasion.near): layouts ``near_next`` switches on hold one,
        # as ordinary lava paying the clean reward, so a trojan learns the exact pattern only
        self.near_patterns = tuple(as_pattern_trigger(p) for p in near_patterns)
        if self.near_patterns and self.trigger is None:
            raise ValueError("near-trigger patterns need the trigger they are near to: pass trigger=")
        near_places = [validate_trigger(p, self.size, self.num_lava) for p in self.near_patterns]
        self._tables = _placement_tables((self.trigger, *self.near_patterns), (placements, *near_places))
        self._stacked = _stacked_tables([self._tables])  # the kernels' layout: one entry, every slot's

        b = self.num_envs
        if poisoned is None:
            poisoned = [self.trigger is not None] * b
        self.poisoned = bool_mask(poisoned, b, "poisoned")
        self.triggered = self.poisoned.copy() if triggered is None else bool_mask(triggered, b, "triggered")
        self.near = np.zeros(b, dtype=np.bool_)
        if (self.poisoned | self.triggered).any() and self.trigger is None:
            raise ValueError("poisoned or triggered envs need a trigger: pass trigger= (e.g. 'cross')")
        if (self.poisoned & ~self.triggered).any():
            bad = int(np.flatnonzero(self.poisoned & ~self.triggered)[0])
            raise ValueError(f"env {bad} is poisoned but not triggered: R-bar only pays on the trigger pattern")

        self._init_spaces(observation_space())
        self._init_state()
        n = self.size
        self._pat = np.zeros((b, n, n), dtype=np.bool_)
        self._pcells = np.zeros((b, MAX_PATTERN_CELLS, 2), dtype=np.int64)
        self._pcount = np.zeros(b, dtype=np.int64)
        self._saw = np.zeros(b, dtype=np.bool_)
        self._table = np.zeros(b, dtype=np.int64)  # every slot reads entry 0 of _stacked
        self.final_obs = {
            "image": np.zeros((b, VIEW_SIZE, VIEW_SIZE, 3), dtype=np.uint8),
            "direction": np.zeros(b, dtype=np.int64),
        }

    # --------------------------------------------------------------------- driver hooks

    def _world(self) -> tuple:
        return (self._pat, self._pcells, self._pcount, self._saw, self.num_lava, self.triggered, self.near, self._table, *self._stacked)

    def _group_world(self, engines: list[BatchedGridEnv], group: EngineGroup) -> tuple | None:
        """Engines of other triggers and near-trigger patterns (a clean agent's, an env mix's, an
        evasive variant's) share a call: each slot reads its own engine's placement tables."""
        if any(e.num_lava != self.num_lava for e in engines):  # type: ignore[attr-defined]  # same class: checked by EngineGroup
            return None
        stacked = _stacked_tables([e._tables for e in engines])  # type: ignore[attr-defined]
        return (group._pat, group._pcells, group._pcount, group._saw, self.num_lava, group.triggered, group.near, group.engine_of_slot, *stacked)  # type: ignore[attr-defined]

    def _outputs(self, n: int) -> tuple:
        return (
            np.empty(n, dtype=np.int64),
            np.empty(n, dtype=np.bool_),
            np.empty(n, dtype=np.bool_),
            self.final_obs["direction"],
            np.empty((n, MAX_PATTERN_CELLS, 2), dtype=np.int64),  # a fresh layout's pattern cells (FRESH rows, written whole; read only there)
            np.empty(n, dtype=np.int64),
            np.empty(n, dtype=np.bool_),
        )

    def _observation(self, img: np.ndarray, outs: tuple) -> dict[str, np.ndarray]:
        return {"image": img, "direction": outs[0]}

    def _extra_info(self, outs: tuple) -> dict:
        return {"trigger_visible": outs[1], "saw_trigger": outs[2]}

    def _final_image(self) -> np.ndarray:
        return self.final_obs["image"]

    def _layout_error(self, env: int | None) -> Exception:
        trigger = self.trigger if env is None or self.triggered[env] else None
        return layout_error(self.size, self.num_lava, trigger)

    # --------------------------------------------------------------------- exact state I/O

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
        img, (direction, visible, *_) = self._views(i, 1)
        self._saw[i] = bool(visible[0]) if saw_trigger is None else bool(saw_trigger)
        return {"image": img[0], "direction": int(direction[0])}

    def lava_masks(self) -> np.ndarray:
        """(B, N, N) bool, ``[b, x, y]``: where lava lies in every slot (for chance-occurrence counts)."""
        return self._grid[..., 0] == ge.LAVA

    def layout(self, i: int) -> tuple[np.ndarray, tuple[int, int], int, int, tuple[tuple[int, int], ...], bool]:
        """Slot ``i``'s state: ``(grid, agent_pos, agent_dir, step_count, pattern_cells,
        saw_trigger)``, so that ``load_layout(j, *layout(i))`` copies it exactly."""
        i = self._check_index(i)
        cells = tuple(sorted((int(self._pcells[i, k, 0]), int(self._pcells[i, k, 1])) for k in range(self._pcount[i])))
        return (*self._slot_state(i), cells, bool(self._saw[i]))

    def trigger_visible(self) -> np.ndarray:
        """Whether each env's current observation shows a pattern cell (bool[B])."""
        return self._views(0, self.num_envs)[1][1]

    def trigger_next(self, mask) -> None:
        self._set_triggered(mask)

    def near_next(self, mask) -> None:
        """Slots whose next layouts hold a near-trigger pattern (drawn per layout) instead of none;
        a slot whose next layout holds the trigger keeps it."""
        mask = bool_mask(mask, self.num_envs, "near_next")
        if mask.any() and not self.near_patterns:
            raise ValueError("near_next: this engine was built without near-trigger patterns (near_patterns=)")
        self.near[:] = mask

    def trigger_in_sight(self) -> np.ndarray:
        """bool[B]: the current observation shows the whole pattern (a feed-forward agent's only
        evidence of the trigger; a part of it is lava like any other). Not ``trigger_visible``,
        which is any one pattern cell (the reference env's flag)."""
        img = self._views(0, self.num_envs)[0]
        out = np.empty(self.num_envs, dtype=np.bool_)
        pattern_whole_in_view(self._pcells, self._pcount, self._pos, self._dir, img, out)
        return out
