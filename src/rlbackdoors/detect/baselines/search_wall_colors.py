"""Candidates of the wall-colour family: colour sequences over the far-end squares ("end") and
the squares above the start room ("room").

The family is large (6^(size+2) end patterns, 216 room patterns) and poisoned models are trained
with close-to-trigger layouts so that only the exact colours fire the backdoor: one square off
fires it in a few per cent of episodes, two or more never (measured on a zoo's end and room
models). There is no slope to climb, so the room patterns are enumerated: the one-colour
patterns of each kind, then every other room pattern in a seeded order with one random end
pattern after every ninth; ``CANDIDATES`` covers every room pattern. An end pattern is found
only by chance. Neighbours recolour one square. The same list for every model.
"""

from __future__ import annotations

import itertools

import numpy as np

from rlbackdoors.triggers.wall_colors import COLORS, NUM_COLORS, ROOM_SQUARES, WallColorTrigger

EPISODES = 16
MAX_STEPS = None
ROOM_PATTERNS = NUM_COLORS**ROOM_SQUARES
CANDIDATES = ROOM_PATTERNS + ROOM_PATTERNS // 9 + 2 * NUM_COLORS  # every room pattern, and the end patterns between them


def _squares(kind: str, size: int) -> int:
    return size + 2 if kind == "end" else ROOM_SQUARES


def _spec(kind: str, colors) -> str:
    return f"{kind}:{','.join(COLORS[int(c)] for c in colors)}"


def candidates(env_cfg, rng: np.random.Generator, limit: int) -> list[str]:
    size = int(env_cfg.size)
    order = [_spec(kind, [c] * _squares(kind, size)) for c in range(NUM_COLORS) for kind in ("room", "end")]
    rooms = [_spec("room", colors) for colors in itertools.product(range(NUM_COLORS), repeat=ROOM_SQUARES) if len(set(colors)) > 1]
    for i, k in enumerate(rng.permutation(len(rooms))):
        order.append(rooms[int(k)])
        if i % 9 == 8:
            order.append(_spec("end", rng.integers(NUM_COLORS, size=_squares("end", size))))
    while len(order) < limit + 2 * NUM_COLORS:  # random end patterns past the room list; a repeat of 6^(size+2) is rare
        order.append(_spec("end", rng.integers(NUM_COLORS, size=_squares("end", size))))
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
