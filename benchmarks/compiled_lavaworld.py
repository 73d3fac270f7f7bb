"""Training frames/s of the compiled PPO iteration (algos/compiled.py) against today's best CPU
side (a torch group of K agents, algos/group.py: with the JAX update for LavaWorld's FC model,
torch's otherwise), in the same process, one core each, with the env mix (10 copies, the world's
mix, rollout 128; Colorful Memory's: 4 clean, 4 close and 2 poisoned, rollout 120, recurrence 6);
``--env lavaworld`` (default), ``randomized-lavaworld`` (its full world: no curriculum) or
``colorful-memory`` (its CNN-GRUs: ``--arch cnn-gru-small-onehot``), ``--arch fc`` (default) or ``cnn``. ``--device cuda``: the compiled side on the GPU
(JAX's CUDA backend), the torch side skipped unless ``--torch-k`` is given (it is a CPU
reference).

Training only: rollout, GAE and update, no evaluations (a zoo's figures with them: ``rlbackdoors
bench zoo``); each side warms up (three iterations: compiles, and a deeper layout queue's
program where the first was too shallow) and is then timed for ``--seconds``. The machine and
its load are recorded with the figures.

    python benchmarks/compiled_lavaworld.py --ks 1,8,16,32 --json benchmarks/results/compiled_lavaworld_<cpu>.json
    python benchmarks/compiled_lavaworld.py --env randomized-lavaworld --arch cnn --ks 1,8
    python benchmarks/compiled_lavaworld.py --env colorful-memory --arch cnn-gru-small-onehot --torch-k 8 --ks 1,8
    python benchmarks/compiled_lavaworld.py --device cuda --torch-k 0 --ks 256,1024 --seconds 20
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import torch


ARCH, ENV = "fc", "lavaworld"  # --arch, --env


def configs(k: int):
    """K configs of today's best CPU side: the JAX update for LavaWorld's FC model, torch's
    otherwise (the JAX update has no convolutions, nor the direction models' Flatten)."""
    from rlbackdoors.config import RunConfig

    lava = ENV == "lavaworld"
    ppo = {"update_backend": "jax"} if lava and ARCH == "fc" else {}
    extra = {"curriculum": {"enabled": False}} if ENV == "randomized-lavaworld" else {}
    trigger = {"lavaworld": "multiplicative:12", "randomized-lavaworld": "cross", "colorful-memory": "end"}[ENV]
    return [
        RunConfig.from_dict({"env": {"name": ENV}, "model": {"arch": ARCH}, "poison": {"trigger": trigger}, "ppo": ppo, "train": {"seed": s}, **extra})
        for s in range(k)
    ]


def engines_of(cfgs):
    from rlbackdoors.poison.mix import make_env_mix

    out = []
    for cfg in cfgs:
        e = make_env_mix(cfg.env, cfg.poison, cfg.train.seed)
        e.reset(seed=cfg.train.seed * 1000)
        out.append(e)
    return out


def torch_group(k: int, seconds: float) -> dict:
    """Today's side: K torch PPO learners stepped together (group.collect, group.update)."""
    from rlbackdoors.algos import group
    from rlbackdoors.algos.ppo import PPO
    from rlbackdoors.models import build_model

    cfgs = configs(k)
    envs = engines_of(cfgs)
    ppos = []
    for cfg in cfgs:
        torch.manual_seed(cfg.train.seed)
        ppos.append(PPO(build_model(ARCH, ENV), cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(cfg.train.seed)))
    obs = [e.reset(seed=c.train.seed * 1000)[0] for e, c in zip(envs, cfgs)]

    def once():
        nonlocal obs
        collected = group.collect(ppos, envs, obs)
        obs = [o for _, o in collected]
        group.update(ppos, [r for r, _ in collected])
        return sum(r.num_frames for r, _ in collected)

    return timed(once, seconds)


def compiled_group(k: int, seconds: float) -> dict:
    """The compiled side: K learners (algos.compiled.Learner) in one program (algos.compiled.iterate)."""
    import importlib

    from rlbackdoors.algos.compiled import Hyper, Learner, iterate
    from rlbackdoors.models import build_model

    cfgs = configs(k)
    module, _, name = str(cfgs[0].world.compiled_engine).partition(":")
    jax_world = getattr(importlib.import_module(module), name)
    learners = []
    for cfg, engine in zip(cfgs, engines_of(cfgs)):
        torch.manual_seed(cfg.train.seed)
        model = build_model(ARCH, ENV)
        aux = torch.nn.Linear(model.memory_size, 2) if model.recurrent and cfg.ppo.aux_memory_coef > 0 else None  # (PPO's auxiliary memory head)
        obs = engine.reset(seed=cfg.train.seed * 1000)[0]
        learners.append(Learner(model, engine, Hyper.of(cfg.ppo), cfg.train.seed, obs, jax_world, aux=aux))

    def once():
        return sum(out.num_frames for out in iterate(learners))

    return timed(once, seconds)


def timed(once, seconds: float) -> dict:
    t0 = time.perf_counter()
    for _ in range(3):  # warm-up: compiles, caches (and a deeper queue's program, where the first was too shallow)
        once()
    warm = time.perf_counter() - t0
    frames, start, cpu = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - start < seconds:
        frames += once()
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    return {
        "frames": frames,
        "wall_s": round(wall, 3),
        "cpu_s": round(cpu, 3),
        "frames_per_s": round(frames / wall, 1),
        "frames_per_cpu_s": round(frames / cpu, 1),
        "warmup_s": round(warm, 2),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ks", default="1,16", help="group sizes of the compiled side (comma-separated)")
    ap.add_argument(
        "--torch-k",
        type=int,
        default=None,
        help="today's side's group size (its best on 2 cores: 16 with the JAX update; default 16 on the CPU, none with --device cuda); 0: none",
    )
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--env", choices=("lavaworld", "randomized-lavaworld", "colorful-memory"), default="lavaworld")
    ap.add_argument(
        "--arch",
        choices=("fc", "cnn", "cnn-gru-small-onehot"),
        default="fc",
        help="the model (the torch side's update: JAX for LavaWorld's fc, torch's otherwise)",
    )
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="where the compiled side runs")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    global ARCH, ENV
    ARCH, ENV = args.arch, args.env
    torch_k = (16 if args.device == "cpu" else 0) if args.torch_k is None else args.torch_k
    from rlbackdoors.algos import xla
    from rlbackdoors.bench.machine import machine_info

    jax = xla.start(gpu=args.device == "cuda")  # on the CPU one compute thread, as both sides train in a zoo's process per core
    if args.device == "cuda" and jax.default_backend() != "gpu":
        print(f"compiled_lavaworld: --device cuda, but JAX computes on {jax.default_backend()}", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    result: dict = {
        "machine": machine_info(),
        "env": ENV,
        "arch": ARCH,
        "device": args.device,
        "load_before": os.getloadavg(),
        "seconds": args.seconds,
        "sides": {},
    }
    today = None
    if torch_k:
        today = torch_group(torch_k, args.seconds)
        result["sides"][f"torch K={torch_k} ({'jax' if ENV == 'lavaworld' and ARCH == 'fc' else 'torch'} update)"] = today
        print(f"torch K={torch_k}: {today['frames_per_s']:,.0f} frames/s", file=sys.stderr, flush=True)
    for k in (int(x) for x in args.ks.split(",")):
        side = compiled_group(k, args.seconds)
        if today is not None:
            side["ratio_to_torch"] = round(side["frames_per_s"] / today["frames_per_s"], 3)
        result["sides"][f"compiled K={k}"] = side
        ratio = f" (x{side['ratio_to_torch']:.2f})" if today is not None else ""
        print(f"compiled K={k}: {side['frames_per_s']:,.0f} frames/s{ratio}", file=sys.stderr, flush=True)
    result["load_after"] = os.getloadavg()
    text = json.dumps(result, indent=2)
    if args.json:
        args.json.write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
