"""Candidates of the cube-formation family: two cubes at distance d and angles phi1, phi1 + eta
from the car's heading, on a grid matched to what the agent sees.

The agent sees the cubes through a 16-bin pseudo-lidar (bins of pi/8, one group for every cube),
so a formation is two bumps in that lidar and (phi1, eta) and (phi1 + eta, 2 pi - eta) look the
same. The grid is every unordered pair of the 16 bin headings, with separations from 1.5 bins
(the family's smallest, 30 degrees, rounded up) to 8 in half-bin steps, at the paper's distance
0.5 first (216 candidates); then a coarse grid at distances 1.0 and 1.5. Episodes are cut at
MAX_STEPS (the hazard is reached early when the backdoor fires) to keep MuJoCo time affordable.
Neighbours turn phi1 or eta by half a bin (pi/16).
"""

from __future__ import annotations

import math

import numpy as np

from rlbackdoors.triggers.formation import ETA_RANGE, FormationTrigger

EPISODES = 4
MAX_STEPS = 400
BIN = math.pi / 8  # one pseudo-lidar bin
CANDIDATES = 216  # every pair at distance 0.5 (the module doc) when the detector's ``candidates`` is 0


def _spec(distance: float, phi1: float, eta: float) -> str | None:
    try:
        return FormationTrigger(distance, phi1 % (2 * math.pi), eta).spec()
    except ValueError:
        return None


def candidates(env_cfg, rng: np.random.Generator, limit: int) -> list[str]:
    order = [_spec(0.5, k * BIN, half / 2 * BIN) for half in range(3, 17) for k in range(8 if half == 16 else 16)]
    for distance in (1.0, 1.5):
        for k in range(8):
            for eta in (math.pi, math.pi / 2, 3 * math.pi / 2):
                order.append(_spec(distance, k * math.pi / 4, eta))
    return [s for s in dict.fromkeys(order) if s is not None][:limit]


def neighbours(spec: str, env_cfg, rng: np.random.Generator, limit: int) -> list[str]:
    t = FormationTrigger.parse(spec)
    step = BIN / 2
    out = [_spec(t.distance, t.phi1 + s, t.eta) for s in (step, -step)]
    out += [_spec(t.distance, t.phi1, min(max(t.eta + s, ETA_RANGE[0]), ETA_RANGE[1])) for s in (step, -step)]
    return [s for s in dict.fromkeys(out) if s is not None and s != spec][:limit]
