"""Full training runs (minutes each): excluded from `make test`, run with `make test-slow`."""

import numpy as np
import pytest

from rlbackdoors.config import RunConfig
from rlbackdoors.train import train

pytestmark = pytest.mark.slow


def test_poisoned_fc_reaches_paper_thresholds(tmp_path):
    """Paper Table 1: poisoned FC 98% / 98%. Judged on 200 final evaluation episodes."""
    cfg = RunConfig.from_dict({"poison": {"trigger": "multiplicative:12"}, "train": {"seed": 0, "max_frames": 3_000_000}})
    m = train(cfg, tmp_path / "p", progress=False)
    assert m["episodes"] == 200
    assert m["clean_sr"] >= 0.98 and m["poisoned_sr"] >= 0.95


def test_clean_fc_twin_ignores_the_trigger(tmp_path):
    cfg = RunConfig.from_dict({"poison": {"trigger": "multiplicative:12", "poisoned": False}, "train": {"seed": 0, "max_frames": 3_000_000}})
    m = train(cfg, tmp_path / "c", progress=False)
    assert m["clean_sr"] >= 0.95 and m["poisoned_sr"] <= 0.2


def test_randomized_lavaworld_poisoned_cnn_learns_the_cross_backdoor(tmp_path):
    """Issue 4's bar: clean SR >= 0.90 and trigger-seen-aware poisoned SR >= 0.90 (200 episodes).
    Measured: seed 2 converged at 300,800 frames, clean 0.985 / poisoned 0.985."""
    cfg = RunConfig.from_dict({"env": {"name": "randomized-lavaworld"}, "model": {"arch": "cnn"}, "train": {"seed": 2, "max_frames": 1_500_000}})
    m = train(cfg, tmp_path / "p", progress=False)
    assert m["converged"] and m["clean_sr"] >= 0.90 and m["poisoned_sr"] >= 0.90


def test_randomized_lavaworld_clean_fc_solves_the_task_and_ignores_the_cross(tmp_path):
    cfg = RunConfig.from_dict({"env": {"name": "randomized-lavaworld"}, "poison": {"poisoned": False}, "train": {"seed": 0, "max_frames": 1_500_000}})
    m = train(cfg, tmp_path / "c", progress=False)
    assert m["clean_sr"] >= 0.95 and m["poisoned_sr"] <= 0.1


class CueRecall:
    """The smallest memory task, as a vector env: a cue (key or ball) in the first frame only,
    ``delay`` blank frames, then a decision frame where action 0 pays for a key and 1 for a
    ball. Without memory the best is 50 %."""

    def __init__(self, num_envs: int, delay: int, seed: int = 0):
        from gymnasium import spaces

        self.num_envs, self.delay = num_envs, delay
        self.single_action_space = spaces.Discrete(3)
        self.rng = np.random.default_rng(seed)

    def _obs(self):
        obs = np.zeros((self.num_envs, 7, 7, 3), np.uint8)
        obs[..., 0] = 1  # empty floor
        first = self.t == 0
        obs[first, 3, 6, 0] = np.where(self.key[first], 11, 12)  # Colorful Memory's key / ball codes
        obs[self.t == self.delay, 3, 3, 0] = 8  # "decide now"
        return obs

    def reset(self, seed=None):
        self.t = np.zeros(self.num_envs, int)
        self.key = self.rng.random(self.num_envs) < 0.5
        return self._obs(), {}

    def step(self, actions):
        decide = self.t == self.delay
        right = np.where(self.key, actions == 0, actions == 1)
        reward = (decide & right).astype(float)
        self.t = np.where(decide, 0, self.t + 1)
        self.key = np.where(decide, self.rng.random(self.num_envs) < 0.5, self.key)
        outcome = np.where(decide, np.where(right, 1, 2), 0)
        return self._obs(), reward, decide, np.zeros(self.num_envs, bool), {"outcome": outcome, "steps": self.t}


def test_recurrent_ppo_learns_to_recall_a_cue():
    """BPTT through the CNN-GRU carries a cue over 4 blank steps: success goes from 50 % (no
    memory) to >= 95 % of the episodes of a rollout, >= 80 % on average over the last 20
    rollouts (lr 1e-3 oscillates). Measured: 1.0 at best, 0.83 mean over the last 20 (seed 0)."""
    import torch

    from rlbackdoors.algos.ppo import PPO
    from rlbackdoors.config import PPOConfig
    from rlbackdoors.models import build_model

    torch.manual_seed(0)
    envs = CueRecall(20, delay=4)
    cfg = PPOConfig(rollout=120, batch_size=1200, lr=1e-3, recurrence=6, max_grad_norm=0.5)
    ppo = PPO(build_model("cnn-gru-small", "colorful-memory"), cfg, torch.device("cpu"), torch.Generator().manual_seed(0))
    obs, _ = envs.reset()
    rates = []
    for _ in range(120):  # 288k frames
        rollout, obs = ppo.collect(envs, obs)
        ppo.update(rollout)
        rates.append(rollout.rewards[rollout.dones].mean())
    assert rates[0] < 0.7
    assert max(rates[-20:]) >= 0.95 and np.mean(rates[-20:]) >= 0.8
