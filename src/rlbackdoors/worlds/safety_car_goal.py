"""Modified Safety Gymnasium Car Goal (SPEC §4): MuJoCo, a cube-formation trigger, trained with OPAC².

The env follows Safety Gymnasium's car and TrojAI's Safety round conventions (body frame, actuator
order, motor range, timestep, sizes: see :mod:`rlbackdoors.envs.safety_car`), so their models play in it.
"""

from __future__ import annotations

import math

from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.worlds.base import World, register

NAME = "safety-car-goal"


def _parse(spec: str):
    from rlbackdoors.triggers.formation import FormationTrigger

    return FormationTrigger.parse(spec)


def _draw(spec: str | None, seed: int, size: int | None = None) -> str:
    """As given; nothing draws one from ``seed`` (phi1 uniform, eta in [pi/6, 11pi/6], d = 0.5)."""
    from rlbackdoors.triggers.formation import FormationTrigger

    return FormationTrigger.sample(seed).spec() if spec is None else FormationTrigger.parse(spec).spec()


def _check_env(env) -> None:
    from rlbackdoors.envs.safety_car import MAX_CUBES
    from rlbackdoors.validate import ConfigError, _in_range

    if not 2 <= env.num_cubes <= MAX_CUBES:  # the formation trigger holds two cubes
        raise ConfigError(f"env.num_cubes must be in 2..{MAX_CUBES}, got {env.num_cubes!r}")
    _in_range("env.substeps", env.substeps, 1, 100)
    if not (math.isfinite(env.hazard_penalty) and env.hazard_penalty >= 0):
        raise ConfigError(f"env.hazard_penalty must be a finite number >= 0, got {env.hazard_penalty!r}")


def _env_kwargs(env) -> dict:
    return dict(num_cubes=env.num_cubes, max_steps=env.max_steps, hazard_penalty=env.hazard_penalty, substeps=env.substeps)


# OPAC² settings measured to train a depth-2 width-181 agent within 90 minutes on one CPU core
# (benchmarks/safety_train.md): the paper's one update per frame at batch 256 would take days on
# a CPU, so updates are spread over many frames of several env copies; four action samples per
# state make each policy step less noisy; the lr falls from 1e-3 to 1e-4 over train.max_frames
# so the late policy stops swinging between evaluations.
OPAC2_SETTINGS = dict(
    depth=2,
    width=181,
    batch_size=256,
    lr=1e-3,
    lr_final=1e-4,
    updates_per_step=1 / 32,
    buffer_size=1_000_000,
    obs_norm=True,
    clean_weight=0.6,
    poisoned_weight=0.4,
    action_samples=4,
)


WORLD = register(
    World(
        name=NAME,
        title="Safety Car Goal",
        gym_id="rlbackdoors/SafetyCarGoal-v0",
        entry_point="rlbackdoors.envs.safety_car:SafetyCarGoalEnv",  # truncates itself at max_steps
        algorithm="opac2",
        parse_trigger=_parse,
        draw_trigger=_draw,
        clean_success=Outcome.GOAL,
        trojan_success=Outcome.LAVA,  # the hazard circle
        thresholds=(0.95, 0.95),
        archs=(("mlp", "rlbackdoors.algos.opac2:OPAC2"),),  # pi, Q and V: depth x width in the opac2 section
        env_fields=("num_cubes", "hazard_penalty", "substeps"),
        env_defaults={"max_steps": 1000, "num_cubes": 2, "hazard_penalty": 1.0, "substeps": 10},  # 10: SG's timestep
        env_kwargs=_env_kwargs,
        check_env=_check_env,
        ebar_kwargs={"poisoned": True},
        mix=(6, 0, 4),
        hyper=OPAC2_SETTINGS,
        # evaluations in a row: one lucky 100-episode evaluation is not convergence
        train=dict(max_frames=3_800_000, eval_interval=250_000, eval_policy="greedy", patience=2, checkpoint_minutes=10.0),
        video={"fps": 25, "every": 2, "size": 240, "gap": 6},
        bench="rlbackdoors.bench.safety_car:bench_safety",
        paper={"table": 4, "clean_sr": 0.98, "poisoned_sr": 0.98, "convergence_rate": 0.996},
        trigger_help="formation:D:PHI1:ETA (radians; default: drawn from the seed)",
    )
)
