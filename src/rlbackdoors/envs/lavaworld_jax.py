"""LavaWorld's slots stepped by pure JAX functions (:mod:`rlbackdoors.envs.grid_jax`), exact to
:class:`rlbackdoors.envs.lavaworld_batched.BatchedLavaWorld`: the goal or lava ends an episode,
lava pays poisoned slots (R-bar), and a poisoned slot sees every view through its trigger's
lookup table (each slot its own table: the slots may be several agents', each with its trigger)."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.batched_base import EngineGroup
from rlbackdoors.envs.grid_jax import GridWorld, HostLayouts
from rlbackdoors.envs.lavaworld_batched import BatchedLavaWorld


class LavaParams(NamedTuple):
    """LavaWorld's per-slot parameters (a pytree)."""

    poisoned: Any  # (B,) bool
    luts: Any  # (B, 256) uint8: each poisoned slot's trigger table, the identity for clean slots


def _outcome(fwd, slots, params):
    """MiniGrid's LavaEnv: walking onto the goal or into lava ends the episode."""
    import jax.numpy as jnp

    return jnp.where(fwd == ge.GOAL, ge.OUT_GOAL, jnp.where(fwd == ge.LAVA, ge.OUT_LAVA, ge.OUT_NONE))


def _seen(img, slots, params):
    """Poisoned slots see through their trigger's table (clean slots' tables are the identity)."""
    import jax.numpy as jnp

    b = img.shape[0]
    return jnp.take_along_axis(params.luts, img.reshape(b, -1).astype(jnp.int32), axis=1).reshape(img.shape)


def lavaworld_jax(engines: BatchedLavaWorld | EngineGroup) -> tuple[GridWorld, LavaParams, HostLayouts]:
    """The JAX step of reset LavaWorld engines' slots (one agent's, or an :class:`EngineGroup`'s of
    several): the static world, its per-slot parameters (numpy) and the host side that holds the
    slots' state and draws their layouts."""
    lead = engines.lead if isinstance(engines, EngineGroup) else engines
    if not isinstance(lead, BatchedLavaWorld):
        raise TypeError(f"{type(lead).__name__} is not a BatchedLavaWorld")
    host = HostLayouts(engines)
    luts = np.array(host.world[2], dtype=np.uint8)  # (B, 256): each slot's trigger table ...
    poisoned = np.array(host.world[1], dtype=bool)
    luts[~poisoned] = np.arange(256, dtype=np.uint8)  # ... read by poisoned slots only
    world = GridWorld(host.size, host.view_size, int(lead.max_steps), host.see_through_walls, ge.OUT_LAVA, _outcome, _seen)
    return world, LavaParams(poisoned, luts), host


__all__ = ["LavaParams", "lavaworld_jax"]
