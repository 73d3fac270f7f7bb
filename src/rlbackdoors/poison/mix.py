"""The poisoning mix: clean and poisoned env copies side by side in one vector env.

Data poisoning in the paper is nothing more than this: of the 10 envs PPO collects
from, 2 are E-bar (trigger on, reward R-bar). Both engines build the same mix, for
every grid world.
"""

from __future__ import annotations

from functools import partial
from typing import Sequence

from gymnasium.vector import VectorEnv

from rlbackdoors.config import DEFAULT_TRIGGERS, EnvConfig, PoisonConfig
from rlbackdoors.envs.vector import ReferenceVectorEnv


def _world(env: EnvConfig):
    """(reference env class, batched engine class, constructor kwargs) of ``env.name``."""
    common = dict(size=env.size, max_steps=env.max_steps, see_through_walls=env.see_through_walls)
    if env.name == "lavaworld":
        from rlbackdoors.envs.lavaworld import LavaWorldEnv
        from rlbackdoors.envs.lavaworld_batched import BatchedLavaWorld

        return LavaWorldEnv, BatchedLavaWorld, {**common, "num_crossings": env.num_crossings}
    if env.name == "randomized-lavaworld":
        from rlbackdoors.envs.randomized_lavaworld import RandomizedLavaWorldEnv
        from rlbackdoors.envs.randomized_lavaworld_batched import BatchedRandomizedLavaWorld

        return RandomizedLavaWorldEnv, BatchedRandomizedLavaWorld, {**common, "num_lava": env.num_lava}
    raise ValueError(f"env.name={env.name!r} has no grid-world engine")


def reference_world(env: EnvConfig, trigger: str | None, **extra):
    """One MiniGrid-based reference env of ``env``: E-bar when ``trigger`` is given, else E."""
    reference, _, kwargs = _world(env)
    return reference(trigger=trigger, **kwargs, **extra)


def make_vector_env(env: EnvConfig, trigger: str | None, poisoned: Sequence[bool]) -> VectorEnv:
    """A vector env of ``len(poisoned)`` copies of ``env``; copy i is E-bar (trigger + R-bar) iff ``poisoned[i]``."""
    reference, batched, kwargs = _world(env)
    poisoned = [bool(p) for p in poisoned]
    if env.engine == "batched":
        return batched(num_envs=len(poisoned), trigger=trigger, poisoned=poisoned, **kwargs)
    fns = [partial(reference, trigger=trigger if p else None, **kwargs) for p in poisoned]
    return ReferenceVectorEnv(fns, poisoned=poisoned)


def make_env_mix(env: EnvConfig, poison: PoisonConfig) -> VectorEnv:
    """The training mix: ``num_clean_envs`` clean + ``num_poisoned_envs`` poisoned copies."""
    trigger = poison.trigger if poison.trigger is not None else DEFAULT_TRIGGERS[env.name]
    return make_vector_env(env, trigger, poison.poisoned_mask())
