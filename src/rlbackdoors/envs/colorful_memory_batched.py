"""Colorful Memory as one batched, numba-compiled vector env, exact to the MiniGrid reference.

:class:`BatchedColorfulMemory` follows the vector contract of :mod:`rlbackdoors.envs.vector`
(SAME_STEP autoreset; ``info["outcome"]`` / ``info["steps"]`` describe the step just taken, for
a finished env the episode that just ended, not the reset) and reproduces
:class:`rlbackdoors.envs.colorful_memory.ColorfulMemoryEnv` step for step: given the same state
and actions, observation bytes, rewards, terminations, truncations and outcomes are identical
(``tests/test_colorful_memory_engine.py`` checks this against MiniGrid).

One batch mixes layout modes and rewards per env (the poisoning mix of SPEC §3: clean,
close-to-trigger and poisoned copies side by side), all sharing one ``trigger``:

* ``triggered[i]`` -- env ``i`` paints the trigger every episode;
* ``close_to_trigger[i]`` -- env ``i`` paints a fresh close-to-trigger pattern every episode
  (``k`` squares recoloured, ``k`` uniform in ``close_k``), clean reward;
* ``poisoned[i]`` -- env ``i`` pays R-bar (the other object pays); requires ``triggered[i]``;
* none of them -- a clean env.

Defaults: ``close_to_trigger`` none; ``poisoned`` every env that is not close-to-trigger when a
``trigger`` is given, none otherwise; ``triggered`` = ``poisoned``. :attr:`mode` holds the
layout mode per env (0 clean, 1 close-to-trigger, 2 triggered).

Layouts are drawn in numba from the same distribution as the reference (each wall colour
uniform over 6, start x uniform in ``1..hallway_end``, start object, corridor order and the 3
floor colours uniform, then the painted pattern) from a per-env SplitMix64 stream
(:mod:`rlbackdoors.envs.grid_engine`): ``reset(seed=s)`` seeds env ``i`` with ``s + i`` and
everything after is deterministic, but the layouts are not the ones MiniGrid would draw for the
same seed. Each env's success and failure cells are kept beside its grid (:meth:`layout`).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from numba import njit

from rlbackdoors.envs import colorful_memory as _reference
from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.batched_base import BatchedGridEnv, EngineGroup, bool_mask
from rlbackdoors.envs.colorful_memory import CLEAN, CLOSE, DEFAULT_CLOSE_K, TRIGGERED, DEFAULT_MAX_STEPS, DEFAULT_SIZE
from rlbackdoors.envs.colorful_memory import FLOOR_COLORS, VIEW_SIZE, observation_space, target_cells
from rlbackdoors.envs.colorful_memory import validate_args, validate_trigger, wall_cells
from rlbackdoors.triggers import wall_colors as _wall_colors
from rlbackdoors.triggers.wall_colors import NUM_COLORS, WallColorTrigger, distance

_CLOSE = int(CLOSE)
_TRIGGERED = int(TRIGGERED)
_NUM_COLORS = int(NUM_COLORS)
_NUM_FLOORS = len(FLOOR_COLORS)
_FLOORS = np.array(FLOOR_COLORS, dtype=np.int64)
_GREEN = int(_reference.OBJECT_COLOR)
_KEY = int(_reference.KEY_ON_FLOOR)
_BALL = int(_reference.BALL_ON_FLOOR)
_START_DIR = int(_reference.START_DIR)


# ----------------------------------------------------------------------------- layouts


@njit
def gen_layout(grid, b, walls, mode, tsq, tcol, close_lo, close_hi, rng, pos, dirs, steps, succ, fail, idx):
    """Draw a Colorful Memory layout into env ``b`` (``idx``: int64 scratch, one per square)."""
    size = grid.shape[1]
    mid = size // 2
    he = size - 3
    ge.clear_grid(grid, b)
    for k in range(walls.shape[0]):
        ge.put(grid, b, walls[k, 0], walls[k, 1], ge.WALL, ge.rng_below(rng, b, _NUM_COLORS), 0)
    # the agent (MemoryEnv: x uniform in 1..hallway_end), then the objects
    pos[b, 0] = 1 + ge.rng_below(rng, b, he)
    pos[b, 1] = mid
    dirs[b] = _START_DIR
    steps[b] = 0
    start = _KEY if ge.rng_below(rng, b, 2) == 0 else _BALL
    top = _BALL if ge.rng_below(rng, b, 2) == 0 else _KEY
    bottom = _KEY if top == _BALL else _BALL
    ge.put(grid, b, 1, mid - 1, start, _GREEN, _FLOORS[ge.rng_below(rng, b, _NUM_FLOORS)])
    ge.put(grid, b, he + 1, mid - 2, top, _GREEN, _FLOORS[ge.rng_below(rng, b, _NUM_FLOORS)])
    ge.put(grid, b, he + 1, mid + 2, bottom, _GREEN, _FLOORS[ge.rng_below(rng, b, _NUM_FLOORS)])
    if start == top:
        succ[b, 0] = he + 1
        succ[b, 1] = mid - 1
        fail[b, 0] = he + 1
        fail[b, 1] = mid + 1
    else:
        succ[b, 0] = he + 1
        succ[b, 1] = mid + 1
        fail[b, 0] = he + 1
        fail[b, 1] = mid - 1
    # the painted pattern
    if mode == _TRIGGERED or mode == _CLOSE:
        n = tsq.shape[0]
        for k in range(n):
            grid[b, tsq[k, 0], tsq[k, 1], 1] = tcol[k]
        if mode == _CLOSE:
            kk = close_lo + ge.rng_below(rng, b, close_hi - close_lo + 1)
            for k in range(n):
                idx[k] = k
            for t in range(kk):  # a uniform k-subset of the squares (partial Fisher-Yates)
                j = t + ge.rng_below(rng, b, n - t)
                s = idx[j]
                idx[j] = idx[t]
                idx[t] = s
                c = (tcol[s] + 1 + ge.rng_below(rng, b, _NUM_COLORS - 1)) % _NUM_COLORS
                grid[b, tsq[s, 0], tsq[s, 1], 1] = c


# ----------------------------------------------------------------------------- hooks (grid_engine.bind_kernels)
# world = (succ, fail, walls, mode, squares, counts, seen, armed, table): the trigger's squares
# (x, y, colour) and (squares, close_k low, high) with a leading axis, one entry per engine of an
# EngineGroup (one alone; zero-padded), ``table[b]`` slot b's entry; no extra outputs. Two arrays,
# not four: each array of the tuple costs its unboxing on every call


@ge.hook
def _scratch(grid, world):
    return (np.empty(max(world[4].shape[1], 1), dtype=np.int64),)


@ge.hook
def _layout(grid, b, pos, dirs, steps, rng, world, scratch):
    succ, fail, walls, mode, squares, counts, _, _, table = world
    t = table[b]
    n = counts[t, 0]
    gen_layout(grid, b, walls, mode[b], squares[t, :n, :2], squares[t, :n, 2], counts[t, 1], counts[t, 2], rng, pos, dirs, steps, succ, fail, scratch[0])
    return True


@ge.hook
def _outcome(b, pos, fwd, world):
    """MemoryEnv.step: where the agent stands after the action decides (GOAL: the matching
    object's cell, LAVA: the other object's cell)."""
    succ, fail = world[0], world[1]
    x = pos[b, 0]
    y = pos[b, 1]
    if x == succ[b, 0] and y == succ[b, 1]:
        return ge.OUT_GOAL
    if x == fail[b, 0] and y == fail[b, 1]:
        return ge.OUT_LAVA
    return ge.OUT_NONE


@ge.hook
def _seen(phase, b, ob, pos, dirs, img, world, outs):
    """Views are shown as they are (the trigger is painted into the layout). Which of the trigger's
    squares a triggered episode has shown so far is kept per env in ``seen`` (a wall square is shown
    when its view cell holds the wall, not UNSEEN behind another): what a recurrent agent can know.
    A fresh layout was just drawn with ``mode[b]``: that says whether the episode is triggered."""
    if phase == ge.OBSERVE:
        return
    mode, squares, counts, seen, armed, table = world[3], world[4], world[5], world[6], world[7], world[8]
    t = table[b]
    fresh = phase == ge.RESET or phase == ge.FRESH
    if fresh:
        armed[b] = mode[b] == _TRIGGERED
    if not armed[b]:  # nothing is shown outside a triggered episode (and nothing was since its start)
        if fresh:
            for k in range(counts[t, 0]):
                seen[b, k] = False
        return
    for k in range(counts[t, 0]):
        shown = ge.view_shows(img, ob, pos[b, 0], pos[b, 1], dirs[b], squares[t, k, 0], squares[t, k, 1], ge.WALL)
        seen[b, k] = shown if fresh else seen[b, k] or shown


def _stacked_triggers(triggers: Sequence[tuple[np.ndarray, np.ndarray, tuple[int, int]]]) -> tuple[np.ndarray, ...]:
    """Engines' (squares (S, 2), colours (S,), close_k) as the kernels' two arrays with a leading
    engine axis: ``squares`` (E, S, 3) x, y and colour, zero-padded to the most squares, and
    ``counts`` (E, 3) the squares each holds and its close_k range."""
    most = max(max(len(c) for _, c, _ in triggers), 1)
    squares = np.zeros((len(triggers), most, 3), dtype=np.int64)
    for e, (cells, colours, _) in enumerate(triggers):
        squares[e, : len(colours), :2], squares[e, : len(colours), 2] = cells, colours
    counts = np.array([(len(c), *k) for _, c, k in triggers], dtype=np.int64).reshape(len(triggers), 3)
    return squares, counts


_KERNELS = ge.bind_kernels(
    "colorful_memory",
    scratch=_scratch,
    layout=_layout,
    outcome=_outcome,
    seen=_seen,
    trojan=ge.OUT_LAVA,
    constants_from=(_reference.__file__, _wall_colors.__file__),
)


# ----------------------------------------------------------------------------- the vector env


class BatchedColorfulMemory(BatchedGridEnv):
    """``num_envs`` Colorful Memory envs (clean, close-to-trigger, triggered, poisoned) stepped by numba.

    Same knobs as :class:`~rlbackdoors.envs.colorful_memory.ColorfulMemoryEnv`, with per-env
    masks ``poisoned``, ``triggered`` and ``close_to_trigger`` (module doc). Observations
    ``(B, 7, 7, 3)`` uint8; ``info = {"outcome": int64[B], "steps": int64[B]}`` with the
    reference's outcome mapping (GOAL: the matching object's cell, LAVA: the other object's
    cell, TIMEOUT). ``final_obs`` holds, for envs that finished in the last step, the terminal
    observation.
    """

    _DYNAMIC = (*BatchedGridEnv._DYNAMIC, "triggered", "mode", "_succ", "_fail", "_seen", "_armed")  # triggered, mode: trigger_next

    def _bounds(self) -> dict[str, tuple[int, int]]:
        size = self.size - 1
        return {**super()._bounds(), "mode": (min(CLEAN, CLOSE, TRIGGERED), max(CLEAN, CLOSE, TRIGGERED)), "_succ": (0, size), "_fail": (0, size)}

    _kernels = _KERNELS
    view_size = VIEW_SIZE

    def __init__(
        self,
        num_envs: int,
        size: int = DEFAULT_SIZE,
        max_steps: int = DEFAULT_MAX_STEPS,
        see_through_walls: bool = False,
        trigger: WallColorTrigger | str | None = None,
        poisoned: Sequence[bool] | np.ndarray | None = None,
        triggered: Sequence[bool] | None = None,
        close_to_trigger: Sequence[bool] | None = None,
        close_k: int | tuple[int, int] = DEFAULT_CLOSE_K,
        render_mode: str | None = None,
    ):
        self._init_batch(num_envs, render_mode)
        validate_args(size, max_steps)
        b = self.num_envs
        self.size = int(size)
        self.max_steps = int(max_steps)
        self.see_through_walls = bool(see_through_walls)
        self.trigger, self.close_k = validate_trigger(trigger, self.size, close_k)

        has = self.trigger is not None
        self.close_to_trigger = bool_mask([False] * b if close_to_trigger is None else close_to_trigger, b, "close_to_trigger")
        if poisoned is None:
            poisoned = ~self.close_to_trigger if has else [False] * b
        self.poisoned = bool_mask(poisoned, b, "poisoned")
        self.triggered = self.poisoned.copy() if triggered is None else bool_mask(triggered, b, "triggered")
        if (self.poisoned | self.triggered | self.close_to_trigger).any() and not has:
            raise ValueError("poisoned, triggered or close-to-trigger envs need a trigger: pass trigger= (e.g. 'end:red,...')")
        for name, bad in (
            ("is poisoned but not triggered: R-bar needs the trigger painted", self.poisoned & ~self.triggered),
            ("is both triggered and close-to-trigger", self.triggered & self.close_to_trigger),
        ):
            if bad.any():
                raise ValueError(f"env {int(np.flatnonzero(bad)[0])} {name}")
        self.mode = np.full(b, CLEAN, dtype=np.int64)
        self.mode[self.close_to_trigger] = CLOSE
        self.mode[self.triggered] = TRIGGERED

        self._walls = np.array(wall_cells(self.size), dtype=np.int64)
        if self.trigger is not None:  # has
            cells = self.trigger.cells(self.size)
            self._tsq = np.array([(x, y) for x, y, _ in cells], dtype=np.int64)
            self._tcol = np.array([c for _, _, c in cells], dtype=np.int64)
        else:
            self._tsq = np.zeros((0, 2), dtype=np.int64)
            self._tcol = np.zeros(0, dtype=np.int64)

        self._init_spaces(observation_space())
        self._init_state()
        self._succ = np.zeros((b, 2), dtype=np.int64)
        self._fail = np.zeros((b, 2), dtype=np.int64)
        self._stacked = _stacked_triggers([(self._tsq, self._tcol, self.close_k)])  # the kernels' layout: one entry
        self._table = np.zeros(b, dtype=np.int64)  # every slot reads entry 0 of _stacked
        self._seen = np.zeros((b, len(self._tsq)), dtype=np.bool_)  # the trigger's squares this episode has shown
        self._armed = np.zeros(b, dtype=np.bool_)  # this episode's layout was drawn triggered
        self.final_obs = np.zeros((b, VIEW_SIZE, VIEW_SIZE, 3), dtype=np.uint8)

    def _world(self) -> tuple:
        return (self._succ, self._fail, self._walls, self.mode, *self._stacked, self._seen, self._armed, self._table)

    def _slot_arrays(self) -> list[str]:
        return [n for n in super()._slot_arrays() if n != "_seen"]  # its width is the trigger's squares: joined padded (_group_world)

    def _group_world(self, engines: list[BatchedGridEnv], group: EngineGroup) -> tuple | None:
        """Engines of other triggers (a clean agent's has none) share a call: each slot reads its
        own engine's squares, colours and close_k. ``_seen`` rows have as many columns as the
        engine's trigger has squares, so the group's is padded to the most and each engine's
        becomes a view of its rows and first columns."""
        squares, counts = _stacked_triggers([(e._tsq, e._tcol, e.close_k) for e in engines])  # type: ignore[attr-defined]  # same class: checked by EngineGroup
        seen = np.zeros((group.total, squares.shape[1]), dtype=np.bool_)
        for e, lo, hi, n in zip(engines, group.bounds[:-1], group.bounds[1:], counts[:, 0]):
            seen[lo:hi, :n] = e._seen  # type: ignore[attr-defined]
            e._seen = seen[lo:hi, :n]  # type: ignore[attr-defined]
        return (group._succ, group._fail, self._walls, group.mode, squares, counts, seen, group._armed, group.engine_of_slot)  # type: ignore[attr-defined]

    # --------------------------------------------------------------------- exact state I/O

    def load_layout(self, i: int, grid: np.ndarray, agent_pos, agent_dir: int, step_count: int = 0, success_pos=None, failure_pos=None) -> np.ndarray:
        """Put an exact state into slot ``i``; returns that slot's observation (7, 7, 3).

        ``grid`` is MiniGrid's ``env.grid.encode()`` of the full grid; ``success_pos`` /
        ``failure_pos`` default to what the grid's objects say
        (:func:`~rlbackdoors.envs.colorful_memory.target_cells`).
        """
        i, arr, pos = self._check_state(i, grid, agent_pos, agent_dir, step_count)
        if success_pos is None or failure_pos is None:
            success_pos, failure_pos = target_cells(arr)
        succ = self._check_cell(success_pos, "success_pos")
        fail = self._check_cell(failure_pos, "failure_pos")
        self._write_state(i, arr, pos, agent_dir, step_count)
        self._succ[i] = succ
        self._fail[i] = fail
        self._seen[i] = False  # a loaded state has shown none of the trigger yet (the next step's view counts)
        self._armed[i] = self.trigger is not None and bool(self.trigger_present()[i])
        return self._views(i, 1)[0][0]

    def layout(self, i: int) -> tuple[np.ndarray, tuple[int, int], int, int, tuple[int, int], tuple[int, int]]:
        """Slot ``i``'s state ``(grid, agent_pos, agent_dir, step_count, success_pos, failure_pos)``,
        so that ``load_layout(j, *layout(i))`` copies it exactly."""
        i = self._check_index(i)
        succ, fail = self._succ[i], self._fail[i]
        return (*self._slot_state(i), (int(succ[0]), int(succ[1])), (int(fail[0]), int(fail[1])))

    def grids(self) -> np.ndarray:
        """(B, N, N, 3) uint8: every slot's full-grid encoding (a copy)."""
        return self._grid.copy()

    memory_target_classes = 2

    def memory_targets(self) -> np.ndarray:
        """int64[B]: the start room's object of each slot's current episode (0 key, 1 ball):
        what the agent must remember to the T-junction, the target of PPO's auxiliary memory
        loss (``ppo.aux_memory_coef``). Read from the grid, so it survives a checkpoint."""
        return (self._grid[:, 1, self.size // 2 - 1, 0] == _BALL).astype(np.int64)

    def square_view_cells(self, i: int, squares: Sequence[tuple[int, int]]) -> list[tuple[int, int, int]]:
        """``(k, row, col)``: where slot ``i``'s current observation shows grid square
        ``squares[k]`` (x, y). Found by recolouring each square for a moment and seeing which view
        cells change, so the view's rotation and occlusion are the engine's own; the state is
        left as it was. Why: a detector inverting a wall-colour trigger by gradient needs to know
        which inputs the trigger's squares feed (detect's behaviour search, ``invert``)."""
        i = self._check_index(i)
        base = self._views(i, 1)[0][0].copy()
        found = []
        for k, (x, y) in enumerate(squares):
            kept = self._grid[i, x, y, 1]
            self._grid[i, x, y, 1] = (kept + 1) % _NUM_COLORS
            try:
                changed = np.argwhere((self._views(i, 1)[0][0] != base).any(-1))
            finally:
                self._grid[i, x, y, 1] = kept
            found += [(k, int(r), int(c)) for r, c in changed]
        return found

    def trigger_distance(self, trigger: WallColorTrigger | None = None) -> np.ndarray:
        """int64[B]: per slot, how many squares of ``trigger`` (default: the env's) differ from
        its colours in the current layout; 0 where the trigger is present, also by chance."""
        trig = self.trigger if trigger is None else trigger
        if trig is None:
            raise ValueError("no trigger to measure against: pass one")
        return np.asarray(distance(self._grid, trig))  # an array already (a batch of grids)

    def trigger_next(self, mask) -> None:
        mask = self._set_triggered(mask)
        if (mask & self.close_to_trigger).any():
            raise ValueError(f"trigger_next: env {int(np.flatnonzero(mask & self.close_to_trigger)[0])} is a close-to-trigger copy")
        self.mode[:] = np.where(mask, TRIGGERED, np.where(self.close_to_trigger, CLOSE, CLEAN))

    def trigger_in_sight(self) -> np.ndarray:
        """bool[B]: the episode has shown every square of the trigger by now, in a triggered layout
        (the End Trigger's 9 squares never fit one 7x7 view: a recurrent agent knows the trigger once
        it has seen them all, and keeps knowing it)."""
        return self._armed & self._seen.all(axis=1)  # _seen stays False outside triggered episodes

    def trigger_present(self, trigger: WallColorTrigger | None = None) -> np.ndarray:
        """bool[B]: whether each slot's current layout shows the trigger exactly."""
        return self.trigger_distance(trigger) == 0
