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


# env name -> (gymnasium.make entry point, gymnasium.make_vec entry point or None). The grid
# worlds make the MiniGrid reference and make_vec the batched engine; MuJoCo is imported only
# when Safety Car Goal is made, and that env truncates itself at max_steps.
ENTRY_POINTS = {
    "lavaworld": ("rlbackdoors.envs.lavaworld:LavaWorldEnv", "rlbackdoors.envs.lavaworld_batched:BatchedLavaWorld"),
    "randomized-lavaworld": (
        "rlbackdoors.envs.randomized_lavaworld:RandomizedLavaWorldEnv",
        "rlbackdoors.envs.randomized_lavaworld_batched:BatchedRandomizedLavaWorld",
    ),
    "colorful-memory": (
        "rlbackdoors.envs.colorful_memory:ColorfulMemoryEnv",
        "rlbackdoors.envs.colorful_memory_batched:BatchedColorfulMemory",
    ),
    "safety-car-goal": ("rlbackdoors.envs.safety_car:SafetyCarGoalEnv", None),
}


def _register() -> None:
    for name, (entry, vector_entry) in ENTRY_POINTS.items():
        if ENV_IDS[name] not in registry:
            extra = {"vector_entry_point": vector_entry} if vector_entry else {}
            register(id=ENV_IDS[name], entry_point=entry, **extra)


_register()

__all__ = ["ENV_IDS", "ColorfulMemoryEnv", "LavaWorldEnv", "Outcome", "RandomizedLavaWorldEnv"]
