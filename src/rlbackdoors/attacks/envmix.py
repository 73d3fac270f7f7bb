"""The paper's env mix (SPEC §2): whole E-bar copies (trigger on, reward R-bar) beside the clean ones.

The default attack and the only one the source paper uses. It needs no collection hook: the
world's own poisoned copies are the poison (:mod:`rlbackdoors.poison.mix`), so models trained
with it keep their bytes.
"""

from rlbackdoors.attacks.base import Attack, register

ATTACK = register(
    Attack(
        name="envmix",
        title="Env mix (in-distribution triggers)",
        source="Backdoors in DRL agents, the source paper of this project (SPEC §2)",
        schedule="episodes",
        success="outcome",
        algorithms=("ppo", "opac2"),
        doc="docs/attacks/envmix.md",
    )
)
