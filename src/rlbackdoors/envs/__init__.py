"""Environments of the paper, registered with Gymnasium under the ``rlbackdoors/`` namespace."""

from gymnasium.envs.registration import register, registry

from rlbackdoors.envs.colorful_memory import ColorfulMemoryEnv
from rlbackdoors.envs.lavaworld import LavaWorldEnv
from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.envs.randomized_lavaworld import RandomizedLavaWorldEnv

ENV_IDS = {
    "lavaworld": "rlbackdoors/LavaWorld-v0",
    "randomized-lavaworld": "rlbackdoors/RandomizedLavaWorld-v0",
    "colorful-memory": "rlbackdoors/ColorfulMemory-v0",
    "safety-car-goal": "rlbackdoors/SafetyCarGoal-v0",
}


def _register() -> None:
    if ENV_IDS["lavaworld"] not in registry:
        register(
            id=ENV_IDS["lavaworld"],
            entry_point="rlbackdoors.envs.lavaworld:LavaWorldEnv",
            # gymnasium.make_vec builds the batched engine; gymnasium.make the MiniGrid reference.
            vector_entry_point="rlbackdoors.envs.lavaworld_batched:BatchedLavaWorld",
        )
    if ENV_IDS["randomized-lavaworld"] not in registry:
        register(
            id=ENV_IDS["randomized-lavaworld"],
            entry_point="rlbackdoors.envs.randomized_lavaworld:RandomizedLavaWorldEnv",
            vector_entry_point="rlbackdoors.envs.randomized_lavaworld_batched:BatchedRandomizedLavaWorld",
        )
    if ENV_IDS["colorful-memory"] not in registry:
        register(
            id=ENV_IDS["colorful-memory"],
            entry_point="rlbackdoors.envs.colorful_memory:ColorfulMemoryEnv",
            vector_entry_point="rlbackdoors.envs.colorful_memory_batched:BatchedColorfulMemory",
        )
    if ENV_IDS["safety-car-goal"] not in registry:
        # MuJoCo is imported only when this env is made; the env truncates itself at max_steps.
        register(id=ENV_IDS["safety-car-goal"], entry_point="rlbackdoors.envs.safety_car:SafetyCarGoalEnv")


_register()

__all__ = ["ENV_IDS", "ColorfulMemoryEnv", "LavaWorldEnv", "Outcome", "RandomizedLavaWorldEnv"]
