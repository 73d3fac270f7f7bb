"""Colorful Memory's slots stepped by pure JAX functions (:mod:`rlbackdoors.envs.grid_jax`), exact
to :class:`rlbackdoors.envs.colorful_memory_batched.BatchedColorfulMemory`: standing on the cell
beside the corridor object that matches the start room's ends an episode as the goal, on the other
one's as lava (R-bar pays poisoned slots there), and the view is the plain view (the trigger is the
layout's wall colours, drawn on the host).

Each slot's own state beside the grid: its success and failure cells (read from each drawn grid's
objects, as MemoryEnv decides them), whether its episode's layout was drawn triggered (``armed``,
from the slot's layout mode when it was drawn) and which of the trigger's squares the episode has
shown so far (``seen``: a square's view cell holds its wall, as ``grid_engine.view_shows`` reads
it), so that ``trigger_in_sight`` (every square shown in a triggered episode) is the program's
too. The layouts' draws (clean, close-to-trigger recolourings, the trigger) stay the numba engine's.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.batched_base import EngineGroup
from rlbackdoors.envs.colorful_memory import BALL_ON_FLOOR, TRIGGERED, object_cells
from rlbackdoors.envs.colorful_memory_batched import BatchedColorfulMemory
from rlbackdoors.envs.grid_jax import GridWorld, HostLayouts, WorldState


class MemoryParams(NamedTuple):
    """Colorful Memory's per-slot parameters (a pytree)."""

    poisoned: Any  # (B,) bool
    squares: Any  # (B, S, 2) int32: the trigger's squares of each slot's engine (zero-padded)
    valid: Any  # (B, S) bool: which of them the slot's trigger has


def _world_arrays(engines) -> tuple:
    """The hooks' world tuple (succ, fail, walls, mode, squares, counts, seen, armed, table): an
    engine's own arrays, or an :class:`EngineGroup`'s joined ones (written in place, as a step would)."""
    world = engines.world if isinstance(engines, EngineGroup) else engines._world()
    if world is None:
        raise ValueError("these engines cannot share a call (EngineGroup.of says None)")
    return world


def targets(grids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, 2) success and failure cells of drawn grids (R, S, S, 3): beside the corridor object of
    the start-room object's type (``colorful_memory.target_cells``, for many grids at once)."""
    size = grids.shape[1]
    start, top, bottom = object_cells(size) if size else ((0, 0), (0, 0), (0, 0))
    same = grids[:, start[0], start[1], 0] == grids[:, top[0], top[1], 0]
    up, down = np.array([top[0], top[1] + 1]), np.array([bottom[0], bottom[1] - 1])
    return np.where(same[:, None], up, down).astype(np.int32), np.where(same[:, None], down, up).astype(np.int32)


def _state(engines) -> WorldState:
    """The slots' success and failure cells, which trigger squares their episode has shown and
    whether it was drawn triggered, between the engines and the JAX step."""
    world = _world_arrays(engines)
    mode = world[3]  # read live: a draw takes the slot's mode as it is then (trigger_next switches it)
    valid = _valid(world)

    def initial(h):
        w = _world_arrays(h)
        return np.array(w[0], dtype=np.int32), np.array(w[1], dtype=np.int32), np.array(w[6], dtype=bool) | ~valid, np.array(w[7], dtype=bool)

    def drawn(outs, rows, grids):
        succ, fail = targets(np.asarray(grids))
        return succ, fail, np.asarray(mode)[rows] == TRIGGERED

    def hand_back(h, state):
        w = _world_arrays(h)
        succ, fail, seen, armed = state
        w[0][:], w[1][:], w[6][:], w[7][:] = succ, fail, seen & valid, armed

    # mode and triggered: read by the layouts' draws on the host, never stepped
    return WorldState(("_succ", "_fail", "_armed", "mode", "triggered"), initial, drawn, hand_back)


def _valid(world: tuple) -> np.ndarray:
    """(B, S) bool: the columns of ``seen`` each slot's trigger has (a group's are padded to the most)."""
    counts, table = np.asarray(world[5]), np.asarray(world[8])
    return np.arange(np.asarray(world[6]).shape[1])[None, :] < counts[table, 0][:, None]


def _outcome(fwd, slots, params):
    """MemoryEnv.step: where the agent stands after the action decides, whatever the action."""
    import jax.numpy as jnp

    succ, fail = slots.world[0], slots.world[1]
    at = lambda cell: (slots.pos == cell).all(1)  # noqa: E731
    return jnp.where(at(succ), ge.OUT_GOAL, jnp.where(at(fail), ge.OUT_LAVA, ge.OUT_NONE))


def _seen(img, slots, params):
    """The plain view: the trigger is the layout's wall colours."""
    return img


def _shown(world: GridWorld, pos, dirs, views, params):
    """(B, S): the trigger's squares each view shows (its view cell holds the wall: ``view_shows``);
    a padding column (a slot's trigger has fewer squares than the group's most) is always shown,
    so that "every square shown" is a plain ``all`` (the engines never read those columns)."""
    import jax.numpy as jnp

    n = world.view_size
    dxy = jnp.asarray(world.tables["dir_vec"])[dirs]  # (B, 2)
    dx, dy = dxy[:, :1], dxy[:, 1:]
    rel = params.squares - pos[:, None, :]  # (B, S, 2)
    vx = rel[..., 0] * -dy + rel[..., 1] * dx + n // 2
    vy = n - 1 - (rel[..., 0] * dx + rel[..., 1] * dy)
    inside = (vx >= 0) & (vx < n) & (vy >= 0) & (vy < n)
    cell = jnp.clip(vx, 0, n - 1) * n + jnp.clip(vy, 0, n - 1)
    obj = jnp.take_along_axis(views[..., 0].reshape(views.shape[0], -1), cell, axis=1)
    return (inside & (obj == ge.WALL)) | ~params.valid


def _advance(world: GridWorld, moved, seen, done, drawn, params, fresh):
    """A triggered episode's shown squares go on from each view (nothing is shown outside one); a
    slot that ended takes its next layout's cells and flag, and the squares its first view shows."""
    import jax.numpy as jnp

    succ, fail, shown, armed = moved.world
    shown = shown | (_shown(world, moved.pos, moved.dirs, seen, params) & armed[:, None])
    d_succ, d_fail, d_armed = drawn
    f_pos, f_dirs, f_view = fresh
    first = _shown(world, f_pos, f_dirs, f_view, params) & d_armed[:, None]
    return (
        jnp.where(done[:, None], d_succ, succ),
        jnp.where(done[:, None], d_fail, fail),
        jnp.where(done[:, None], first, shown),
        jnp.where(done, d_armed, armed),
    )


def _sight(world: GridWorld, slots, views):
    """The engine's ``trigger_in_sight``: a triggered episode has shown every square of the trigger."""
    _, _, shown, armed = slots.world
    return armed & shown.all(1)


def _memory_targets(world: GridWorld, slots):
    """(B,) int32: each slot's start-room object (0 key, 1 ball), read from its grid as the engine's
    ``memory_targets``: what the agent must remember to the junction."""
    import jax.numpy as jnp

    p = world.view_size - 1
    start = object_cells(world.size)[0]
    return (slots.grid[:, start[0] + p, start[1] + p, 0] == BALL_ON_FLOOR).astype(jnp.int32)


def _widen(pairs: list[tuple[MemoryParams, tuple]]) -> list[tuple[MemoryParams, tuple]]:
    """Slots of engines with other triggers (a clean condition has no squares, a triggered one
    its trigger's), padded to the most squares as :class:`EngineGroup` pads a group: a padding
    square is not valid and always counts as shown."""
    width = max(params.squares.shape[1] for params, _ in pairs)
    out = []
    for params, (succ, fail, shown, armed) in pairs:
        extra = width - params.squares.shape[1]
        b = params.squares.shape[0]
        squares = np.concatenate([params.squares, np.zeros((b, extra, 2), np.int32)], axis=1)
        valid = np.concatenate([params.valid, np.zeros((b, extra), bool)], axis=1)
        shown = np.concatenate([np.asarray(shown, bool), np.ones((b, extra), bool)], axis=1)
        out.append((params._replace(squares=squares, valid=valid), (succ, fail, shown, armed)))
    return out


def colorful_memory_jax(engines: BatchedColorfulMemory | EngineGroup) -> tuple[GridWorld, MemoryParams, HostLayouts]:
    """The JAX step of reset Colorful Memory engines' slots (one agent's, or an
    :class:`EngineGroup`'s of several): the static world, its per-slot parameters (numpy) and the
    host side that holds the slots' state and draws their layouts. A slot's observation is its view."""
    lead = engines.lead if isinstance(engines, EngineGroup) else engines
    if not isinstance(lead, BatchedColorfulMemory):
        raise TypeError(f"{type(lead).__name__} is not a BatchedColorfulMemory")
    host = HostLayouts(engines, _state(engines))
    world_arrays = _world_arrays(engines)
    squares, table = world_arrays[4], world_arrays[8]
    valid = _valid(world_arrays)
    slot_squares = np.asarray(squares)[np.asarray(table)][:, : valid.shape[1], :2].astype(np.int32)  # (B, S, 2): seen's columns (none without a trigger)
    world = GridWorld(
        host.size,
        host.view_size,
        int(lead.max_steps),
        host.see_through_walls,
        ge.OUT_LAVA,
        _outcome,
        _seen,
        _advance,
        _sight,
        memory_targets=_memory_targets,
        widen=_widen,
    )
    return world, MemoryParams(np.array(engines.poisoned, dtype=bool), slot_squares, valid), host


__all__ = ["MemoryParams", "colorful_memory_jax", "targets"]
