"""SleeperNets (Rathbun, Amato, Oprea, NeurIPS 2024): dynamic reward poisoning from the agent's own values.

R-bar of a poisoned frame is ``+-c - alpha * gamma * V(s')`` (V(s') = 0 where the episode
ended): the attacker subtracts the bootstrap the learner will add, so the poisoned state's
return is +c for the target action and -c for any other whatever the future holds, which is
why a small budget suffices. The agent's actions are never changed. The source poisons in an
outer loop over finished episodes; here the trigger is stamped while collecting (the frame the
agent acts on carries it) and V(s') is the learner's critic on the clean next frame.
"""

from __future__ import annotations

import numpy as np

from rlbackdoors.attacks import common
from rlbackdoors.attacks.base import Attack, Param, register
from rlbackdoors.attacks.seam import TargetActionPoisoner

NAME = "sleepernets"


class SleeperNetsPoisoner(TargetActionPoisoner):
    needs_values = True

    def __init__(self, params: dict, hits):
        super().__init__(params, hits)  # no force_action: the source never changes the agent's action
        self.alpha, self.gamma = params["alpha"], params["gamma"]

    def reward(self, rewards, actions, marked, next_values, dones):
        bootstrap = np.where(dones, 0.0, next_values)
        return super().reward(rewards, actions, marked, next_values, dones) - self.alpha * self.gamma * bootstrap


_unsupported = common.value_guided_refusal(NAME)


ATTACK = register(
    Attack(
        name=NAME,
        title="SleeperNets",
        source="Rathbun, Amato, Oprea: SleeperNets: universal backdoor poisoning attacks against reinforcement learning agents (NeurIPS 2024)",
        schedule="steps",
        success="action",
        params=(
            common.budget(0.01),
            common.target_action(0),
            common.magnitude(),
            Param("alpha", 1.0, 0.0, 10.0, help="weight of the subtracted bootstrap alpha * gamma * V(s')"),
            Param("gamma", 0.99, 0.0, 1.0, help="the discount the attacker assumes (0.99: ppo.gamma's default)"),
        ),
        poisoner=SleeperNetsPoisoner,
        unsupported=_unsupported,
        success_threshold=0.90,
        doc="docs/attacks/sleepernets.md",
    )
)
