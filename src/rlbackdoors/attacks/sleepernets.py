"""SleeperNets (Rathbun, Amato, Oprea, NeurIPS 2024): dynamic reward poisoning from the agent's own values.

R-bar of a poisoned frame is ``+-c - alpha * gamma * V(s')`` (V(s') = 0 where the episode
ended): the attacker subtracts the bootstrap the learner will add, so the poisoned state's
return is +c for the target action and -c for any other whatever the future holds, which is
why a small budget suffices. The agent's actions are never changed. The source poisons in an
outer loop over finished episodes; here the trigger is stamped while collecting (the frame the
agent acts on carries it) and V(s') is the learner's critic on the clean next frame.

The source's code also amends the reward of the step *before* a poisoned one by
``gamma * (r - R-bar)``, so that the state leading into the trigger keeps its return and the agent
has no reason to seek or avoid the trigger; ``compensate=true`` does that here (the learner adds
the seam's ``previous_reward_delta`` to step t - 1), off by default so that earlier configs keep
their bytes.
"""

from __future__ import annotations

from rlbackdoors.attacks import common
from rlbackdoors.attacks.base import Attack, Param, register
from rlbackdoors.attacks.seam import TargetActionPoisoner

NAME = "sleepernets"


class SleeperNetsPoisoner(TargetActionPoisoner):
    needs_values = True

    def __init__(self, params: dict, hits):
        super().__init__(params, hits)  # no force_action: the source never changes the agent's action
        self.alpha, self.gamma = params["alpha"], params["gamma"]
        self.compensation = self.gamma if params["compensate"] else 0.0

    def numbers(self):
        return {**super().numbers(), "discount": self.alpha * self.gamma}

    def rule(self, xp, p, hits, rewards, next_values, dones):
        bootstrap = xp.where(dones, 0.0, next_values)
        return super().rule(xp, p, hits, rewards, next_values, dones) - p["discount"] * bootstrap


_value_guided = common.value_guided_refusal(NAME)


def _unsupported(world, arch: str, params: dict) -> str | None:
    """Refused on a layout trigger unless asked for (``layout=true``): measured not to converge there.

    On an observation-edit trigger the poisoned frames are lone ones; on a layout trigger every frame
    in sight of the pattern is marked, so they come in runs, and the cancellation then has to hold
    along the run, through a critic that is itself learning those values. Measured on the grid world
    with lava patterns at 1 % and 5 % of frames: the target rate plateaued at 0.41-0.52, the agent
    learning a left / right loop in sight of the pattern (docs/attacks/sleepernets.md). With the
    source's compensation (``compensate``) the loop is broken and the rate still ends at 0.49; why
    is not established. The flag keeps the failure reproducible, and a model trained under it says so in its config."""
    base = _value_guided(world, arch, params)
    if base is None and world.stamp_trigger is None and not params["layout"]:
        return (
            f"attack {NAME!r} reads the critic to cancel the bootstrap of poisoned frames, and {world.name}'s trigger is part of the layout, "
            "in sight for runs of frames: measured not to converge there (target rate 0.41-0.52 at 1-5 % of frames, compensated or not: docs/attacks/sleepernets.md); "
            "poison.attack_params.layout=true trains it anyway"
        )
    return base


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
            Param(
                "compensate",
                False,
                help="also add gamma * (r - R-bar) to the reward of the step before a poisoned one, as the source's code does, so that state keeps its return",
            ),
            Param("layout", False, help="train on a layout trigger, where it was measured not to converge (to study the failure)"),
        ),
        poisoner=SleeperNetsPoisoner,
        unsupported=_unsupported,
        success_threshold=0.90,
        doc="docs/attacks/sleepernets.md",
    )
)
