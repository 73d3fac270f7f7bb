"""What every batched grid engine shares: the gymnasium driver, argument checks, seeding, slots.

The engines differ only in their layout generators, terminal rules and extra state, which
they hand to :func:`rlbackdoors.envs.grid_engine.bind_kernels` as hooks; reset / step /
observe (argument checks, output buffers, SAME_STEP autoreset, ``final_obs``, info) and the
checks on num_envs, per-env masks, seeds, actions and slot indices are the same and live here,
so every world behaves, and every error reads, the same.
"""

from __future__ import annotations

import collections
import os
import time
from typing import Any, Sequence

import numba
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from rlbackdoors.envs import grid_engine as ge

NUM_ACTIONS = 3
ACTIONS_DOC = f"Discrete({NUM_ACTIONS}) (0 left, 1 right, 2 forward)"


def seed_array(seed, num_envs: int) -> np.ndarray:
    """Per-env uint64 seeds: ``seed + i`` for an int, a given list, or fresh entropy for None."""
    if seed is None:
        return np.random.SeedSequence().generate_state(num_envs, dtype=np.uint64)
    if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
        seeds = [int(seed) + i for i in range(num_envs)]
    else:
        seeds = list(seed)
        if len(seeds) != num_envs:
            raise ValueError(f"got {len(seeds)} seeds for {num_envs} envs")
    fresh = None
    out = np.empty(num_envs, dtype=np.uint64)
    for i, s in enumerate(seeds):
        if s is None:
            if fresh is None:
                fresh = np.random.SeedSequence().generate_state(num_envs, dtype=np.uint64)
            out[i] = fresh[i]
            continue
        if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or not 0 <= int(s) < 2**64:
            raise ValueError(f"seed {s!r} must be a non-negative integer below 2**64 (or None)")
        out[i] = int(s)
    return out


def bool_mask(values, num_envs: int, name: str) -> np.ndarray:
    """A per-env bool mask of exactly ``num_envs`` entries (a copy)."""
    arr = np.asarray(values, dtype=np.bool_).copy()
    if arr.shape != (num_envs,):
        raise ValueError(f"{name} mask has shape {arr.shape}, expected ({num_envs},)")
    return arr


# Largest codes a grid cell may hold: MiniGrid's object types (plus our objects on coloured floor,
# 11 and 12), its 6 colours, and states (door states, or a floor colour under an object).
MAX_OBJECT, MAX_COLOR, MAX_STATE = 12, 5, 5


def copy_value(value):
    return value.copy() if isinstance(value, np.ndarray) else value


def switchable(envs) -> np.ndarray:
    """(B,) bool: the copies an attack may switch to a trigger layout (``trigger_next``): all but
    the close-to-trigger copies, which stay near-miss negatives (their engine refuses the switch).
    One rule for the attack seam and the compiled trainer's layout queues."""
    return ~np.asarray(getattr(envs, "close_to_trigger", np.zeros(envs.num_envs, dtype=bool)), dtype=bool)


class BatchedGridEnv(VectorEnv):
    """Base of the numba engines: SAME_STEP autoreset, B envs in one process, no rendering.

    A world sets :attr:`_kernels` (its :func:`~rlbackdoors.envs.grid_engine.bind_kernels`) and
    supplies :meth:`_world` (the state and parameters its hooks read); worlds with more than an
    image per observation also override :meth:`_outputs`, :meth:`_observation`,
    :meth:`_extra_info` and :meth:`_final_image`. ``final_obs`` holds, for envs that finished in
    the last step, the observation of the terminal state (what the single env returned before
    being reset).
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}
    _kernels: ge.Kernels
    # "module:Class" of the world's engine on a torch device (envs.grid_device), or None
    device_engine: str | None = None
    view_size: int  # MiniGrid's agent_view_size, the world's VIEW_SIZE
    size: int  # set by the world's __init__
    see_through_walls: bool
    max_steps: int
    final_obs: Any  # the world's terminal observations: an array, or a dict of arrays
    poisoned: np.ndarray  # per env: pays R-bar
    triggered: np.ndarray  # per env: its layouts hold the trigger (worlds whose trigger is a layout)

    def _init_batch(self, num_envs, render_mode) -> int:
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs={num_envs!r} must be a positive integer")
        if render_mode is not None:
            raise ValueError(f"render_mode={render_mode!r} is not supported by {type(self).__name__} (use None)")
        self.num_envs = int(num_envs)
        self.render_mode = None
        self._has_reset = False
        return self.num_envs

    def _init_spaces(self, single_observation_space: spaces.Space) -> None:
        self.single_observation_space = single_observation_space
        self.single_action_space = spaces.Discrete(NUM_ACTIONS)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)

    def _init_state(self) -> None:
        """The per-env state every world has (a world adds its own arrays, then ``final_obs``)."""
        b, n = self.num_envs, self.size
        self._grid = np.zeros((b, n, n, 3), dtype=np.uint8)
        self._pos = np.ones((b, 2), dtype=np.int64)
        self._dir = np.zeros(b, dtype=np.int64)
        self._steps = np.zeros(b, dtype=np.int64)
        self._rng = np.zeros(b, dtype=np.uint64)

    def _images(self, n: int) -> np.ndarray:
        return np.empty((n, self.view_size, self.view_size, 3), dtype=np.uint8)

    # --------------------------------------------------------------------- what a world supplies

    def _world(self) -> tuple:
        """The per-env state and parameters the world's hooks read and write (kernel ``world``)."""
        raise NotImplementedError

    def _outputs(self, n: int) -> tuple:
        """Fresh per-call outputs the world's hooks fill for ``n`` envs (kernel ``outs``)."""
        return ()

    def _observation(self, img: np.ndarray, outs: tuple):
        """The observation made of the rendered views and the world's outputs."""
        return img

    def _extra_info(self, outs: tuple) -> dict:
        """What the world adds to reset's and step's info."""
        return {}

    def _final_image(self) -> np.ndarray:
        """Where the step kernel writes terminal views."""
        return self.final_obs

    def _layout_error(self, env: int | None) -> Exception:
        """The error for a reset (``env``) or autoreset (None) that found no layout."""
        return RuntimeError(f"{type(self).__name__} found no layout")

    # --------------------------------------------------------------------- gymnasium API

    def reset(self, *, seed: int | Sequence[int | None] | None = None, options: dict | None = None):
        seeds = seed_array(seed, self.num_envs)
        img, outs = self._images(self.num_envs), self._outputs(self.num_envs)
        bad = self._kernels.reset(
            self._grid,
            self._pos,
            self._dir,
            self._steps,
            self._rng,
            seeds,
            self.see_through_walls,
            self._world(),
            img,
            outs,
        )
        if bad >= 0:
            raise self._layout_error(bad)
        return self._observation(img, outs), self._reset_info(**self._extra_info(outs))

    def step(self, actions):
        acts = self._check_actions(actions)
        img, outs = self._images(self.num_envs), self._outputs(self.num_envs)
        reward, terminated, truncated, outcome, steps = step_slots(self, self, acts, self.poisoned, self._world(), img, self._final_image(), outs)
        info = {"outcome": outcome, "steps": steps, **self._extra_info(outs)}
        return self._observation(img, outs), reward, terminated, truncated, info

    def _views(self, first: int, n: int) -> tuple[np.ndarray, tuple]:
        """Views and world outputs of envs ``first .. first + n - 1``, changing no state."""
        img, outs = self._images(n), self._outputs(n)
        self._kernels.observe(self._grid, self._pos, self._dir, self.see_through_walls, self._world(), first, img, outs)
        return img, outs

    def observe(self):
        """The current observation of every env (with its trigger, where the world applies one)."""
        return self._observation(*self._views(0, self.num_envs))

    # --------------------------------------------------------------------- layout triggers, per episode

    def trigger_next(self, mask) -> None:
        """Which slots' next episodes hold the trigger (bool[B]), read at every (auto)reset.

        An attack poisoning whole episodes of a layout-trigger world sets this before each step
        (a slot that finishes in that step starts its next episode with or without the trigger);
        R-bar stays the attack's, so the slots set here must not be ``poisoned`` ones.
        """
        raise NotImplementedError(f"{type(self).__name__} has no per-episode trigger switch")

    def _set_triggered(self, mask) -> np.ndarray:
        mask = bool_mask(mask, self.num_envs, "trigger_next")
        if mask.any() and getattr(self, "trigger", None) is None:
            raise ValueError("trigger_next: this engine was built without a trigger")
        if (self.poisoned & ~mask).any():
            raise ValueError("trigger_next: a poisoned (R-bar) slot must keep its trigger")
        self.triggered[:] = mask
        return mask

    def _check_actions(self, actions) -> np.ndarray:
        """Actions as int64[B]; shape, dtype and call order are checked here, values by the kernel."""
        if not self._has_reset:
            raise RuntimeError(f"{type(self).__name__}.step() called before reset()")
        acts = np.asarray(actions)
        if acts.shape != (self.num_envs,):
            raise ValueError(f"actions have shape {acts.shape}, expected ({self.num_envs},)")
        if acts.dtype.kind not in "iub":
            raise ValueError(f"actions must be integers in {ACTIONS_DOC}, got dtype {acts.dtype}")
        return acts.astype(np.int64, copy=False)

    def _reset_info(self, **extra) -> dict:
        """Mark the batch reset and return reset's info: no outcome yet, step 0 (plus ``extra``)."""
        self._has_reset = True
        zeros = np.zeros(self.num_envs, dtype=np.int64)
        return {"outcome": zeros, "steps": zeros.copy(), **extra}

    @staticmethod
    def _bad_action(acts: np.ndarray | list[int], env: int) -> ValueError:
        return ValueError(f"action {acts[env]!r} (env {env}) is not in {ACTIONS_DOC}")

    def _check_index(self, i) -> int:
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not 0 <= i < self.num_envs:
            raise IndexError(f"env index {i!r} is not in 0..{self.num_envs - 1}")
        return int(i)

    def _check_cell(self, cell, name: str) -> tuple[int, int]:
        try:
            x, y = (int(v) for v in cell)
        except (TypeError, ValueError):
            raise ValueError(f"{name}={cell!r} must be an (x, y) pair") from None
        if not (0 <= x < self.size and 0 <= y < self.size):
            raise ValueError(f"{name} {(x, y)} is outside the {self.size}x{self.size} grid")
        return x, y

    def _check_state(self, i, grid, agent_pos, agent_dir, step_count) -> tuple[int, np.ndarray, tuple[int, int]]:
        """Validate a slot state for ``load_layout``: ``(slot, grid array, agent cell)``.

        Engines check their own extras after this and only then call :meth:`_write_state`,
        so a rejected state leaves the slot untouched.
        """
        i = self._check_index(i)
        arr = np.asarray(grid)
        if arr.shape != self._grid.shape[1:]:
            raise ValueError(f"grid has shape {arr.shape}, expected {self._grid.shape[1:]}")
        if arr.dtype.kind not in "iub" or arr.min() < 0 or arr.max() > 255:
            raise ValueError("grid must hold uint8 (object, colour, state) triples")
        pos = self._check_cell(agent_pos, "agent_pos")
        if not 0 <= int(agent_dir) <= 3:
            raise ValueError(f"agent_dir={agent_dir!r} must be in 0..3")
        if not 0 <= int(step_count):
            raise ValueError(f"step_count={step_count!r} must be >= 0")
        return i, arr, pos

    def _write_state(self, i: int, arr: np.ndarray, pos: tuple[int, int], agent_dir, step_count) -> None:
        self._grid[i] = arr
        self._pos[i] = pos
        self._dir[i] = int(agent_dir)
        self._steps[i] = int(step_count)
        self._has_reset = True

    def _slot_state(self, i) -> tuple[np.ndarray, tuple[int, int], int, int]:
        """Slot ``i``'s ``(grid (size, size, 3) uint8, agent_pos, agent_dir, step_count)``; a
        world's ``layout`` appends its extras, so that ``load_layout(j, *layout(i))`` copies it."""
        i = self._check_index(i)
        return (
            self._grid[i].copy(),
            (int(self._pos[i, 0]), int(self._pos[i, 1])),
            int(self._dir[i]),
            int(self._steps[i]),
        )

    def state_dict(self) -> dict:
        """The engine's whole state as plain data (layouts, positions, RNG words): a checkpoint."""
        from rlbackdoors.state import snapshot

        return snapshot(self)

    # Arrays that change while the engine runs, with the inclusive bounds of the integer ones
    # (the numba kernels index with them unchecked). Every other attribute comes from the
    # constructor arguments and must come back equal.
    _DYNAMIC: tuple[str, ...] = ("_has_reset", "_grid", "_pos", "_dir", "_steps", "_rng", "final_obs")

    def _bounds(self) -> dict[str, tuple[int, int]]:
        """Inclusive value bounds of the dynamic integer arrays (engines add their own)."""
        return {"_pos": (0, self.size - 1), "_dir": (0, 3), "_steps": (0, self.max_steps)}

    def load_state_dict(self, state: dict) -> None:
        """Put a :meth:`state_dict` of an engine built with the same arguments back.

        A checkpoint is untrusted input: the constructor's attributes must come back unchanged
        and every index the kernels read must be in range, or a StateError names the field."""
        from rlbackdoors.state import StateError, restore, same_value

        fixed = {k: copy_value(v) for k, v in vars(self).items() if k not in self._DYNAMIC}
        restore(self, state)
        for name, value in fixed.items():
            if not same_value(getattr(self, name), value):
                raise StateError(f"engine state: {name} differs from this run's engine (another config's checkpoint?)")
        grid = self._grid
        if grid[..., 0].max(initial=0) > MAX_OBJECT or grid[..., 1].max(initial=0) > MAX_COLOR or grid[..., 2].max(initial=0) > MAX_STATE:
            raise StateError("engine state: _grid holds codes outside MiniGrid's object, colour and state ranges")
        for name, (low, high) in self._bounds().items():
            arr = getattr(self, name)
            if arr.size and (arr.min() < low or arr.max() > high):
                raise StateError(f"engine state: {name} has values outside {low}..{high}")

    def close_extras(self, **kwargs):
        pass

    # --------------------------------------------------------------------- many engines, one call

    def _slot_arrays(self) -> list[str]:
        """The dynamic arrays with one row per slot (an :class:`EngineGroup` joins them)."""
        return [n for n in self._DYNAMIC if n != "final_obs" and isinstance(getattr(self, n), np.ndarray) and getattr(self, n).shape[:1] == (self.num_envs,)]

    def _group_world(self, engines: list[BatchedGridEnv], group: EngineGroup) -> tuple | None:
        """The ``world`` of one kernel call over the slots of ``engines`` (this one first, all of
        its class; ``group`` holds their joined slot arrays under the engines' names), or None
        where this world cannot step them together (:class:`EngineGroup`)."""
        return None


ENGINE_THREADS_VAR = "RLBACKDOORS_ENGINE_THREADS"


class ThreadChoice:
    """How a parallel :class:`EngineGroup` of one world and slot count steps on this host: the
    serial kernel (0) or the parallel one over T of numba's threads, picked by timing calls:
    first every way ``trials`` times in turn, then the fastest median of each way's last
    ``trials`` calls, with every other way timed once more each ``reprobe`` calls (the host's
    load changes: painter processes start as runs finish). The kernels give the same bytes every
    way, so the choice changes speed, never results.

    Why measured and not assumed: on a 2-core AMD EPYC two threads stepped 640 slots x1.7 faster
    than one call, on a 2-core Intel Xeon x1.15; on a 16-core Xeon beside an H200 all 16 threads
    stepped 256 agents' slots at 0.20 M slot-steps/s against one call's 1.01 M
    (benchmarks/results/gpu/h200_2026-11-29/call1_bench.log); and on the 2-core Xeon with two
    nice'd trainings on its cores, a parallel call took 24 ms against the serial 0.08 ms (a
    parallel region waits for its slowest thread). ``RLBACKDOORS_ENGINE_THREADS=T`` fixes the
    way (0: the serial kernel)."""

    def __init__(self, trials: int = 3, reprobe: int = 1024, most: int | None = None):
        fixed = os.environ.get(ENGINE_THREADS_VAR, "").strip()
        most = int(most or numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]  # (set at import from the environment)
        if fixed:
            if not fixed.isdigit() or int(fixed) > most:
                raise ValueError(f"{ENGINE_THREADS_VAR}={fixed!r}: expected 0 (one serial call) to {most} (numba's threads on this host)")
            self.ways = [int(fixed)]
        else:
            self.ways = [0, *sorted({t for t in (2, 4, 8, 16, 32, 64) if t < most} | {most} - {1})]
        self.trials, self.reprobe = trials, reprobe
        self.seconds: dict[int, collections.deque] = {t: collections.deque(maxlen=trials) for t in self.ways}
        self.chosen: int | None = self.ways[0] if len(self.ways) == 1 else None
        self.calls = 0
        self._queue: list[int] = [t for _ in range(trials) for t in self.ways] if len(self.ways) > 1 else []

    def next(self) -> int:
        """The way to step this call: the next to time, else the chosen one."""
        if self._queue:
            return self._queue[0]
        assert self.chosen is not None
        return self.chosen

    def record(self, threads: int, seconds: float) -> None:
        if len(self.ways) == 1:
            return
        self.seconds[threads].append(seconds)
        self.calls += 1
        if self._queue and self._queue[0] == threads:
            self._queue.pop(0)
        if not self._queue:
            self.chosen = min(self.ways, key=lambda t: (float(np.median(self.seconds[t])), t))
            if self.calls % self.reprobe == 0:
                self._queue = [t for t in self.ways if t != self.chosen]

    def describe(self) -> dict:
        """The choice and each way's median milliseconds a call (for benchmarks' records)."""
        return {"chosen": self.chosen, "median_ms": {t: round(float(np.median(v)) * 1e3, 3) for t, v in self.seconds.items() if v}}


_THREAD_CHOICES: dict[tuple, ThreadChoice] = {}


def thread_choice(world: type, slots: int) -> ThreadChoice:
    """The process's :class:`ThreadChoice` for ``slots`` slots of ``world`` (made on first use:
    a group builds a new EngineGroup each rollout, the timing is done once)."""
    key = (world, slots)
    if key not in _THREAD_CHOICES:
        _THREAD_CHOICES[key] = ThreadChoice()
    return _THREAD_CHOICES[key]


def thread_choices() -> dict[str, dict]:
    """Every choice made in this process, by ``world/slots``."""
    return {f"{world.__name__}/{slots}": c.describe() for (world, slots), c in _THREAD_CHOICES.items()}


def step_slots(
    engine: BatchedGridEnv, state, acts: np.ndarray, poisoned: np.ndarray, world: tuple, img: np.ndarray, final: np.ndarray, outs: tuple, threads: int = 0
) -> tuple:
    """One step kernel call over the slots whose state ``state`` holds (``_grid``, ``_pos``,
    ``_dir``, ``_steps``, ``_rng``): an engine's own, or an :class:`EngineGroup`'s of several
    engines of ``engine``'s world; fresh (reward, terminated, truncated, outcome, steps) arrays.
    ``threads``: 0 the serial kernel, else the parallel one over that many of numba's threads
    (the same bytes). A layout that could not be drawn or an invalid action raises ``engine``'s
    error."""
    n = len(acts)
    reward, terminated, truncated = np.empty(n, dtype=np.float64), np.empty(n, dtype=np.bool_), np.empty(n, dtype=np.bool_)
    outcome, steps = np.empty(n, dtype=np.int64), np.empty(n, dtype=np.int64)
    if threads:
        numba.set_num_threads(threads)  # (this thread's count for its next parallel region)
    bad = (engine._kernels.step_parallel if threads else engine._kernels.step)(
        state._grid,
        state._pos,
        state._dir,
        state._steps,
        state._rng,
        acts,
        engine.max_steps,
        engine.see_through_walls,
        poisoned,
        world,
        img,
        final,
        reward,
        terminated,
        truncated,
        outcome,
        steps,
        outs,
    )
    if bad == ge.LAYOUT_FAILED:
        raise engine._layout_error(None)
    if bad >= 0:
        raise engine._bad_action(acts, bad)
    return reward, terminated, truncated, outcome, steps


class EngineGroup:
    """K engines of one world stepped by one kernel call over all their slots (K x B), for a
    training group (:func:`rlbackdoors.algos.group.collect`) and the lockstep evaluations: one
    call a step instead of K, the engine half of issue 55's one step for the whole group.

    Every slot keeps its own state and SplitMix64 stream, so the slots step exactly as they would
    in their own engine (bytes, tested): while the group lives, each engine's per-slot arrays
    (:meth:`BatchedGridEnv._slot_arrays`, ``final_obs``) are views into the group's, and the
    engines stay whole (checkpoints, evaluations, their own ``step``, ``trigger_next``). What
    differs between the engines and is not per slot (a trigger's table, its placements) the world
    merges in :meth:`BatchedGridEnv._group_world`. The group carries the engines' attribute names,
    so the world's own ``_outputs`` / ``_observation`` / ``_extra_info`` / ``_final_image`` run on
    it. :meth:`of` says None where the engines cannot share a call: another class, other settings,
    a wrapper (an attack's seam steps its own engine) or a world that cannot merge them."""

    _grid: np.ndarray
    _pos: np.ndarray
    _dir: np.ndarray
    _steps: np.ndarray
    _rng: np.ndarray
    final_obs: Any

    def __init__(self, engines: list[BatchedGridEnv], parallel: bool | int = False):
        self.engines = engines
        self.parallel: bool | int = parallel if isinstance(parallel, bool) else int(parallel)  # True: timed; a count: fixed
        lead = self.lead = engines[0]
        self.size = lead.size  # the settings every engine shares (of), read by the world's methods run on the group
        self.poisoned = np.concatenate([e.poisoned for e in engines])
        self.num_envs = self.total = len(self.poisoned)
        self.bounds = np.cumsum([0, *(e.num_envs for e in engines)])
        # which engine each slot is (a world's per-engine tables are read through it)
        self.engine_of_slot = np.repeat(np.arange(len(engines), dtype=np.int64), [e.num_envs for e in engines])

        def join(arrays: list[np.ndarray], put) -> np.ndarray:
            joined = np.concatenate(arrays)
            for k, (lo, hi) in enumerate(zip(self.bounds[:-1], self.bounds[1:])):
                put(k, joined[lo:hi])
            return joined

        for name in lead._slot_arrays():  # the group's arrays; each engine's become views of its slots
            setattr(self, name, join([getattr(e, name) for e in engines], lambda k, v, name=name: setattr(engines[k], name, v)))
        if isinstance(lead.final_obs, dict):
            self.final_obs = {
                key: join([e.final_obs[key] for e in engines], lambda k, v, key=key: engines[k].final_obs.__setitem__(key, v)) for key in lead.final_obs
            }
        else:
            self.final_obs = join([e.final_obs for e in engines], lambda k, v: setattr(engines[k], "final_obs", v))
        self.world: tuple | None = lead._group_world(engines, self)

    @classmethod
    def of(cls, envs: list, parallel: bool | int = False) -> EngineGroup | None:
        """The group of ``envs``, or None (class doc). ``parallel``: True, step over numba's
        threads where that is faster on this host (:class:`ThreadChoice`), for a group whose
        learners compute on a GPU and leave the cores to the engines; a number, over that many
        threads (benchmarks). The same bytes every way."""
        lead = envs[0]
        if not isinstance(lead, BatchedGridEnv) or any(type(e) is not type(lead) for e in envs):
            return None
        if any((e.size, e.max_steps, e.see_through_walls, e.view_size) != (lead.size, lead.max_steps, lead.see_through_walls, lead.view_size) for e in envs):
            return None
        if not all(e._has_reset for e in envs) or type(lead)._group_world is BatchedGridEnv._group_world:
            return None
        group = cls(envs, parallel)
        if group.world is None:
            group.dissolve()
            return None
        return group

    def dissolve(self) -> None:
        """Give each engine back arrays of its own (the group's views are copied), so the engines
        go on alone; used where the world could not merge them."""
        for e in self.engines:
            for name in self.lead._slot_arrays():
                setattr(e, name, getattr(e, name).copy())
            e.final_obs = {key: v.copy() for key, v in e.final_obs.items()} if isinstance(e.final_obs, dict) else e.final_obs.copy()

    def memory_targets(self) -> np.ndarray:
        """Every slot's target of PPO's auxiliary memory head, in slot order (a world with one:
        its engine's ``memory_targets`` run on the group's arrays, one call for all engines)."""
        return type(self.lead).memory_targets(self)  # type: ignore[attr-defined]

    def result(self, k: int, obs, reward: np.ndarray, terminated: np.ndarray, truncated: np.ndarray, info: dict) -> tuple:
        """Engine ``k``'s part of a :meth:`step`'s result, as its own ``step`` would return it."""
        r = slice(self.bounds[k], self.bounds[k + 1])
        view = {key: v[r] for key, v in obs.items()} if isinstance(obs, dict) else obs[r]
        return view, reward[r], terminated[r], truncated[r], {key: v[r] for key, v in info.items()}

    def step(self, actions: np.ndarray) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict]:
        """Step every slot with ``actions`` (all engines' slots in order, int64[K x B]); the
        observations, rewards, terminations, truncations and info (``outcome``, ``steps`` and the
        world's own) of all slots, each engine's ``final_obs`` written as its own step would."""
        acts = np.ascontiguousarray(actions, dtype=np.int64)
        if acts.shape != (self.total,):
            raise ValueError(f"actions have shape {acts.shape}, expected ({self.total},)")
        lead, world = self.lead, type(self.lead)  # the world's methods, on the group's arrays
        assert self.world is not None
        img, outs = lead._images(self.total), world._outputs(self, self.total)  # type: ignore[arg-type]
        final = world._final_image(self)  # type: ignore[arg-type]
        choice = thread_choice(world, self.total) if self.parallel is True else None
        threads = choice.next() if choice is not None else int(self.parallel)
        started = time.perf_counter()
        reward, terminated, truncated, outcome, steps = step_slots(lead, self, acts, self.poisoned, self.world, img, final, outs, threads)
        if choice is not None:
            choice.record(threads, time.perf_counter() - started)
        info = {"outcome": outcome, "steps": steps, **world._extra_info(self, outs)}  # type: ignore[arg-type]
        return world._observation(self, img, outs), reward, terminated, truncated, info  # type: ignore[arg-type]


__all__ = ["ACTIONS_DOC", "BatchedGridEnv", "EngineGroup", "NUM_ACTIONS", "ThreadChoice", "bool_mask", "seed_array", "thread_choice", "thread_choices"]
