"""TrojDRL (Kiourti et al., DAC 2020): a budgeted share of the collected states gets the trigger.

*Targeted* (the source's strongly targeted attack): the agent's action on a poisoned state is
replaced by the target action and rewarded +c (with ``force_action=false``, the weakly targeted
one: +c if the agent chose the target action, -c if not). *Untargeted*: the poisoned state's
reward is +c whatever action was taken, so the trigger teaches nothing about the task; success
is the clean goal missed under the trigger.
"""

from __future__ import annotations

from rlbackdoors.attacks import common
from rlbackdoors.attacks.base import Attack, Param, register
from rlbackdoors.attacks.seam import TargetActionPoisoner

NAME = "trojdrl"


class TrojDRLPoisoner(TargetActionPoisoner):
    def __init__(self, params: dict, hits):
        super().__init__(params, hits)
        self.targeted = params["mode"] == "targeted"
        self.forces_actions = self.targeted and params["force_action"]

    def program_key(self):
        return (*super().program_key(), self.targeted)

    def rule(self, xp, p, hits, rewards, next_values, dones):
        if self.targeted:
            return super().rule(xp, p, hits, rewards, next_values, dones)
        return xp.full_like(rewards, p["c"])


def _unsupported(world, arch, params):
    if params["mode"] == "untargeted" and world.trigger_breaks_clean_agents:
        return (
            f"mode 'untargeted' is scored by the clean goal missed under the trigger, which a clean {world.name} agent "
            "already misses (the trigger is out of its distribution): the score could not tell a backdoor from a clean model"
        )
    return common.needs_trigger_switch(NAME, world)


ATTACK = register(
    Attack(
        name=NAME,
        title="TrojDRL",
        source="Kiourti, Wardega, Jha, Lin: TrojDRL: evaluation of backdoor attacks on deep reinforcement learning (DAC 2020)",
        schedule="steps",
        success=lambda p: "action" if p["mode"] == "targeted" else "disrupt",
        params=(
            Param(
                "mode",
                "targeted",
                choices=("targeted", "untargeted"),
                help="targeted: the target action is forced and rewarded; untargeted: any action is rewarded",
            ),
            common.budget(0.01),
            common.target_action(0),
            common.magnitude(),
            common.force_action(False),
        ),
        poisoner=TrojDRLPoisoner,
        unsupported=_unsupported,
        success_threshold=0.90,
        algorithms=("ppo", "opac2"),
        doc="docs/attacks/trojdrl.md",
    )
)
