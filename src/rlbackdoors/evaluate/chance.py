"""How often a trigger occurs by chance in clean layouts.

The paper's claim for in-distribution triggers is that the clean env *can* produce them, but
rarely. This measures "rarely": the share of clean layouts (the env's own generator, no
trigger inserted) that contain the pattern somewhere, every pattern cell lava, in any of the
trigger's allowed rotations (Randomized LavaWorld), or whose walls wear the trigger's colours
exactly (Colorful Memory, where the exact rate is also known: 6 to the minus number of squares).
"""

from __future__ import annotations

import math

import numpy as np

from rlbackdoors.config import EnvConfig


def trigger_chance(env: EnvConfig, trigger: str, layouts: int = 100_000, seed: int = 12_345, batch: int = 10_000) -> dict:
    """Share of ``layouts`` clean layouts containing ``trigger`` (with a binomial standard error)."""
    if layouts < 1:
        raise ValueError(f"layouts={layouts!r} must be >= 1")
    if env.name == "colorful-memory":
        return _wall_color_chance(env, trigger, layouts, seed, batch)
    if env.name != "randomized-lavaworld":
        raise ValueError(
            f"chance occurrence is defined for layout triggers (randomized-lavaworld, colorful-memory), not env {env.name!r}"
        )
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


def _wall_color_chance(env: EnvConfig, trigger: str, layouts: int, seed: int, batch: int) -> dict:
    from rlbackdoors.envs.colorful_memory_batched import BatchedColorfulMemory
    from rlbackdoors.triggers.wall_colors import WallColorTrigger, chance_probability

    wall = WallColorTrigger.parse(trigger, rng=seed, size=env.size)
    hits = done = 0
    while done < layouts:
        n = min(batch, layouts - done)
        engine = BatchedColorfulMemory(n, size=env.size, max_steps=env.max_steps)
        engine.reset(seed=seed + done)
        hits += int(engine.trigger_present(wall).sum())
        done += n
        engine.close()
    rate = hits / layouts
    return {
        "trigger": wall.spec(),
        "layouts": layouts,
        "size": env.size,
        "rate": rate,
        "stderr": math.sqrt(rate * (1 - rate) / layouts),
        "exact_rate": chance_probability(wall, env.size),
        "seed": seed,
    }
