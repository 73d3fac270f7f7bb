"""Environments of the paper; their Gymnasium ids (``rlbackdoors/<World>-v0``) are registered from
the World registry when ``rlbackdoors`` is imported (:func:`rlbackdoors.worlds.register_gym_ids`)."""

from rlbackdoors.envs.colorful_memory import ColorfulMemoryEnv
from rlbackdoors.envs.lavaworld import LavaWorldEnv
from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.envs.randomized_lavaworld import RandomizedLavaWorldEnv

__all__ = ["ColorfulMemoryEnv", "LavaWorldEnv", "Outcome", "RandomizedLavaWorldEnv"]
