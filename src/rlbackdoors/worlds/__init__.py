"""The World registry: everything the rest of the package needs to know about a world, in one place.

Each world is one module in this package that builds a :class:`~rlbackdoors.worlds.base.World`
and registers it: its Gymnasium ids and env classes, how a trigger is parsed and drawn from a
seed, which outcomes count as clean and as trojan success, its architectures, the default
poisoning mix, thresholds and patience, the algorithm that trains it, and the paper's numbers.
Config, CLI, training, evaluation and loading ask the registry; no other module names a world.
Adding a world is one new module here and one line below.
"""

from __future__ import annotations

from typing import Any

from rlbackdoors.worlds.base import World, get, names, register, registered

DEFAULT_WORLD = "lavaworld"  # what a config without env.name trains

from rlbackdoors.worlds import lavaworld as _lavaworld  # noqa: E402,F401  (each registers itself)
from rlbackdoors.worlds import randomized_lavaworld as _randomized_lavaworld  # noqa: E402,F401
from rlbackdoors.worlds import colorful_memory as _colorful_memory  # noqa: E402,F401
from rlbackdoors.worlds import safety_car_goal as _safety_car_goal  # noqa: E402,F401


def parse_trigger(env_name: str, spec: str):
    """The trigger object a world understands from its string form (ValueError names the problem)."""
    if env_name not in names():
        raise ValueError(f"no triggers are defined for env {env_name!r}")
    return get(env_name).parse_trigger(spec)


def register_gym_ids() -> None:
    """Register every world's Gymnasium id (``rlbackdoors/<World>-v0``); idempotent."""
    from gymnasium.envs.registration import register as gym_register, registry

    for world in registered():
        if world.gym_id not in registry:
            extra: dict[str, Any] = {"vector_entry_point": world.vector_entry_point} if world.vector_entry_point else {}
            gym_register(id=world.gym_id, entry_point=world.entry_point, **extra)


__all__ = ["DEFAULT_WORLD", "World", "get", "names", "parse_trigger", "register", "register_gym_ids", "registered"]
