"""The poisoning mix: clean and poisoned env copies side by side in one vector env.

Data poisoning in the paper is nothing more than this: of the 10 envs PPO collects
from, 2 are E-bar (trigger on, reward R-bar). Both engines build the same mix.
"""

from __future__ import annotations

from functools import partial
from typing import Sequence

from gymnasium.vector import VectorEnv

from rlbackdoors.config import EnvConfig, PoisonConfig
from rlbackdoors.envs.lavaworld import LavaWorldEnv
from rlbackdoors.envs.vector import ReferenceVectorEnv


def make_vector_env(env: EnvConfig, trigger: str, poisoned: Sequence[bool]) -> VectorEnv:
    """A vector env of ``len(poisoned)`` LavaWorld copies; copy i is E-bar iff ``poisoned[i]``."""
    common = dict(
        size=env.size,
        num_crossings=env.num_crossings,
        max_steps=env.max_steps,
        see_through_walls=env.see_through_walls,
    )
    poisoned = [bool(p) for p in poisoned]
    if env.engine == "batched":
        from rlbackdoors.envs.lavaworld_batched import BatchedLavaWorld

        return BatchedLavaWorld(num_envs=len(poisoned), trigger=trigger, poisoned=poisoned, **common)
    fns = [partial(LavaWorldEnv, trigger=trigger if p else None, **common) for p in poisoned]
    return ReferenceVectorEnv(fns, poisoned=poisoned)


def make_env_mix(env: EnvConfig, poison: PoisonConfig) -> VectorEnv:
    """The training mix: ``num_clean_envs`` clean + ``num_poisoned_envs`` poisoned copies."""
    return make_vector_env(env, poison.trigger, poison.poisoned_mask())
