"""How often a trigger occurs by chance in clean layouts.

The paper's claim for in-distribution triggers is that the clean env *can* produce them, but
rarely. This measures "rarely": the share of clean layouts (the env's own generator, no
trigger inserted) that contain the pattern somewhere, every pattern cell lava, in any of the
trigger's allowed rotations, or whose walls wear the trigger's colours exactly (each world's
``World.chance`` says what counts, and gives the exact rate where one is known).
"""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

from rlbackdoors import worlds
from rlbackdoors.config import EnvConfig


def trigger_chance(env: EnvConfig, trigger: str, layouts: int = 100_000, seed: int = 12_345, batch: int = 10_000) -> dict:
    """Share of ``layouts`` clean layouts containing ``trigger`` (with a binomial standard error)."""
    if layouts < 1:
        raise ValueError(f"layouts={layouts!r} must be >= 1")
    world = worlds.get(env.name)
    if world.chance is None:
        defined = ", ".join(w.name for w in worlds.registered() if w.chance is not None)
        raise ValueError(f"chance occurrence is defined for layout triggers ({defined}), not env {env.name!r}")
    extra = world.chance(env, trigger, layouts, seed, lambda make, count: _count(make, count, layouts, seed, batch))
    counts, spec = extra.pop("counts"), extra.pop("trigger")
    rate = float(np.mean(counts > 0))
    return {
        "trigger": spec,
        "layouts": layouts,
        "size": env.size,
        "rate": rate,
        "stderr": math.sqrt(rate * (1 - rate) / layouts),
        **extra,
        "seed": seed,
    }


def _count(make_engine: Callable, count: Callable, layouts: int, seed: int, batch: int) -> np.ndarray:
    """``count(engine)`` per clean layout, over ``layouts`` layouts drawn ``batch`` at a time from ``seed``."""
    parts, done = [], 0
    while done < layouts:
        n = min(batch, layouts - done)
        engine = make_engine(n)
        engine.reset(seed=seed + done)
        parts.append(np.asarray(count(engine), dtype=np.int64))
        done += n
        engine.close()
    return np.concatenate(parts)
