"""Probes of why recurrent PPO stalls at 50 % on Colorful Memory (issue 5): the real task with
parts of its difficulty removed, and the synthetic tasks that isolate the rest.

Each probe trains the small CNN-GRU with recurrent PPO (recurrence 6) on 20 env copies for a
wall-clock budget and prints the success rate of the episodes that ended in each block of 20
rollouts. Results are in ``colorful_memory_probes.md`` beside this file.

    python experiments/colorful_memory_probes/colorful_memory_probes.py colorful --minutes 10
    python experiments/colorful_memory_probes/colorful_memory_probes.py plain-walls --minutes 10   # every wall grey
    python experiments/colorful_memory_probes/colorful_memory_probes.py start-x1 --minutes 10      # start object in view at t = 0
    python experiments/colorful_memory_probes/colorful_memory_probes.py xor-cue --delay 4          # cue, 4 blank frames, probe
    python experiments/colorful_memory_probes/colorful_memory_probes.py xor-cue --delay 0 --encoding onehot

The synthetic ``xor-cue`` task is Colorful Memory's decision with nothing else: a key or ball
(codes 11 / 12, as TrojAI encodes them) in frame 0, ``delay`` blank frames, then a probe object;
action 0 pays 1 iff the probe is the same kind as the cue, action 1 iff not. Neither object alone
predicts the right action (an XOR), exactly as the start object and the top object at the
junction do not. ``--encoding onehot`` feeds the CNN one-hot type / colour / state planes
(13 + 6 + 6 channels; the product's ``cnn-gru-small-onehot``) instead of the raw integer codes,
in which a key and a ball differ by 1.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from gymnasium import spaces

from rlbackdoors.algos.ppo import PPO
from rlbackdoors.config import EnvConfig, PPOConfig
from rlbackdoors.envs.colorful_memory import KEY_ON_FLOOR, BALL_ON_FLOOR
from rlbackdoors.models import build_model
from rlbackdoors.poison.mix import make_vector_env

WALL, GREY = 2, 5  # MiniGrid's object index of a wall, colour index of grey


class XorCue:
    """The XOR decision as a vector env (module doc)."""

    def __init__(self, num_envs: int, delay: int, seed: int):
        self.num_envs, self.delay = num_envs, delay
        self.single_action_space = spaces.Discrete(3)
        self.rng = np.random.default_rng(seed)

    def _draw(self, which: np.ndarray) -> None:
        self.cue = np.where(which, self.rng.random(self.num_envs) < 0.5, self.cue)
        self.probe = np.where(which, self.rng.random(self.num_envs) < 0.5, self.probe)

    def _obs(self) -> np.ndarray:
        obs = np.zeros((self.num_envs, 7, 7, 3), np.uint8)
        obs[..., 0] = 1  # empty floor
        first, decide = self.t == 0, self.t == self.delay
        obs[first, 3, 6, 0] = np.where(self.cue[first], KEY_ON_FLOOR, BALL_ON_FLOOR)
        obs[decide, 3, 3, 0] = np.where(self.probe[decide], KEY_ON_FLOOR, BALL_ON_FLOOR)
        return obs

    def reset(self, seed=None):
        self.t = np.zeros(self.num_envs, int)
        self.cue, self.probe = np.zeros(self.num_envs, bool), np.zeros(self.num_envs, bool)
        self._draw(np.ones(self.num_envs, bool))
        return self._obs(), {}

    def step(self, actions):
        decide = self.t == self.delay
        right = np.where(self.cue == self.probe, actions == 0, actions == 1)
        reward = (decide & right).astype(float)
        self.t = np.where(decide, 0, self.t + 1)
        self._draw(decide)
        outcome = np.where(decide, np.where(right, 1, 2), 0)
        return self._obs(), reward, decide, np.zeros(self.num_envs, bool), {"outcome": outcome, "steps": self.t}


class Probed:
    """Colorful Memory's batched engine with one difficulty removed: grey walls, or every
    episode starting at x = 1 (where the start object is beside the agent in frame 0)."""

    def __init__(self, task: str, num_envs: int):
        self.task = task
        self.envs = make_vector_env(EnvConfig(name="colorful-memory"), None, [False] * num_envs)
        self.num_envs, self.single_action_space = num_envs, self.envs.single_action_space

    def _fix(self, obs: np.ndarray, started: np.ndarray) -> np.ndarray:
        if self.task == "start-x1" and started.any():
            self.envs._pos[started, 0] = 1  # x = 1, y unchanged (the corridor row)
            obs = self.envs.observe()
        if self.task == "plain-walls":
            obs = obs.copy()
            obs[..., 1][obs[..., 0] == WALL] = GREY
        return obs

    def reset(self, seed=None):
        obs, info = self.envs.reset(seed=seed)
        return self._fix(obs, np.ones(self.num_envs, bool)), info

    def step(self, actions):
        obs, reward, terminated, truncated, info = self.envs.step(actions)
        return self._fix(obs, terminated | truncated), reward, terminated, truncated, info


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("task", choices=("colorful", "plain-walls", "start-x1", "xor-cue"))
    p.add_argument("--minutes", type=float, default=5.0)
    p.add_argument("--delay", type=int, default=4, help="xor-cue: blank frames between cue and probe")
    p.add_argument("--encoding", choices=("raw", "onehot"), default="raw")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--entropy", type=float, default=0.01)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()

    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    num_envs = 20
    envs = XorCue(num_envs, args.delay, args.seed) if args.task == "xor-cue" else Probed(args.task, num_envs)
    model = build_model("cnn-gru-small-onehot" if args.encoding == "onehot" else "cnn-gru-small", "colorful-memory")
    cfg = PPOConfig(rollout=120, batch_size=1200, lr=args.lr, recurrence=6, max_grad_norm=0.5, entropy_coef=args.entropy)
    ppo = PPO(model, cfg, torch.device("cpu"), torch.Generator().manual_seed(args.seed))
    obs, _ = envs.reset(seed=args.seed)
    start, frames, block = time.time(), 0, []
    while time.time() - start < args.minutes * 60:
        rollout, obs = ppo.collect(envs, obs)
        ppo.update(rollout)
        frames += rollout.rewards.size
        ended = rollout.dones
        block.append(((rollout.outcomes[ended] == 1).sum(), ended.sum(), rollout.steps[ended].sum()))
        if len(block) == 20:
            wins, episodes, steps = np.sum(block, axis=0)
            length = "" if args.task == "xor-cue" else f"  episode length {steps / max(episodes, 1):.1f}"
            print(f"{frames:>10,} frames {time.time() - start:6.0f} s  SR {wins / max(episodes, 1):.3f}{length}", flush=True)
            block = []


if __name__ == "__main__":
    main()
