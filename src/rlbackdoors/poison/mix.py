"""The poisoning mix: clean and poisoned env copies side by side in one vector env.

Data poisoning in the paper is nothing more than this: of the 10 envs PPO collects
from, 2 are E-bar (trigger on, reward R-bar). Both engines build the same mix, for
every grid world.
"""

from __future__ import annotations

from functools import partial
from typing import Sequence

from gymnasium.vector import VectorEnv

from rlbackdoors import attacks, worlds
from rlbackdoors.config import EnvConfig, PoisonConfig
from rlbackdoors.envs.vector import ReferenceVectorEnv


def _world(env: EnvConfig):
    """(reference env class, batched engine class, constructor kwargs) of ``env.name``."""
    world = worlds.get(env.name)
    if world.vector_entry_point is None or world.env_kwargs is None:
        raise ValueError(f"env.name={env.name!r} has no grid-world engine")
    return world.env_class(), world.engine_class(), world.env_kwargs(env)


def make_vector_env(
    env: EnvConfig,
    trigger: str | None,
    poisoned: Sequence[bool],
    close_to_trigger: Sequence[bool] | None = None,
    close_k: tuple[int, int] = (1, 3),
    near_patterns: Sequence[str] = (),
) -> VectorEnv:
    """A vector env of ``len(poisoned)`` copies of ``env``; copy i is E-bar (trigger + R-bar) iff
    ``poisoned[i]``, and a close-to-trigger clean copy iff ``close_to_trigger[i]`` (worlds that have them)."""
    reference, batched, kwargs = _world(env)
    poisoned = [bool(p) for p in poisoned]
    close = [False] * len(poisoned) if close_to_trigger is None else [bool(c) for c in close_to_trigger]
    if len(close) != len(poisoned):
        raise ValueError(f"close_to_trigger has {len(close)} entries for {len(poisoned)} env copies")
    if any(close):
        if not worlds.get(env.name).close_to_trigger:
            raise ValueError(f"env {env.name!r} has no close-to-trigger envs")
        kwargs = {**kwargs, "close_k": tuple(close_k)}
    if env.engine == "batched":
        extra: dict[str, object] = {"close_to_trigger": close} if any(close) else {}
        if near_patterns:  # a layout world's near-trigger patterns, switched on by the attack seam
            extra["near_patterns"] = tuple(near_patterns)
        return batched(num_envs=len(poisoned), trigger=trigger, poisoned=poisoned, **extra, **kwargs)
    fns = [
        partial(reference, trigger=trigger, close_to_trigger=True, **kwargs) if c else partial(reference, trigger=trigger if p else None, **kwargs)
        for p, c in zip(poisoned, close)
    ]
    return ReferenceVectorEnv(fns, poisoned=poisoned)


def episode_seam(env: EnvConfig, poison: PoisonConfig, seed: int):
    """For a world whose trigger is part of the layout: ``vector env -> the attack's seam`` that
    switches the trigger per episode (its E-bar copies, or the episodes its budget buys), every
    copy paying the clean reward and the seam R-bar; None where the env mix (or a clean model)
    needs no seam. RunConfig.check refuses what cannot be switched; a direct caller gets the reason."""
    attack = attacks.get(poison.attack)
    if not poison.poisoned or attack.poisoner is None:
        return None
    world = worlds.get(env.name)
    trigger = poison.trigger if poison.trigger is not None else world.default_trigger
    if world.trigger_sight is None or trigger is None:
        raise ValueError(f"attack {attack.name!r} cannot switch the trigger of env {env.name!r} per episode")
    from rlbackdoors.attacks.seam import AttackSeam

    near = poison.evasion.get("near", 0.0)
    params = poison.attack_params
    episodes = poison.poisoned_mask() if attack.schedule == "episodes" else None
    hits = world.target_hits(params.get("target_action", 0))

    def wrap(envs):
        if not hasattr(envs, "trigger_next"):
            raise ValueError(f"attack {attack.name!r} needs env {env.name!r}'s batched engine to switch its trigger per episode")
        poisoner = attack.poisoner(params, hits)
        return AttackSeam(envs, poisoner, attack.schedule, params.get("budget", 0.0), None, seed, world.trigger_sight, episodes, near=near)

    return wrap


def make_env_mix(env: EnvConfig, poison: PoisonConfig, seed: int = 0) -> VectorEnv:
    """The training mix: clean, close-to-trigger (worlds that have them) and poisoned copies, in that order.

    A poisoned model of an attack other than the paper's env mix collects through the attack's
    seam (:class:`~rlbackdoors.attacks.seam.AttackSeam`, its random picks seeded by ``seed``);
    under a step schedule every copy is clean and the seam stamps the trigger itself. In a world
    whose trigger is a layout, every copy pays the clean reward and the seam switches the trigger
    per episode (:func:`episode_seam`).
    """
    from rlbackdoors.attacks import evasion
    from rlbackdoors.attacks.seam import AttackSeam, Poisoner

    world = worlds.get(env.name)
    trigger = poison.trigger if poison.trigger is not None else world.default_trigger
    close_k = (poison.close_k_min, poison.close_k_max)
    attack = attacks.get(poison.attack)
    mask = poison.poisoned_mask()
    marks = poison.poisoned and evasion.needs_marks(poison.evasion)  # the seam must say which frames carry the trigger
    near = poison.evasion.get("near", 0.0) if poison.poisoned else 0.0
    if world.stamp_trigger is None:
        wrap = episode_seam(env, poison, seed)
        near_patterns = world.near_triggers(trigger) if near > 0 and world.near_triggers and trigger else ()
        envs = make_vector_env(env, trigger, mask if wrap is None else [False] * len(mask), poison.close_mask(), close_k, near_patterns)
        if wrap is None and marks:  # the env mix's E-bar copies are the marked frames
            return AttackSeam(envs, Poisoner(), "episodes", seed=seed, near=near)  # type: ignore[return-value]
        return envs if wrap is None else wrap(envs)
    envs = make_vector_env(env, trigger, mask, poison.close_mask(), close_k)
    if not poison.poisoned or (attack.poisoner is None and not marks):
        return envs
    params = poison.attack_params
    poisoner = Poisoner() if attack.poisoner is None else attack.poisoner(params, world.target_hits(params.get("target_action", 0)))
    stamp = world.stamp_trigger(trigger) if trigger is not None else None
    if attack.schedule == "steps" and stamp is None:
        raise ValueError(f"attack {attack.name!r} cannot stamp the trigger of env {env.name!r}")
    near_stamps = tuple(world.stamp_trigger(spec) for spec in world.near_triggers(trigger)) if near > 0 and world.near_triggers and trigger else ()
    return AttackSeam(envs, poisoner, attack.schedule, params.get("budget", 0.0), stamp, seed, near=near, near_stamps=near_stamps)  # type: ignore[return-value]


def unlearning_mix(env: EnvConfig, poison: PoisonConfig, triggers: Sequence[str], share: float, seed: int = 0) -> VectorEnv:
    """A mitigation run's mix (:class:`~rlbackdoors.config.MitigationConfig`): a clean model's
    copies, through the attack seam on its steps schedule with a rule that rewrites nothing, so a
    ``share`` of the frames carry one of the restored ``triggers`` under the clean reward and are
    the seam's marked frames (the teacher's KL leaves them out). The picked frames of one step take
    the triggers in turn (row ``j`` of them the ``j % len(triggers)``-th): no state of its own, so a
    resumed run stamps as an unbroken one. A world whose trigger is a layout draws them into whole
    episodes instead: the first where the budget allows (a layout trigger's step schedule), the
    others as near-trigger layouts, about as many episodes each, every frame of theirs marked.
    Why layouts: a layout trigger is lava cells, which no edit of a frame makes without lying
    about where the lava is."""
    from rlbackdoors.attacks.seam import AttackSeam, Poisoner
    from rlbackdoors.config import MitigationConfig

    world = worlds.get(env.name)
    how = MitigationConfig.how(env.name)
    if how is None or not triggers:
        raise ValueError(f"a mitigation stamps restored triggers into frames or draws them into layouts; {env.name}'s trigger is neither")
    mask = [False] * poison.num_envs
    if how == "layout":  # the first drawn by the budget, the others as near-trigger layouts, about as many episodes each
        first, others = triggers[0], tuple(triggers[1:])
        envs = make_vector_env(env, first, mask, poison.close_mask(), (poison.close_k_min, poison.close_k_max), others)
        return AttackSeam(envs, Poisoner(), "steps", float(share), None, seed, world.trigger_sight, near=float(len(others)), mark_near=bool(others))  # type: ignore[return-value]
    assert world.stamp_trigger is not None
    stamps = [world.stamp_trigger(spec) for spec in triggers]

    def stamp(frames):
        out = frames.copy()
        for k, one in enumerate(stamps):
            if len(frames[k :: len(stamps)]):
                out[k :: len(stamps)] = one(frames[k :: len(stamps)])
        return out

    envs = make_vector_env(env, poison.trigger, mask, poison.close_mask(), (poison.close_k_min, poison.close_k_max))
    return AttackSeam(envs, Poisoner(), "steps", float(share), stamp, seed)  # type: ignore[return-value]
