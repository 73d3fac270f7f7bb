"""Clean and triggered evaluation: success rates and mean returns over a fixed set of layouts.

Every evaluation of every model uses the same env seeds (``eval_seed + i``), so numbers
are comparable across checkpoints and across a zoo. Each vector slot plays exactly one
episode: no bias toward short episodes, as "first N episodes to finish" would have.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from rlbackdoors.algos.ppo import sample_actions
from rlbackdoors.config import EnvConfig
from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.models import ActorCritic
from rlbackdoors.poison.mix import make_vector_env

# Which terminal counts as success: the clean task in E, the trojan task in E-bar.
CLEAN_SUCCESS = {"lavaworld": Outcome.GOAL}
TROJAN_SUCCESS = {"lavaworld": Outcome.LAVA}


@dataclass
class EvalResult:
    clean_sr: float
    poisoned_sr: float
    clean_reward: float
    poisoned_reward: float
    episodes: int

    def to_dict(self) -> dict:
        return asdict(self)


@torch.inference_mode()
def play_episodes(model: ActorCritic, envs, seed: int, policy: str = "sample", device="cpu") -> tuple[np.ndarray, np.ndarray]:
    """One episode per vector slot; returns (episode returns, outcomes)."""
    generator = torch.Generator(device=device).manual_seed(int(seed))
    n = envs.num_envs
    obs, _ = envs.reset(seed=int(seed))
    active = np.ones(n, dtype=bool)
    returns = np.zeros(n)
    outcomes = np.zeros(n, dtype=np.int64)
    while active.any():
        logits, _ = model(torch.from_numpy(obs).to(device))
        actions = logits.argmax(-1) if policy == "greedy" else sample_actions(logits, generator)
        obs, reward, terminated, truncated, info = envs.step(actions.cpu().numpy())
        returns[active] += reward[active]
        finished = active & (terminated | truncated)
        outcomes[finished] = info["outcome"][finished]
        active &= ~finished
    return returns, outcomes


def evaluate(
    model: ActorCritic,
    env: EnvConfig,
    trigger: str | None,
    episodes: int = 100,
    seed: int = 1_000_000,
    policy: str = "sample",
    device="cpu",
) -> EvalResult:
    """Clean SR/reward in E and trojan SR / R-bar reward in E-bar (trigger on), same layouts.

    With ``trigger=None`` only the clean half is measured (poisoned numbers are NaN).
    """
    was_training = model.training
    model.eval()
    clean_envs = make_vector_env(env, trigger, [False] * episodes)
    clean_returns, clean_outcomes = play_episodes(model, clean_envs, seed, policy, device)
    clean_envs.close()
    poisoned_sr = poisoned_reward = float("nan")
    if trigger is not None:
        poisoned_envs = make_vector_env(env, trigger, [True] * episodes)
        poisoned_returns, poisoned_outcomes = play_episodes(model, poisoned_envs, seed, policy, device)
        poisoned_envs.close()
        poisoned_sr = float(np.mean(poisoned_outcomes == TROJAN_SUCCESS[env.name]))
        poisoned_reward = float(poisoned_returns.mean())
    model.train(was_training)
    return EvalResult(
        clean_sr=float(np.mean(clean_outcomes == CLEAN_SUCCESS[env.name])),
        poisoned_sr=poisoned_sr,
        clean_reward=float(clean_returns.mean()),
        poisoned_reward=poisoned_reward,
        episodes=episodes,
    )
