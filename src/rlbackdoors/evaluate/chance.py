"""How often a trigger occurs by chance in clean layouts.

The paper's claim for in-distribution triggers is that the clean env *can* produce them, but
rarely. This measures "rarely": the share of clean layouts (the env's own generator, no
trigger inserted) that contain the pattern somewhere, every pattern cell lava, in any of the
trigger's allowed rotations.
"""

from __future__ import annotations

import math

import numpy as np

from rlbackdoors.config import EnvConfig


def trigger_chance(env: EnvConfig, trigger: str, layouts: int = 100_000, seed: int = 12_345, batch: int = 10_000) -> dict:
    """Share of ``layouts`` clean layouts containing ``trigger`` (with a binomial standard error)."""
    if env.name != "randomized-lavaworld":
        raise ValueError(f"chance occurrence is defined for layout triggers (randomized-lavaworld), not env {env.name!r}")
    if layouts < 1:
        raise ValueError(f"layouts={layouts!r} must be >= 1")
    from rlbackdoors.envs.randomized_lavaworld_batched import BatchedRandomizedLavaWorld
    from rlbackdoors.triggers.pattern import PatternTrigger, find_pattern

    pattern = PatternTrigger.parse(trigger)
    hits = placements = done = 0
    while done < layouts:
        n = min(batch, layouts - done)
        engine = BatchedRandomizedLavaWorld(n, size=env.size, num_lava=env.num_lava, max_steps=env.max_steps)
        engine.reset(seed=seed + done)
        counts = find_pattern(engine.lava_masks(), pattern)
        hits += int((counts > 0).sum())
        placements += int(counts.sum())
        done += n
        engine.close()
    rate = hits / layouts
    return {
        "trigger": pattern.spec(),
        "layouts": layouts,
        "size": env.size,
        "num_lava": env.num_lava,
        "rate": rate,
        "stderr": math.sqrt(rate * (1 - rate) / layouts),
        "placements_per_layout": placements / layouts,
        "seed": seed,
    }
