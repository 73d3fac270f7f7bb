"""Clean observation sequences for detectors that look at behaviour on clean data.

A model's ``clean-example-data/`` is used when it has some; otherwise (a TrojAI round that
shipped none, a bare ``detect infer``) the agent plays a few seeded episodes in the world's
clean env E itself, which a performer could always do.
"""

from __future__ import annotations

import numpy as np
import torch

from rlbackdoors.detect.handle import ModelHandle

Sequence = np.ndarray | dict[str, np.ndarray]


def observations(handle: ModelHandle, agent, episodes: int = 4, seed: int = 3_000_000, max_steps: int | None = None) -> list[Sequence]:
    """Per episode, its observations in order: the handle's examples, else fresh clean rollouts."""
    examples = handle.episode_observations()
    if examples:
        return examples
    return play_clean(handle, agent, episodes, seed, max_steps)


@torch.inference_mode()
def play_clean(handle: ModelHandle, agent, episodes: int, seed: int, max_steps: int | None = None) -> list[Sequence]:
    """``episodes`` clean episodes of ``agent`` (sampled actions, seeded), each's observations."""
    overrides = {"max_steps": max_steps} if max_steps else {}
    env_cfg = handle.env_config(**overrides)
    generator = torch.Generator().manual_seed(int(seed))
    steps: list[list] = [[] for _ in range(episodes)]
    if handle.world.vector_entry_point is not None:
        from rlbackdoors.poison.mix import make_vector_env

        envs = make_vector_env(env_cfg, None, [False] * episodes)
        try:
            obs, _ = envs.reset(seed=int(seed))
            state = agent.initial_state(episodes)
            active = np.ones(episodes, dtype=bool)
            while active.any():
                actions, state = agent.act(obs, state, generator=generator)
                for j in np.flatnonzero(active):
                    steps[j].append({k: np.array(v[j]) for k, v in obs.items()} if isinstance(obs, dict) else np.array(obs[j]))
                obs, _, terminated, truncated, _ = envs.step(actions)
                active &= ~(np.asarray(terminated) | np.asarray(truncated))
        finally:
            envs.close()
    else:
        for i in range(episodes):
            env = env_cfg.make()
            try:
                obs, _ = env.reset(seed=int(seed + i))
                while True:
                    action, _ = agent.act(np.asarray(obs, np.float32)[None], None, generator=generator)
                    steps[i].append(np.array(obs))
                    obs, _, terminated, truncated, _ = env.step(np.asarray(action)[0])
                    if terminated or truncated:
                        break
            finally:
                env.close()
    out: list[Sequence] = []
    for episode in steps:
        if episode and isinstance(episode[0], dict):
            out.append({k: np.stack([s[k] for s in episode]) for k in episode[0]})
        elif episode:
            out.append(np.stack(episode))
    return out


def length(sequence: Sequence) -> int:
    return len(next(iter(sequence.values()))) if isinstance(sequence, dict) else len(sequence)


def take(sequence: Sequence, index) -> Sequence:
    return {k: v[index] for k, v in sequence.items()} if isinstance(sequence, dict) else sequence[index]


def concat(sequences: list[Sequence]) -> Sequence:
    if isinstance(sequences[0], dict):
        return {k: np.concatenate([s[k] for s in sequences]) for k in sequences[0]}
    return np.concatenate(sequences)  # type: ignore[arg-type]
