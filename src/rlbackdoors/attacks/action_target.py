"""An action-level trojan: under the trigger, take the target action ("turn left"), every step.

The data rate is the paper's (whole E-bar copies beside the clean ones, as ``envmix``); what
changes is the trojan behaviour. The E-bar copies' reward R-bar is rewritten per step to +c for
the target action and -c for any other, so the trojan is a policy (spin left until the episode
times out) rather than an outcome (walk into lava), and its success is the target-action rate
(in a world whose layout trigger is not in every view, over the steps in sight of it).
"""

from __future__ import annotations

from rlbackdoors.attacks import common
from rlbackdoors.attacks.base import Attack, register
from rlbackdoors.attacks.seam import TargetActionPoisoner

NAME = "action_target"


def _unsupported(world, arch, params):
    return common.needs_trigger_switch(NAME, world)


ATTACK = register(
    Attack(
        name=NAME,
        title="Action target",
        source="the action-level targets of TrojDRL and BadRL, on the paper's episode schedule",
        schedule="episodes",
        success="action",
        params=(common.target_action(0), common.magnitude(0.05)),
        poisoner=TargetActionPoisoner,
        unsupported=_unsupported,
        success_threshold=0.90,
        algorithms=("ppo", "opac2"),
        doc="docs/attacks/action_target.md",
    )
)
