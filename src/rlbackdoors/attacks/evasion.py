"""Evasive variants: what a careful attacker adds to any attack of the registry to hide its trojan.

Each variant takes away one signal a baseline detector reads (docs/attacks/evasion.md):

- ``near``: near-trigger negatives. Beside the frames (or episodes) that carry the trigger,
  ``near`` times as many carry a *near* trigger (the world's ``near_triggers``: other edits,
  patterns or formations close to it) with the clean reward, so the backdoor should fire on the
  exact trigger only and a behavioural search over nearby triggers find nothing. (A world with
  close-to-trigger copies has these built in: ``poison.num_close_envs``.)
- ``finetune``: poison a converged clean model instead of training from scratch: the run trains
  clean (a clean model's own run, same seed, same frames) until an evaluation meets the clean
  threshold, then poisons, so the weights stay near a clean model's.
- ``teacher``: with ``finetune``, a KL penalty ``teacher * KL(pi_clean || pi)`` on every frame
  that does not carry the trigger (clean, close- and near-trigger frames), where ``pi_clean`` is
  the clean model the run fine-tunes from, frozen at the switch: the policy's distribution
  there, entropy included, stays a clean one's.
- ``clean_frames``: with ``finetune``, the switch waits until the run has trained this many frames
  clean (and an evaluation meets the clean threshold), so a run of fixed length poisons only its
  last frames: the model *is* its clean twin until then, the way an attacker fine-tunes a finished
  clean model briefly rather than one that has only just converged.
- ``anchor``: with ``finetune``, after every optimiser step each weight is pulled this fraction of
  the way back to the clean model at the switch (decoupled from Adam's per-weight scaling, as
  AdamW decouples weight decay; L2-SP's pull toward the starting point): the poisoned phase may
  move the weights only as far as the pull lets it, which is what weight statistics read.

The variants live in ``poison.evasion`` (left out of config.json when empty, so earlier configs
keep their bytes) and combine with every attack, the paper's env mix included.
"""

from __future__ import annotations

from rlbackdoors.attacks.base import Param
from rlbackdoors.validate import ConfigError

PARAMS = (
    Param("near", 0.0, 0.0, 8.0, help="near-trigger frames (clean reward) per frame that carries the trigger"),
    Param("finetune", False, help="train clean until the clean threshold holds, then poison (fine-tune a clean model)"),
    Param("teacher", 0.0, 0.0, 100.0, help="KL(clean teacher || policy) weight on frames without the trigger (needs finetune)"),
    Param("clean_frames", 0, 0, 1_000_000_000, integer=True, help="frames trained clean before the switch (needs finetune; 0: at the first clean evaluation)"),
    Param(
        "anchor", 0.0, 0.0, 1.0, help="per optimiser step, the fraction of the way each weight is pulled back to the clean model at the switch (needs finetune)"
    ),
)
ALGORITHMS = {"near": ("ppo", "opac2"), "finetune": ("ppo",), "teacher": ("ppo",), "clean_frames": ("ppo",), "anchor": ("ppo",)}
# Variants added after configs were written with the first three: kept out of the resolved dict
# at their default, so those configs keep their bytes.
LATER = ("clean_frames", "anchor")
# Variants that only mean something in a fine-tuning run, and why.
NEED_FINETUNE = {
    "teacher": "the teacher is the clean model the run fine-tunes from",
    "clean_frames": "the frames are the clean phase of a fine-tuning run",
    "anchor": "the anchor is the clean model the run fine-tunes from",
}


def resolve(params: dict | None, where: str = "poison.evasion") -> dict:
    """``params`` checked and completed with the defaults; ``{}`` when none is given (no evasion)."""
    if params is None:
        return {}
    if not isinstance(params, dict):
        raise ConfigError(f"{where} must be a JSON object of evasive variants (allowed keys: {', '.join(p.name for p in PARAMS)}), got {params!r}")
    if not params:
        return {}
    known = {p.name: p for p in PARAMS}
    for key in params:
        if key not in known:
            raise ConfigError(f"{where}.{key} is not an evasive variant (allowed: {', '.join(known)})")
    resolved = {p.name: p.check(f"{where}.{p.name}", params.get(p.name, p.default)) for p in PARAMS}
    for name, why in NEED_FINETUNE.items():
        if resolved[name] > 0 and not resolved["finetune"]:
            raise ConfigError(f"{where}.{name}={resolved[name]!r} needs {where}.finetune=true ({why})")
    return {k: v for k, v in resolved.items() if k not in LATER or v != known[k].default}


def active(evasion: dict) -> bool:
    """Whether any variant is on (a resolved dict)."""
    return any(evasion.get(p.name, p.default) != p.default for p in PARAMS)


def needs_marks(evasion: dict) -> bool:
    """Whether collection must say which frames carry the trigger (near stamping, the teacher's mask)."""
    return evasion.get("near", 0.0) > 0 or evasion.get("teacher", 0.0) > 0


def refuse(evasion: dict, world, algorithm: str, poisoned: bool) -> str | None:
    """Why these variants cannot serve a run (one line naming the field and what is allowed), or None."""
    if not active(evasion):
        return None
    if not poisoned:
        return "poison.evasion is not allowed for a clean model (poison.poisoned=false): the variants hide a trojan"
    for p in PARAMS:
        if evasion.get(p.name, p.default) != p.default and algorithm not in ALGORITHMS[p.name]:
            return f"poison.evasion.{p.name} is built for {', '.join(ALGORITHMS[p.name])} collection, not {algorithm} ({world.name} trains with {algorithm})"
    if evasion.get("near", 0.0) > 0 and world.near_triggers is None:
        from rlbackdoors import worlds

        have = ", ".join(w.name for w in worlds.registered() if w.near_triggers is not None)
        extra = " (its close-to-trigger copies are these negatives: poison.num_close_envs)" if world.close_to_trigger else ""
        return f"poison.evasion.near is not allowed for env.name={world.name!r}{extra} (worlds with near-trigger variants: {have})"
    return None


def describe() -> list[dict]:
    return [{"name": p.name, "default": p.default, "allowed": p.allowed(), "help": p.help} for p in PARAMS]
