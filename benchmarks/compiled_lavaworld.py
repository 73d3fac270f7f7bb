"""Training frames/s of the compiled PPO iteration (algos/compiled.py) against today's best CPU
side (a torch group of K agents, algos/group.py: with the JAX update for the FC model, torch's
for the CNN), in the same process, one core each, on LavaWorld with the env mix (10 copies,
8 clean : 2 poisoned, rollout 128); ``--arch fc`` (default) or ``cnn``.

Training only: rollout, GAE and update, no evaluations (a zoo's figures with them: ``rlbackdoors
bench zoo``); each side warms up (three iterations: compiles, and a deeper layout queue's
program where the first was too shallow) and is then timed for ``--seconds``. The machine and
its load are recorded with the figures.

    python benchmarks/compiled_lavaworld.py --ks 1,8,16,32 --json benchmarks/results/compiled_lavaworld_<cpu>.json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import torch


ARCH = "fc"  # --arch


def configs(k: int):
    """K configs of today's best CPU side: the JAX update for the FC model, torch's for the CNN (the JAX update has no convolutions)."""
    from rlbackdoors.config import RunConfig

    ppo = {"update_backend": "jax"} if ARCH == "fc" else {}
    return [
        RunConfig.from_dict(
            {"env": {"name": "lavaworld"}, "model": {"arch": ARCH}, "poison": {"trigger": "multiplicative:12"}, "ppo": ppo, "train": {"seed": s}}
        )
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
        ppos.append(PPO(build_model(ARCH, "lavaworld"), cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(cfg.train.seed)))
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
    from rlbackdoors.algos.compiled import Hyper, Learner, iterate
    from rlbackdoors.envs.lavaworld_jax import lavaworld_jax
    from rlbackdoors.models import build_model

    cfgs = configs(k)
    learners = []
    for cfg, engine in zip(cfgs, engines_of(cfgs)):
        torch.manual_seed(cfg.train.seed)
        obs = engine.reset(seed=cfg.train.seed * 1000)[0]
        learners.append(Learner(build_model(ARCH, "lavaworld"), engine, Hyper.of(cfg.ppo), cfg.train.seed, obs, lavaworld_jax))

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
    ap.add_argument("--torch-k", type=int, default=16, help="today's side's group size (its best on 2 cores: 16 with the JAX update)")
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--arch", choices=("fc", "cnn"), default="fc", help="the model (the torch side's update: JAX for fc, torch for cnn)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    global ARCH
    ARCH = args.arch
    from rlbackdoors.algos.jax_update import _jax
    from rlbackdoors.bench.machine import machine_info

    _jax()  # one compute thread, as both sides train in a zoo's process per core
    torch.set_num_threads(1)
    result: dict = {"machine": machine_info(), "arch": ARCH, "load_before": os.getloadavg(), "seconds": args.seconds, "sides": {}}
    today = torch_group(args.torch_k, args.seconds)
    result["sides"][f"torch K={args.torch_k} ({'jax' if ARCH == 'fc' else 'torch'} update)"] = today
    print(f"torch K={args.torch_k}: {today['frames_per_s']:,.0f} frames/s", file=sys.stderr, flush=True)
    for k in (int(x) for x in args.ks.split(",")):
        side = compiled_group(k, args.seconds)
        side["ratio_to_torch"] = round(side["frames_per_s"] / today["frames_per_s"], 3)
        result["sides"][f"compiled K={k}"] = side
        print(f"compiled K={k}: {side['frames_per_s']:,.0f} frames/s (x{side['ratio_to_torch']:.2f})", file=sys.stderr, flush=True)
    result["load_after"] = os.getloadavg()
    text = json.dumps(result, indent=2)
    if args.json:
        args.json.write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
