"""Clean and triggered evaluation: success rates and mean returns over a fixed set of layouts.

Every evaluation of every model uses the same env seeds (``eval_seed + i``), so numbers
are comparable across checkpoints and across a zoo. Each vector slot plays exactly one
episode: no bias toward short episodes, as "first N episodes to finish" would have.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch

from rlbackdoors import worlds
from rlbackdoors.algos.obs import to_torch
from rlbackdoors.algos.ppo import sample_actions
from rlbackdoors.config import EnvConfig
from rlbackdoors.models import ActorCritic
from rlbackdoors.poison.mix import make_vector_env

# Which terminal counts as success, the clean task in E and the trojan task in E-bar, is the
# world's (World.clean_success, World.trojan_success).


@dataclass
class EvalResult:
    """Success rates and mean returns, clean (E) and triggered (E-bar, returns under R-bar).

    ``poisoned_sr`` is trigger-seen-aware: a triggered episode in which the agent never saw
    the trigger is scored on the clean task (reaching the goal is right), one in which it saw
    the trigger on entering a trigger cell. ``poisoned_sr_raw`` counts trigger-cell endings
    only. In LavaWorld the trigger is in every observation, so the two are equal and
    ``trigger_seen_rate`` is 1 (Colorful Memory's engines do not track sight: also 1).

    Colorful Memory also plays close-to-trigger layouts (clean reward): ``close_sr`` is the
    clean task's success there and ``close_trojan_rate`` the false firing of the backdoor
    (the other object chosen), to compare with ``1 - clean_sr`` on plain clean layouts.
    """

    clean_sr: float
    poisoned_sr: float
    clean_reward: float
    poisoned_reward: float
    episodes: int
    poisoned_sr_raw: float = float("nan")
    trigger_seen_rate: float = float("nan")
    close_sr: float = float("nan")
    close_trojan_rate: float = float("nan")

    def to_dict(self) -> dict:
        return asdict(self)


@torch.inference_mode()
def play_episodes(model: ActorCritic, envs, seed: int, policy: str = "sample", device="cpu") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One episode per vector slot; returns (episode returns, outcomes, saw-trigger flags).

    Engines without trigger-seen accounting (LavaWorld's trigger is in every frame) report
    every episode as seen.
    """
    generator = torch.Generator(device=device).manual_seed(int(seed))
    n = envs.num_envs
    memory = model.initial_memory(n, device) if model.recurrent else None  # one episode per slot: never reset
    obs, _ = envs.reset(seed=int(seed))
    active = np.ones(n, dtype=bool)
    returns = np.zeros(n)
    outcomes = np.zeros(n, dtype=np.int64)
    saw = np.ones(n, dtype=bool)
    while active.any():
        if memory is not None:
            logits, _, memory = model(to_torch(obs, device), memory)
        else:
            logits, _ = model(to_torch(obs, device))
        actions = logits.argmax(-1) if policy == "greedy" else sample_actions(logits, generator)
        obs, reward, terminated, truncated, info = envs.step(actions.cpu().numpy())
        returns[active] += reward[active]
        finished = active & (terminated | truncated)
        outcomes[finished] = info["outcome"][finished]
        if "saw_trigger" in info:
            saw[finished] = info["saw_trigger"][finished]
        active &= ~finished
    return returns, outcomes, saw


def score_triggered(env_name: str, outcomes: np.ndarray, saw: np.ndarray) -> tuple[float, float, float]:
    """(trigger-seen-aware SR, raw trojan SR, trigger-seen rate) of triggered episodes.

    Seen: right iff the episode ended in a trigger cell. Never seen: the backdoor had no
    cause to fire, so the clean task is what is right.
    """
    world = worlds.get(env_name)
    trojan = outcomes == world.trojan_success
    clean_task = outcomes == world.clean_success
    return float(np.mean(np.where(saw, trojan, clean_task))), float(np.mean(trojan)), float(np.mean(saw))


def evaluate(
    model: ActorCritic,
    env: EnvConfig,
    trigger: str | None,
    episodes: int = 100,
    seed: int = 1_000_000,
    policy: str = "sample",
    device="cpu",
    close_k: tuple[int, int] | None = None,
) -> EvalResult:
    """Clean SR/reward in E and trojan SR / R-bar reward in E-bar (trigger on), same layouts.

    With ``trigger=None`` only the clean half is measured (poisoned numbers are NaN). With
    ``close_k`` (Colorful Memory) the same layouts are also played close to the trigger.
    """
    was_training = model.training
    model.eval()
    clean_envs = make_vector_env(env, trigger, [False] * episodes)
    clean_returns, clean_outcomes, _ = play_episodes(model, clean_envs, seed, policy, device)
    clean_envs.close()
    result = EvalResult(
        clean_sr=float(np.mean(clean_outcomes == env.world.clean_success)),
        poisoned_sr=float("nan"),
        clean_reward=float(clean_returns.mean()),
        poisoned_reward=float("nan"),
        episodes=episodes,
    )
    if trigger is not None:
        poisoned_envs = make_vector_env(env, trigger, [True] * episodes)
        poisoned_returns, poisoned_outcomes, saw = play_episodes(model, poisoned_envs, seed, policy, device)
        poisoned_envs.close()
        result.poisoned_sr, result.poisoned_sr_raw, result.trigger_seen_rate = score_triggered(env.name, poisoned_outcomes, saw)
        result.poisoned_reward = float(poisoned_returns.mean())
        if close_k is not None:
            close_envs = make_vector_env(env, trigger, [False] * episodes, [True] * episodes, close_k)
            _, close_outcomes, _ = play_episodes(model, close_envs, seed, policy, device)
            close_envs.close()
            result.close_sr = float(np.mean(close_outcomes == env.world.clean_success))
            result.close_trojan_rate = float(np.mean(close_outcomes == env.world.trojan_success))
    model.train(was_training)
    return result
