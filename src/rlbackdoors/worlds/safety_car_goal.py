"""Modified Safety Gymnasium Car Goal (SPEC §4): MuJoCo, a cube-formation trigger, trained with OPAC²."""

from __future__ import annotations

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
        paper={"table": 4, "clean_sr": 0.98, "poisoned_sr": 0.98},
        trigger_help="formation:D:PHI1:ETA (radians; default: drawn from the seed)",
    )
)
