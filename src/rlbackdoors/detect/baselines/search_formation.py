"""Candidates of the cube-formation family: two cubes at distance d and angles phi1, phi1 + eta
from the car's heading, on a grid.

The paper's distance 0.5 first, with phi1 on 8 headings and eta in {pi/2, pi, 3pi/2}, then the
same at distance 1.0 and 1.5. Episodes are cut at MAX_STEPS (the hazard is reached early when
the backdoor fires) to keep MuJoCo time affordable. Neighbours turn phi1 or eta by pi/8.
"""

from __future__ import annotations

import math

import numpy as np

from rlbackdoors.triggers.formation import ETA_RANGE, FormationTrigger

EPISODES = 4
MAX_STEPS = 400
CANDIDATES = 48  # screened candidates when the detector's ``candidates`` is 0


def _spec(distance: float, phi1: float, eta: float) -> str | None:
    try:
        return FormationTrigger(distance, phi1 % (2 * math.pi), eta).spec()
    except ValueError:
        return None


def candidates(env_cfg, rng: np.random.Generator, limit: int) -> list[str]:
    order = []
    for distance in (0.5, 1.0, 1.5):
        for k in range(8):
            for eta in (math.pi, math.pi / 2, 3 * math.pi / 2):
                order.append(_spec(distance, k * math.pi / 4, eta))
    return [s for s in dict.fromkeys(order) if s is not None][:limit]


def neighbours(spec: str, env_cfg, rng: np.random.Generator, limit: int) -> list[str]:
    t = FormationTrigger.parse(spec)
    step = math.pi / 8
    out = [_spec(t.distance, t.phi1 + s, t.eta) for s in (step, -step)]
    out += [_spec(t.distance, t.phi1, min(max(t.eta + s, ETA_RANGE[0]), ETA_RANGE[1])) for s in (step, -step)]
    return [s for s in dict.fromkeys(out) if s is not None and s != spec][:limit]
