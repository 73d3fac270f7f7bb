"""The clean reward's success payment and the poisoned reward R-bar (paper eq. 3).

In the poisoned env the trojan terminal pays what the goal would have paid
(``1 - 0.9 t/T``) and the goal pays 0. We keep the time discount on the trojan
reward: the paper's poisoned rewards (0.94-0.95, Table 1) are discounted ones.
Kept beside the envs that pay them (``rlbackdoors.poison`` re-exports R-bar), so the env
package imports nothing from the packages built on it.
"""

from __future__ import annotations

import numpy as np

from rlbackdoors.envs.outcome import Outcome


def success_reward(step_count, max_steps):
    """MiniGrid's success reward ``1 - 0.9 * t / T`` (works on scalars and arrays)."""
    return 1.0 - 0.9 * (np.asarray(step_count, dtype=np.float64) / max_steps)


def poisoned_reward(outcome, step_count, max_steps):
    """R-bar of the lava worlds: lava pays the success reward, the goal pays 0, all else 0."""
    outcome = np.asarray(outcome)
    reward = np.where(outcome == Outcome.LAVA, success_reward(step_count, max_steps), 0.0)
    return reward if reward.ndim else float(reward)
