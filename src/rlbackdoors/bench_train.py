"""End-to-end PPO throughput (collect + update) on each engine, measured in the same process."""

from __future__ import annotations

import time

import torch

from rlbackdoors.algos.ppo import PPO
from rlbackdoors.config import EnvConfig, PoisonConfig, PPOConfig
from rlbackdoors.models import build_model
from rlbackdoors.poison.mix import make_env_mix


def ppo_frames_per_s(arch: str, engine: str, seconds: float = 5.0, seed: int = 0) -> float:
    """Frames/s of the paper's setup (10 envs, 8:2 mix, rollout 128) with ``arch`` on ``engine``."""
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    envs = make_env_mix(EnvConfig(engine=engine), PoisonConfig())
    ppo = PPO(build_model(arch), PPOConfig(), torch.device("cpu"), torch.Generator().manual_seed(seed))
    obs, _ = envs.reset(seed=seed)
    rollout, obs = ppo.collect(envs, obs)  # warm-up: numba cache load, torch first-call costs
    ppo.update(rollout)
    frames, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        rollout, obs = ppo.collect(envs, obs)
        ppo.update(rollout)
        frames += rollout.num_frames
    return frames / (time.perf_counter() - start)


def bench_train(seconds: float = 5.0) -> dict:
    """FC and CNN, batched engine vs MiniGrid reference; the ratio per arch is the headline."""
    result = {}
    for arch in ("fc", "cnn"):
        batched = ppo_frames_per_s(arch, "batched", seconds)
        minigrid = ppo_frames_per_s(arch, "minigrid", seconds)
        result[arch] = {"batched_fps": batched, "minigrid_fps": minigrid, "ratio": batched / minigrid}
    return result
