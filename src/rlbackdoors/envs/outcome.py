"""How an episode ended: the one fact both the clean and the trojan task are scored on."""

from enum import IntEnum


class Outcome(IntEnum):
    """Stored in ``info["outcome"]`` at every step (``NONE`` while the episode runs).

    Integers rather than strings so that vector envs can batch them into one array.
    """

    NONE = 0
    GOAL = 1
    LAVA = 2
    TIMEOUT = 3
    PATTERN_LAVA = 4  # entered a lava cell of an inserted trigger pattern
