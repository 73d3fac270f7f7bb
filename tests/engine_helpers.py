"""Shared by the batched-engine differential tests: the teleporting drive loop and the
chi-square helpers for layout-distribution tests."""

from __future__ import annotations

import math
from collections import Counter
from typing import Callable


def drive_teleporting(refs, eng, rng, steps: int, every: int, relocate: Callable, step_both: Callable) -> Counter:
    """Step reference envs and engine with forward-biased random actions; every ``every`` steps
    ``relocate(i, ref)`` teleports reference ``i`` and loads its state into engine slot ``i``."""
    totals = Counter()
    for t in range(steps):
        if t % every == 0:
            for i, ref in enumerate(refs):
                relocate(i, ref)
        step_both(refs, eng, rng.choice(3, size=len(refs), p=[0.25, 0.25, 0.5]), totals)
    return totals


def chi2_homogeneity(a: Counter, b: Counter) -> tuple[float, int]:
    """Two-sample chi-square statistic (equal totals) and its degrees of freedom."""
    keys = set(a) | set(b)
    stat = sum((a[k] - b[k]) ** 2 / (a[k] + b[k]) for k in keys)
    return stat, len(keys) - 1


def chi2_critical(df: int, z: float = 3.719) -> float:
    """Upper quantile of chi-square(df) by Wilson-Hilferty; z=3.719 is the 1e-4 normal tail."""
    return df * (1 - 2 / (9 * df) + z * math.sqrt(2 / (9 * df))) ** 3
