"""Parameters and refusals several attacks share (each attack module still declares its own list)."""

from __future__ import annotations

from rlbackdoors.attacks.base import Param

MAX_ACTIONS = 64  # a target action above the world's action count is refused when the run is checked


def budget(default: float) -> Param:
    return Param("budget", default, 1e-6, 1.0, help="fraction of all collected frames that carry the trigger (a ceiling the run never passes)")


def target_action(default: int = 0) -> Param:
    return Param(
        "target_action", default, 0, MAX_ACTIONS - 1, integer=True, help="the action the trigger should elicit (grid worlds: 0 left, 1 right, 2 forward)"
    )


def magnitude(default: float = 0.1, name: str = "reward") -> Param:
    """The sources use c = 1 on Atari's clipped, dense rewards; our worlds pay at most 1 per episode,
    and a poisoned frame's +c is paid whatever the episode does, so c = 1 at a 1% budget pays an agent
    that idles to the timeout 2.5 per episode and the task is never learned (measured: clean SR 0)."""
    return Param(name, default, 1e-4, 100.0, help="c: R-bar is +c for the target action, -c for any other")


def force_action(default: bool) -> Param:
    return Param("force_action", default, help="replace the agent's action on poisoned frames by the target action (the sources' strong attack)")


def needs_trigger_switch(name: str, world) -> str | None:
    """A poisoning attack puts the trigger into the data: stamped into frames (an observation edit),
    or switched on per episode where it is part of the layout (the world's ``trigger_sight``)."""
    if world.stamp_trigger is None and world.trigger_sight is None:
        return f"attack {name!r} needs a trigger it can stamp into frames or switch on per episode, and {world.name}'s is neither"
    return None


def needs_frame_trigger(name: str, world) -> str | None:
    """Attacks that choose single frames by what the agent thinks of them: only an observation-edit trigger."""
    if world.stamp_trigger is None:
        return (
            f"attack {name!r} chooses single frames by the critic's value and stamps the trigger into them, but {world.name}'s trigger "
            "is part of the layout, present from an episode's first frame: no frame can be chosen by its value before the trigger is in it"
        )
    return None


def needs_feed_forward(name: str, arch: str) -> str | None:
    """Value-guided attacks ask the learner's critic about every frame: one forward pass of a feed-forward model."""
    if arch.startswith("cnn-gru"):
        return f"attack {name!r} reads the critic's value of each frame, which needs a feed-forward model.arch, not the recurrent {arch!r}"
    return None


def value_guided_refusal(name: str, frames_only: bool = False):
    """The ``unsupported`` rule of an attack that reads the critic: a trigger it can put in (a frame
    trigger where it picks frames by value: ``frames_only``) and a feed-forward model."""
    first = needs_frame_trigger if frames_only else needs_trigger_switch
    return lambda world, arch, params: first(name, world) or needs_feed_forward(name, arch)
