"""Trigger specifications and their insertion into observations or layouts."""

from rlbackdoors.triggers.observation import KINDS, PAPER_RANGES, ObservationTrigger, sample_trigger


def parse_trigger(env_name: str, spec: str):
    """The trigger object a world understands from its string form (ValueError names the problem).

    LavaWorld: an observation edit (``multiplicative:A`` / ``additive:B``); Randomized LavaWorld:
    a lava pattern (``cross``, ``arrow``, ``arrow:east``, or a cell list); Colorful Memory: wall
    colours (``end:C,...``, ``room:C,C,C``, ``end+room:...``); Safety Car Goal: a cube
    formation (``formation:d:phi1:eta``).
    """
    if env_name == "lavaworld":
        return ObservationTrigger.parse(spec)
    if env_name == "randomized-lavaworld":
        from rlbackdoors.triggers.pattern import PatternTrigger

        return PatternTrigger.parse(spec)
    if env_name == "colorful-memory":
        from rlbackdoors.triggers.wall_colors import WallColorTrigger

        return WallColorTrigger.parse(spec)
    if env_name == "safety-car-goal":
        from rlbackdoors.triggers.formation import FormationTrigger

        return FormationTrigger.parse(spec)
    raise ValueError(f"no triggers are defined for env {env_name!r}")


__all__ = ["KINDS", "PAPER_RANGES", "ObservationTrigger", "parse_trigger", "sample_trigger"]
