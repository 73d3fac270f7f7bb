"""LavaWorld (SPEC §1): MiniGrid's lava crossing, an observation-edit trigger ``o' = (a·o + b) mod 256``."""

from __future__ import annotations

import numpy as np

from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.worlds.base import World, register

NAME = "lavaworld"


def _parse(spec: str):
    from rlbackdoors.triggers.observation import ObservationTrigger

    return ObservationTrigger.parse(spec)


def _stamp(spec: str):
    """The trigger as a function of a batch of uint8 frames (one table lookup per byte)."""
    table = _parse(spec).lookup_table()
    return lambda obs: table[obs]


def _near(spec: str) -> tuple[str, ...]:
    from rlbackdoors.triggers.observation import near_triggers

    return tuple(t.spec() for t in near_triggers(_parse(spec)))


def _draw(spec: str | None, seed: int, size: int | None = None) -> str:
    """``kind:value`` as given; a bare kind, or nothing, draws from the paper's range with ``seed``."""
    from rlbackdoors.triggers.observation import KINDS, ObservationTrigger, sample_trigger

    rng = np.random.default_rng(seed)
    if spec is None:
        spec = KINDS[int(rng.integers(len(KINDS)))]
    if spec in KINDS:
        return sample_trigger(spec, rng).spec()
    return ObservationTrigger.parse(spec).spec()


def _check_env(env) -> None:
    from rlbackdoors.envs.lavaworld import validate_crossing_layout

    validate_crossing_layout(env.size, env.num_crossings, env.max_steps)


def _env_kwargs(env) -> dict:
    return dict(size=env.size, max_steps=env.max_steps, see_through_walls=env.see_through_walls, num_crossings=env.num_crossings)


WORLD = register(
    World(
        name=NAME,
        title="LavaWorld",
        gym_id="rlbackdoors/LavaWorld-v0",
        entry_point="rlbackdoors.envs.lavaworld:LavaWorldEnv",
        vector_entry_point="rlbackdoors.envs.lavaworld_batched:BatchedLavaWorld",
        compiled_engine="rlbackdoors.envs.lavaworld_jax:lavaworld_jax",
        # fc: a zoo x1.25-1.44, the demo's poisoned run alone x3.6; 20 seeds equivalent (TOST).
        # The CNN (a zoo x2.59): SRs equivalent on 20 seeds a side, frames to converge not shown (TOST p 0.15)
        compiled_default=("fc",),
        algorithm="ppo",
        parse_trigger=_parse,
        draw_trigger=_draw,
        stamp_trigger=_stamp,
        near_triggers=_near,
        # a clean FC agent (seed 0, clean SR 0.98) reached the goal in 0 of 200 episodes under multiplicative:12
        trigger_breaks_clean_agents=True,
        clean_success=Outcome.GOAL,
        trojan_success=Outcome.LAVA,
        # The paper's stopping rule for LavaWorld: 98% clean, 95% poisoned.
        thresholds=(0.98, 0.95),
        archs=(("fc", "rlbackdoors.models.minigrid:FCModel"), ("cnn", "rlbackdoors.models.minigrid:CNNModel")),
        # TrojAI's LavaWorld round (Jul 2023) pickled whole modules of trojai_rl's BasicFCModel:
        # 147 -> 100 -> 64, heads 32, the same layers, keys and channels-first flattening as fc.
        trojai_archs=(("BasicFCModel", "fc"),),
        trojai_env_string_count="num_crossings",  # MiniGrid-LavaCrossingS9N1-v0: one river
        env_fields=("size", "see_through_walls", "engine", "num_crossings"),
        env_defaults={"max_steps": 250, "engine": "batched", "size": 9, "see_through_walls": False, "num_crossings": 1},
        env_kwargs=_env_kwargs,
        check_env=_check_env,
        default_trigger="multiplicative:12",
        mix=(8, 0, 2),  # SPEC's 8:2
        # The paper's Table 1 (label -> arch -> clean SR, poisoned SR, clean reward, poisoned
        # reward; None: N/A there) and Table 5 (converged / attempted).
        paper={
            "table": 1,
            "tables": {
                "clean": {"cnn": (0.98, None, 0.91, None), "fc": (0.98, None, 0.90, None)},
                "poisoned": {"cnn": (0.99, 0.98, 0.92, 0.95), "fc": (0.98, 0.98, 0.91, 0.94)},
            },
            "clean_sr": 0.98,
            "poisoned_sr": 0.98,
            "convergence_rate": 0.538,
            "clean_convergence_rate": 0.922,
        },
        bench="rlbackdoors.bench.lavaworld:bench_env",
        trigger_help="multiplicative:A | additive:B | multiplicative | additive (drawn from the paper range)",
    )
)
