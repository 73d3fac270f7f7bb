"""The Attack registry: how training data is poisoned (the world says what the trigger is).

Each attack is one module here that builds an :class:`~rlbackdoors.attacks.base.Attack` and
registers it; config, training and evaluation ask the registry and name no attack. Adding an
attack is one new module and one line below.
"""

from rlbackdoors.attacks.base import SUCCESS_KINDS, Attack, Param, describe, get, names, register, registered

DEFAULT_ATTACK = "envmix"  # the paper's; configs without poison.attack train with it

from rlbackdoors.attacks import envmix as _envmix  # noqa: E402,F401  (each registers itself)
from rlbackdoors.attacks import trojdrl as _trojdrl  # noqa: E402,F401
from rlbackdoors.attacks import badrl as _badrl  # noqa: E402,F401
from rlbackdoors.attacks import sleepernets as _sleepernets  # noqa: E402,F401
from rlbackdoors.attacks import action_target as _action_target  # noqa: E402,F401

__all__ = ["DEFAULT_ATTACK", "SUCCESS_KINDS", "Attack", "Param", "describe", "get", "names", "register", "registered"]
