"""Randomized LavaWorld's slots stepped by pure JAX functions (:mod:`rlbackdoors.envs.grid_jax`),
exact to :class:`rlbackdoors.envs.randomized_lavaworld_batched.BatchedRandomizedLavaWorld`: the goal
or lava ends an episode, lava of the inserted pattern pays poisoned slots (R-bar), and the view is
the plain view (the trigger is in the layout, not stamped on the image).

The pattern is each slot's own state beside the grid (its cells are lava like any other): a mask
for the outcome, the cells and their count as the numba engine holds them, and whether a view of
the episode showed a pattern cell (``saw_trigger``), each drawn with its layout on the host and
handed back, so the numba engine goes on from the JAX side's state as from its own. The layouts'
draws (trigger, near-trigger pattern or none, per slot) stay the numba engine's.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.batched_base import EngineGroup
from rlbackdoors.envs.grid_jax import GridWorld, HostLayouts, WorldState
from rlbackdoors.envs.randomized_lavaworld_batched import BatchedRandomizedLavaWorld


class PatternParams(NamedTuple):
    """Randomized LavaWorld's per-slot parameters (a pytree)."""

    poisoned: Any  # (B,) bool


def _masks(cells: np.ndarray, count: np.ndarray, size: int) -> np.ndarray:
    """(R, S, S) bool: the cells ``cells[r, :count[r]]`` of each row, as the engine's ``_pat``."""
    rows = len(count)
    mask = np.zeros((rows, size, size), dtype=bool)
    k = np.arange(cells.shape[1])[None, :] < count[:, None]
    r = np.broadcast_to(np.arange(rows)[:, None], k.shape)
    mask[r[k], cells[..., 0][k], cells[..., 1][k]] = True
    return mask


def _state(size: int, final_direction) -> WorldState:
    """The slots' pattern (mask, cells, count), the episode's ``saw_trigger`` and the terminal
    view's direction (``final_obs["direction"]``), between the engines and the JAX step."""

    def initial(h):
        return (
            np.array(h._pat, dtype=bool),
            np.array(h._pcells, dtype=np.int32),
            np.array(h._pcount, dtype=np.int32),
            np.array(h._saw, dtype=bool),
            np.array(final_direction(h), dtype=np.int32),
        )

    def drawn(outs, rows, grids):
        cells, count, saw = outs[4], outs[5], outs[6]
        return _masks(cells, count, size), cells.astype(np.int32), count.astype(np.int32), saw.astype(bool)

    def hand_back(h, state):
        pat, cells, count, saw, final = state
        h._pat[:], h._pcells[:], h._pcount[:], h._saw[:] = pat, cells, count, saw
        final_direction(h)[:] = final

    # triggered / near: read by the layouts' draws on the host, never stepped
    return WorldState(("_pat", "_pcells", "_pcount", "_saw", "triggered", "near"), initial, drawn, hand_back)


def _outcome(fwd, slots, params):
    """Lava ends the episode, as the pattern's lava where the cell is one of the slot's pattern."""
    import jax.numpy as jnp

    pat = slots.world[0]
    on_pattern = pat[jnp.arange(pat.shape[0]), slots.pos[:, 0], slots.pos[:, 1]]
    lava = jnp.where(on_pattern, ge.OUT_PATTERN, ge.OUT_LAVA)
    return jnp.where(fwd == ge.GOAL, ge.OUT_GOAL, jnp.where(fwd == ge.LAVA, lava, ge.OUT_NONE))


def _seen(img, slots, params):
    """The plain view: the trigger is lava of the layout."""
    return img


def _shown(world: GridWorld, slots, views):
    """(B, V V): the view cells that show a cell of the slot's pattern (lava there: the agent's own cell shows empty)."""
    import jax.numpy as jnp

    pat = slots.world[0]
    b, p = pat.shape[0], world.view_size - 1
    padded = jnp.pad(pat, ((0, 0), (p, p), (p, p))).reshape(b, -1)
    return jnp.take_along_axis(padded, world.view_cells(slots), axis=1) & (views[..., 0].reshape(b, -1) == ge.LAVA)


def _sight(world: GridWorld, slots, views):
    """The engine's ``trigger_in_sight``: the view shows every cell of the slot's pattern (one
    cell is lava like any other; a view cell per grid cell, so all of them is the count)."""
    count = slots.world[2]
    return (count > 0) & (_shown(world, slots, views).sum(1) == count)


def _saw(world: GridWorld, moved, seen):
    """The episode's ``saw_trigger`` with the views ``seen``: a pattern cell shown in it or an earlier one."""
    return moved.world[3] | _shown(world, moved, seen).any(1)


def _advance(world: GridWorld, moved, seen, done, drawn, params, fresh):
    """``saw_trigger`` goes on from each view (a pattern cell shown: lava in the view where the
    slot's pattern lies; the agent's own cell shows empty), the terminal direction is kept, and a
    slot that ended takes its next layout's pattern and first view's flag."""
    import jax.numpy as jnp

    pat, cells, count, _, final = moved.world
    saw = _saw(world, moved, seen)
    final = jnp.where(done, moved.dirs, final)
    d_pat, d_cells, d_count, d_saw = drawn
    return (
        jnp.where(done[:, None, None], d_pat, pat),
        jnp.where(done[:, None, None], d_cells, cells),
        jnp.where(done, d_count, count),
        jnp.where(done, d_saw, saw),
        final,
    )


def randomized_lavaworld_jax(engines: BatchedRandomizedLavaWorld | EngineGroup) -> tuple[GridWorld, PatternParams, HostLayouts]:
    """The JAX step of reset Randomized LavaWorld engines' slots (one agent's, or an
    :class:`EngineGroup`'s of several): the static world, its per-slot parameters (numpy) and the
    host side that holds the slots' state and draws their layouts. A slot's observation is its
    view and its direction (``Slots.dirs`` after the step)."""
    lead = engines.lead if isinstance(engines, EngineGroup) else engines
    if not isinstance(lead, BatchedRandomizedLavaWorld):
        raise TypeError(f"{type(lead).__name__} is not a BatchedRandomizedLavaWorld")
    host = HostLayouts(engines, _state(lead.size, lambda h: h.final_obs["direction"]))
    world = GridWorld(host.size, host.view_size, int(lead.max_steps), host.see_through_walls, ge.OUT_PATTERN, _outcome, _seen, _advance, _sight, _saw)
    return world, PatternParams(np.array(engines.poisoned, dtype=bool)), host


__all__ = ["PatternParams", "randomized_lavaworld_jax"]
