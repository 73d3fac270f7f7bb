"""Training algorithms: PPO (incl. recurrent, later) and OPAC² (later)."""

from rlbackdoors.algos.ppo import PPO, Rollout, sample_actions

__all__ = ["PPO", "Rollout", "sample_actions"]
