"""Candidates of the lava-pattern family: sets of lava cells in a 3×3 box, placed in view.

The built-in patterns (cross, the arrowhead in any and in each direction) and the full box come
first (the full box contains every pattern, so an agent that reacts to part of one may react to
it), then the 2×2 squares, lines and L-shapes, then random cell sets of 3 to 6 cells. Neighbours
add or remove one cell. The same list for every model.

The family is small enough to play whole: :func:`every` lists all :data:`FAMILY_SIZE` patterns of
3 to 9 cells in the box (the effect detector's default screen). Why: a trojan trained with near
negatives ignores every pattern one cell off its trigger, so a sample of the family that misses
the trigger sees nothing to refine from (docs/results/detectors.md).
"""

from __future__ import annotations

import itertools
import math

import numpy as np

from rlbackdoors.triggers.pattern import BOX, BUILTIN, PatternTrigger

EPISODES = 16
MAX_STEPS = None
CANDIDATES = 48  # screened candidates when the detector's ``candidates`` is 0

ALL_CELLS = tuple((x, y) for x in range(BOX) for y in range(BOX))
MIN_CELLS = 3  # the smallest candidate (a line, the arrowhead): pattern cells count toward num_lava
FAMILY_SIZE = sum(math.comb(BOX * BOX, k) for k in range(MIN_CELLS, BOX * BOX + 1))  # 466


def unsupported(env_cfg) -> str | None:
    """Why no candidate can be played in ``env_cfg`` (too few lava squares for any pattern), else None."""
    if env_cfg.num_lava < MIN_CELLS:
        return (
            f"its lava-pattern candidates need at least {MIN_CELLS} lava squares and this env has num_lava={env_cfg.num_lava} "
            "(TrojAI's Aug 2023 round, 9x9 with one lava square, poisoned by observation edits, which this search does not cover; "
            "use weights or attribution there)"
        )
    return None


def _spec(cells) -> str | None:
    try:
        return PatternTrigger.from_cells(sorted(set(cells))).spec()
    except ValueError:
        return None


def _structured() -> list[str | None]:
    """The built-in patterns, the full box, 2x2 squares, lines and L-shapes, in screening order."""
    order: list[str | None] = [_spec(ALL_CELLS), "cross", "arrow", *(name for name in BUILTIN if name.startswith("arrow:"))]
    order += [_spec([(x, y), (x + 1, y), (x, y + 1), (x + 1, y + 1)]) for x in range(BOX - 1) for y in range(BOX - 1)]
    order += [_spec([(x, y) for x in range(BOX)]) for y in range(BOX)] + [_spec([(x, y) for y in range(BOX)]) for x in range(BOX)]
    return order + [_spec([(0, 0), (0, 1), (0, 2), (1, 2), (2, 2)]), _spec([(0, 0), (1, 0), (2, 0), (2, 1), (2, 2)])]


def candidates(env_cfg, rng: np.random.Generator, limit: int) -> list[str]:
    order = _structured()
    tries = 0
    while len(order) < 4 * limit and tries < 50 * limit:
        tries += 1
        size = int(rng.integers(3, 7))
        pick = rng.choice(len(ALL_CELLS), size=size, replace=False)
        order.append(_spec([ALL_CELLS[int(i)] for i in pick]))
    return list(dict.fromkeys(s for s in order if s is not None))[:limit]


def every(env_cfg) -> list[str]:
    """Every pattern of :data:`MIN_CELLS` to 9 cells in the box, once, each as placed (a rotation is
    another member): the built-in and structured ones first (as :func:`candidates` orders them),
    then by size and cells."""
    order = [s for s in _structured() if s != "arrow"]  # "arrow" is any turn: each turn is a member
    order += [_spec(cells) for size in range(MIN_CELLS, len(ALL_CELLS) + 1) for cells in itertools.combinations(ALL_CELLS, size)]
    return list(dict.fromkeys(s for s in order if s is not None))


def neighbours(spec: str, env_cfg, rng: np.random.Generator, limit: int) -> list[str]:
    trigger = PatternTrigger.parse(spec)
    cells = set(trigger.pattern.cells)
    out = [_spec(cells - {c}) for c in sorted(cells)] if len(cells) > 1 else []
    out += [_spec(cells | {c}) for c in ALL_CELLS if c not in cells]
    found = [s for s in dict.fromkeys(out) if s is not None and s != spec]
    rng.shuffle(found)
    return found[:limit]
