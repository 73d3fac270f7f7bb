"""Candidates of the wall-colour family: colour sequences over the far-end squares ("end") and
the squares above the start room ("room").

The family is large (6^(size+2) end patterns, 216 room patterns) and poisoned models are trained
with close-to-trigger layouts so that only the exact colours fire the backdoor: a budgeted
search can enumerate a share of the room patterns but finds an end pattern only by chance. The
order: the one-colour patterns of each kind, then random patterns alternating the kinds.
Neighbours recolour one square. The same list for every model.
"""

from __future__ import annotations

import numpy as np

from rlbackdoors.triggers.wall_colors import COLORS, NUM_COLORS, ROOM_SQUARES, WallColorTrigger

EPISODES = 16
MAX_STEPS = None


def _squares(kind: str, size: int) -> int:
    return size + 2 if kind == "end" else ROOM_SQUARES


def _spec(kind: str, colors) -> str:
    return f"{kind}:{','.join(COLORS[int(c)] for c in colors)}"


def candidates(env_cfg, rng: np.random.Generator, limit: int) -> list[str]:
    size = int(env_cfg.size)
    order = [_spec(kind, [c] * _squares(kind, size)) for c in range(NUM_COLORS) for kind in ("room", "end")]
    kinds = ("room", "end")
    i = 0
    while len(order) < limit + 2 * NUM_COLORS and i < 50 * limit:
        kind = kinds[i % 2]
        order.append(_spec(kind, rng.integers(NUM_COLORS, size=_squares(kind, size))))
        i += 1
    return list(dict.fromkeys(WallColorTrigger.parse(s).spec() for s in order))[:limit]


def neighbours(spec: str, env_cfg, rng: np.random.Generator, limit: int) -> list[str]:
    trigger = WallColorTrigger.parse(spec)
    colors = list(trigger.colors)
    out = []
    for square in rng.permutation(len(colors)):
        for c in range(NUM_COLORS):
            if c != colors[int(square)]:
                out.append(trigger.with_colors([c if j == int(square) else v for j, v in enumerate(colors)]).spec())
    return out[:limit]
