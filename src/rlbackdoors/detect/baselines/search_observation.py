"""Candidates of the observation-transform family ``o' = (a·o + b) mod 256``.

Ordered so that a small budget covers the family coarsely first: every multiplicative ``a`` and
every tenth additive ``b`` of the paper's ranges (a in 10..24, b in 20..200), interleaved; then
the rest of the family's values (a in 2..255, b in 1..255) on a widening grid. Neighbours of a
candidate are the values next to it, for the refinement stage. Nothing here knows a model's
trigger: the list is the same for every model.
"""

from __future__ import annotations

import numpy as np

from rlbackdoors.triggers.observation import PAPER_RANGES, ObservationTrigger

EPISODES = 16  # episodes per candidate in the screening stage
MAX_STEPS = None  # the world's own episode length
CANDIDATES = 48  # screened candidates when the detector's ``candidates`` is 0


def _valid(kind: str, value: int) -> str | None:
    try:
        return ObservationTrigger(kind, int(value)).spec()
    except ValueError:
        return None


def candidates(env_cfg, rng: np.random.Generator, limit: int) -> list[str]:
    (a_lo, a_hi), (b_lo, b_hi) = PAPER_RANGES["multiplicative"], PAPER_RANGES["additive"]
    first_mult = [f"multiplicative:{a}" for a in range(a_lo, a_hi + 1)]
    first_add = [f"additive:{b}" for b in range(b_lo, b_hi + 1, 10)]
    order: list[str] = []
    for i in range(max(len(first_mult), len(first_add))):
        order += first_mult[i : i + 1] + first_add[i : i + 1]
    rest = [f"multiplicative:{a}" for a in (*range(2, a_lo), *range(a_hi + 1, 64, 2), *range(64, 256, 16))]
    rest += [f"additive:{b}" for b in (*range(1, b_lo, 4), *range(b_hi + 5, 256, 10), *range(b_lo + 5, b_hi, 10))]
    order += rest
    seen: dict[str, None] = {}
    for spec in order:
        valid = _valid(*spec.split(":"))  # type: ignore[arg-type]  # "kind:value" always splits in two
        if valid is not None:
            seen.setdefault(valid)
    return list(seen)[:limit]


def neighbours(spec: str, env_cfg, rng: np.random.Generator, limit: int) -> list[str]:
    trigger = ObservationTrigger.parse(spec)
    steps = (1, -1, 2, -2) if trigger.kind == "multiplicative" else (1, -1, 2, -2, 3, -3, 5, -5)
    out = [_valid(trigger.kind, trigger.value + s) for s in steps]
    return [s for s in out if s is not None][:limit]
