"""Randomized LavaWorld (SPEC §2): random single lava squares; the trigger is a lava pattern the
clean generator can produce too (in-distribution)."""

from __future__ import annotations

import numpy as np

from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.worlds.base import World, register

NAME = "randomized-lavaworld"


def _parse(spec: str):
    from rlbackdoors.triggers.pattern import PatternTrigger

    return PatternTrigger.parse(spec)


def _near(spec: str) -> tuple[str, ...]:
    from rlbackdoors.triggers.pattern import near_patterns

    return tuple(p.spec() for p in near_patterns(_parse(spec)))


def _draw(spec: str | None, seed: int, size: int | None = None) -> str:
    if spec is None:
        spec = WORLD.default_trigger
        assert spec is not None  # this world has a default trigger
    return _parse(spec).spec()


def _check_env(env) -> None:
    from rlbackdoors.validate import ConfigError, _at_least, _in_range

    _in_range("env.size", env.size, 5, 64)
    _at_least("env.num_lava", env.num_lava, 0)
    free = (env.size - 2) ** 2 - 2  # inside the outer walls, minus start and goal
    if env.num_lava > free // 2:
        raise ConfigError(f"env.num_lava={env.num_lava} is too many for size {env.size} (at most {free // 2})")


def _env_kwargs(env) -> dict:
    return dict(size=env.size, max_steps=env.max_steps, see_through_walls=env.see_through_walls, num_lava=env.num_lava)


def _chance(env, trigger: str, layouts: int, seed: int, count) -> dict:
    """Clean layouts holding the pattern, every cell lava, in any allowed rotation."""
    from rlbackdoors.envs.randomized_lavaworld_batched import BatchedRandomizedLavaWorld
    from rlbackdoors.triggers.pattern import PatternTrigger, find_pattern

    pattern = PatternTrigger.parse(trigger)
    counts = count(
        lambda n: BatchedRandomizedLavaWorld(n, size=env.size, num_lava=env.num_lava, max_steps=env.max_steps),
        lambda engine: find_pattern(engine.lava_masks(), pattern),
    )
    return {"trigger": pattern.spec(), "counts": counts, "num_lava": env.num_lava, "placements_per_layout": float(np.sum(counts)) / layouts}


WORLD = register(
    World(
        name=NAME,
        title="Randomized LavaWorld",
        gym_id="rlbackdoors/RandomizedLavaWorld-v0",
        entry_point="rlbackdoors.envs.randomized_lavaworld:RandomizedLavaWorldEnv",
        vector_entry_point="rlbackdoors.envs.randomized_lavaworld_batched:BatchedRandomizedLavaWorld",
        compiled_engine="rlbackdoors.envs.randomized_lavaworld_jax:randomized_lavaworld_jax",
        # one agent a program: its networks' iteration ran x1.68 (CNN) and x1.60 (FC) of the torch
        # group of 8 alone, x1.27 and x1.31 in compiled groups of 8 (2-core AMD EPYC, 2026-12-02)
        compiled_cpu_group=1,
        # cnn: a zoo x1.14-1.20; 20 seeds equivalent (TOST). The FC has no equivalence report yet
        compiled_default=("cnn",),
        algorithm="ppo",
        parse_trigger=_parse,
        draw_trigger=_draw,
        clean_success=Outcome.GOAL,
        trojan_success=Outcome.PATTERN_LAVA,  # only lava of the pattern is the trojan task
        # The paper selected models at 90% on both; we stop at clean >= 95% (a clean model
        # stopped at 90% on 100 episodes measured 0.885 on 200) and poisoned >= 90%.
        thresholds=(0.95, 0.90),
        archs=(
            ("fc", "rlbackdoors.models.randomized_lavaworld:DirectionFCModel"),
            ("cnn", "rlbackdoors.models.randomized_lavaworld:DirectionCNNModel"),
        ),
        # TrojAI's Randomized LavaWorld round (Aug 2023) saved {"model": CLASS, "state_dict": ...,
        # gymnasium spaces}: its FCModel and CNNModel are fc and cnn, layer for layer.
        trojai_archs=(("FCModel", "fc"), ("CNNModel", "cnn")),
        # the Aug 2023 round's env-string.txt: MiniGrid-LavaCrossingS9N1-v0 for 9x9 rooms with one
        # lava square (its config.json gives the grid size only; the example's args.json says 1)
        trojai_env_string_count="num_lava",
        placeholder_triggers=("cells:0,0",),  # one cell: fits any num_lava >= 1 (TrojAI's 9x9 rooms had 1)
        env_fields=("size", "see_through_walls", "engine", "num_lava"),
        env_defaults={"max_steps": 250, "engine": "batched", "size": 11, "see_through_walls": True, "num_lava": 10},
        env_kwargs=_env_kwargs,
        check_env=_check_env,
        default_trigger="cross",
        # 9 clean : 1 poisoned, not the paper's 8 : 2: with 2 poisoned copies the FC learnt the
        # backdoor while its clean task collapsed (measured, docs/randomized-lavaworld.md)
        mix=(9, 0, 1),
        curriculum=True,
        chance=_chance,
        # The paper's Table 2 (label -> arch -> clean SR, poisoned SR, clean reward, poisoned
        # reward) and Table 5.
        near_triggers=_near,
        trigger_sight="frame",  # per-episode attacks (attacks/seam.py)
        paper={
            "table": 2,
            "tables": {
                "clean": {"cnn": (1.00, 0.25, 0.93, 0.24), "fc": (1.00, 0.23, 0.93, 0.21)},
                "poisoned": {"cnn": (1.00, 0.93, 0.93, 0.90), "fc": (1.00, 0.93, 0.93, 0.90)},
            },
            "convergence_rate": 0.134,
            "clean_convergence_rate": 1.0,
        },
        trigger_help="cross | arrow | arrow:east|south|west|north | a cell list (cells:0,0;1,1[:any])",
    )
)
