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


def needs_frame_trigger(name: str, world) -> str | None:
    """Step attacks stamp the trigger into one frame: only worlds whose trigger is an observation edit."""
    if world.stamp_trigger is None:
        return (
            f"attack {name!r} stamps the trigger into single frames, but {world.name}'s trigger is part of the world "
            "(a layout, not an observation edit): it needs episode-level poisoning, which is not built yet"
        )
    return None


def needs_feed_forward(name: str, arch: str) -> str | None:
    """Value-guided attacks ask the learner's critic about every frame: one forward pass of a feed-forward model."""
    if arch.startswith("cnn-gru"):
        return f"attack {name!r} reads the critic's value of each frame, which needs a feed-forward model.arch, not the recurrent {arch!r}"
    return None


def value_guided_refusal(name: str):
    """The ``unsupported`` rule of a step attack that reads the critic: a frame trigger and a feed-forward model."""
    return lambda world, arch, params: needs_frame_trigger(name, world) or needs_feed_forward(name, arch)
