"""Reward poisoning and the clean / poisoned (/ close-to-trigger) env mix."""

from rlbackdoors.poison.reward import poisoned_reward, success_reward

__all__ = ["poisoned_reward", "success_reward"]
