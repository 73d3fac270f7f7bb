"""The poisoned reward R-bar (paper eq. 3); defined beside the envs that pay it."""

from rlbackdoors.envs.rewards import poisoned_reward, success_reward

__all__ = ["poisoned_reward", "success_reward"]
