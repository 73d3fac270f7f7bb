"""Truncated BPTT's sequence starts, one rule for the torch trainer (``PPO.sequence_starts``) and
the compiled one (``compiled._iteration``), so the two cannot drift apart."""

from __future__ import annotations

import numpy as np


def sequence_starts(steps: int, num_envs: int, recurrence: int, shifted: bool) -> np.ndarray:
    """Flat rollout rows (``t * num_envs + b``, int64) where sequences of ``recurrence`` steps
    start: every ``recurrence``-th step of every env copy; on ``shifted`` epochs (torch-ac
    alternates) half a sequence later, the last block dropped so that no sequence leaves the rollout."""
    times = np.arange(0, steps, recurrence, dtype=np.int64)
    if shifted and recurrence > 1:
        times = times[times + recurrence < steps] + recurrence // 2
    return (times[:, None] * num_envs + np.arange(num_envs, dtype=np.int64)[None, :]).reshape(-1)


__all__ = ["sequence_starts"]
