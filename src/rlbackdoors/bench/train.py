"""Training benchmarks: end-to-end PPO frames/s on each engine, and wall-clock to a converged agent."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import torch

from rlbackdoors.algos.ppo import PPO
from rlbackdoors.bench.machine import machine_info
from rlbackdoors.config import EnvConfig, PoisonConfig, PPOConfig, RunConfig
from rlbackdoors.models import build_model
from rlbackdoors.poison.mix import make_env_mix


def ppo_frames_per_s(arch: str, engine: str, seconds: float = 5.0, seed: int = 0) -> dict:
    """Frames/s of the paper's setup (10 envs, 8:2 mix, rollout 128) with ``arch`` on ``engine``.

    Also splits the time into collection (env + policy) and update (4 epochs of SGD), which
    is what tells whether the env or the learner holds a run back.
    """
    torch.set_num_threads(1)
    torch.manual_seed(seed)
    envs = make_env_mix(EnvConfig(engine=engine), PoisonConfig())
    ppo = PPO(build_model(arch), PPOConfig(), torch.device("cpu"), torch.Generator().manual_seed(seed))
    obs, _ = envs.reset(seed=seed)
    rollout, obs = ppo.collect(envs, obs)  # warm-up: numba cache load, torch first-call costs
    ppo.update(rollout)
    frames, collect_s, update_s = 0, 0.0, 0.0
    start = time.perf_counter()
    while time.perf_counter() - start < seconds:
        t0 = time.perf_counter()
        rollout, obs = ppo.collect(envs, obs)
        t1 = time.perf_counter()
        ppo.update(rollout)
        collect_s += t1 - t0
        update_s += time.perf_counter() - t1
        frames += rollout.num_frames
    envs.close()
    total = collect_s + update_s
    return {"fps": frames / total, "collect_share": collect_s / total, "frames": frames, "seconds": total}


def bench_train(seconds: float = 5.0) -> dict:
    """FC and CNN, batched engine vs MiniGrid reference; the ratio per arch is the headline."""
    result: dict = {"machine": machine_info()}
    for arch in ("fc", "cnn"):
        batched = ppo_frames_per_s(arch, "batched", seconds)
        minigrid = ppo_frames_per_s(arch, "minigrid", seconds)
        result[arch] = {
            "batched_fps": batched["fps"],
            "minigrid_fps": minigrid["fps"],
            "ratio": batched["fps"] / minigrid["fps"],
            "batched_collect_share": batched["collect_share"],
            "minigrid_collect_share": minigrid["collect_share"],
        }
    return result


def bench_converge(
    seed: int = 0,
    trigger: str = "multiplicative:12",
    out: str | Path | None = None,
    progress: bool = False,
    max_frames: int = 5_000_000,
) -> dict:
    """Wall-clock to a converged poisoned FC agent of the default world (clean SR >= 0.98, poisoned SR >= 0.95).

    Runs the real ``train`` with the paper's defaults (evaluations every 1e5 frames
    included in the clock, as a user would see it) into ``out`` or a temporary folder.
    """
    from rlbackdoors.train import train

    cfg = RunConfig.from_dict({"poison": {"trigger": trigger}, "model": {"arch": "fc"}, "train": {"seed": seed, "max_frames": max_frames}})
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(out) if out is not None else Path(tmp) / "poisoned-fc"
        start = time.perf_counter()
        metrics = train(cfg, folder, overwrite=True, progress=progress)
        wall = time.perf_counter() - start
    return {
        "machine": machine_info(),
        "seed": seed,
        "trigger": trigger,
        "converged": metrics["converged"],
        "frames": metrics["frames"],
        "wall_clock_s": wall,
        "train_time_s": metrics["wall_time_s"],
        "clean_sr": metrics["clean_sr"],
        "poisoned_sr": metrics["poisoned_sr"],
        "episodes": metrics["episodes"],
        "fps": metrics["frames"] / metrics["wall_time_s"],
    }
