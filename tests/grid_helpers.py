"""Helpers shared by the grid-world tests: the engines' teleporting drive loop, chi-square
helpers for layout-distribution tests, and a scripted walk to the goal."""

from __future__ import annotations

import math
from collections import Counter, deque
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


def walk_to_goal(env, right: int = 1, forward: int = 2):
    """Follow a BFS path (around lava and walls) to the goal at (W-2, H-2) with right/forward
    actions on a MiniGrid-based env; return the last step's result."""
    start = tuple(int(v) for v in env.agent_pos)
    prev, todo = {start: None}, deque([start])
    while todo:
        cell = todo.popleft()
        for dx, dy in ((1, 0), (0, 1), (-1, 0), (0, -1)):
            nxt = (cell[0] + dx, cell[1] + dy)
            c = env.grid.get(*nxt)
            if nxt not in prev and (c is None or c.type == "goal"):
                prev[nxt] = cell
                todo.append(nxt)
    path, cell = [], (env.width - 2, env.height - 2)
    while cell != start:
        path.append(cell)
        cell = prev[cell]
    vec_to_dir = {(1, 0): 0, (0, 1): 1, (-1, 0): 2, (0, -1): 3}
    result = None
    for target in reversed(path):
        want = vec_to_dir[(target[0] - env.agent_pos[0], target[1] - env.agent_pos[1])]
        while env.agent_dir != want:
            result = env.step(right)
        result = env.step(forward)
    return result
