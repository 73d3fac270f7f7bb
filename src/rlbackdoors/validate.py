"""Validation at the edge: the one error type for bad config values and the checks that raise it.

A leaf module (it imports nothing from the package), so config, the World registry and the
algorithms can all name fields the same way without importing each other.
"""

from __future__ import annotations

import math
import numbers


class ConfigError(ValueError):
    """A config value is missing, unknown, mistyped or out of range."""


def _choice(name: str, value, allowed) -> None:
    if value not in allowed:
        raise ConfigError(f"{name}={value!r} is not allowed (allowed: {', '.join(allowed)})")


def _at_least(name: str, value, low: int) -> None:
    if value < low:
        raise ConfigError(f"{name} must be >= {low}, got {value!r}")


def _in_range(name: str, value, low: int, high: int) -> None:
    """Integers with a hard ceiling: a typo'd 10**12 should be refused, not allocated."""
    if not low <= value <= high:
        raise ConfigError(f"{name} must be in {low}..{high:,}, got {value!r}")


MAX_SEED = 2**32 - 1  # numpy, torch and the env seeds (seed * 1000 + i) all take it
MAX_ENV_COPIES = 4096
MAX_EPISODES = 1_000_000
MAX_FRAMES = 10**12


def check_seed(name: str, value) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{name} must be an integer in 0..{MAX_SEED:,}, got {value!r}")
    _in_range(name, value, 0, MAX_SEED)


def _unit_interval(name: str, value) -> None:
    if not 0 <= value <= 1:
        raise ConfigError(f"{name} must be in [0, 1], got {value!r}")


def _finite(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float, numbers.Integral, numbers.Real)) and math.isfinite(value)


def _integer_at_least(name: str, value, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < low:
        raise ConfigError(f"{name} must be an integer >= {low}, got {value!r}")


def check_weights(weights: dict[str, float], field: str = "mix weight of kind {kind!r}") -> None:
    """Mixing weights must be finite, >= 0, and not all 0; ``field`` names them in the ValueError."""
    for kind, weight in weights.items():
        if not (_finite(weight) and weight >= 0):
            raise ConfigError(f"{field.format(kind=kind)} must be a finite number >= 0, got {weight!r}")
    if not sum(weights.values()) > 0:
        names = ", ".join(field.format(kind=kind) for kind in weights)
        raise ConfigError(f"{names}: the mixing weights must not all be 0, got {dict(weights)!r}")
