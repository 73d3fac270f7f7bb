"""Env steps per second of a group's engines: a call per agent, one call for the group
(``EngineGroup``), and one call over numba's threads (``parallel``: the engine half of issue 55
on a GPU machine, where the learners compute on the device and the cores are free).

    python benchmarks/engine_threads.py --agents 64 --steps 300 --json benchmarks/results/engine_threads_epyc.json

For each grid world: ``--agents`` env mixes of the world's default poisoned config (half clean:
``poison.poisoned = false``), their engines reset, then ``--steps`` steps of random actions per
side, the same actions on every side; slot-steps per second (slots = agents x copies), best of
``--repeats``. The parallel side runs at each thread count of ``--threads`` (numba.set_num_threads).
The machine and its load are recorded; the sides give the same bytes (tests/test_engine_group.py).
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numba
import numpy as np


def engines_of(world: str, agents: int) -> list:
    from rlbackdoors.config import RunConfig
    from rlbackdoors.poison.mix import make_env_mix

    out = []
    for k in range(agents):
        cfg = RunConfig.from_dict({"env": {"name": world}, "poison": {"poisoned": k % 2 == 1}, "train": {"seed": k}})
        envs = make_env_mix(cfg.env, cfg.poison, k)
        envs = getattr(envs, "envs", envs)  # a seam's engine (the default attack has none)
        envs.reset(seed=1000 * k)
        out.append(envs)
    return out


def run(engines: list, steps: int, side: str, seed: int) -> float:
    from rlbackdoors.envs.batched_base import EngineGroup

    rng = np.random.default_rng(seed)
    actions = [rng.integers(0, 3, (steps, e.num_envs)) for e in engines]
    group = None if side == "per agent" else EngineGroup.of(engines, parallel=side == "parallel")
    if side != "per agent" and group is None:
        raise SystemExit(f"{type(engines[0]).__name__}: these engines cannot share a call")
    started = time.perf_counter()
    for t in range(steps):
        if group is None:
            for e, a in zip(engines, actions):
                e.step(a[t])
        else:
            group.step(np.concatenate([a[t] for a in actions]))
    return sum(e.num_envs for e in engines) * steps / (time.perf_counter() - started)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--worlds", nargs="+", default=["lavaworld", "randomized-lavaworld", "colorful-memory"])
    parser.add_argument("--agents", type=int, default=64)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, nargs="+", default=sorted({1, numba.config.NUMBA_NUM_THREADS}))
    parser.add_argument("--json")
    args = parser.parse_args()
    from rlbackdoors.bench.machine import machine_info
    from rlbackdoors.io import atomic_write_text

    results = {}
    for world in args.worlds:
        engines = engines_of(world, args.agents)
        for side in ("per agent", "one call", "parallel"):  # the first calls compile the kernels
            run(engines, 5, side, 0)
        row = {"slots": sum(e.num_envs for e in engines), "steps": args.steps}
        for side, threads in [("per agent", None), ("one call", None), *(("parallel", n) for n in args.threads)]:
            if threads is not None:
                numba.set_num_threads(threads)
            best = max(run(engines, args.steps, side, r) for r in range(args.repeats))
            name = side if threads is None else f"parallel, {threads} threads"
            row[name] = round(best)
            print(f"{world}: {name}: {best:,.0f} slot-steps/s", flush=True)
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        results[world] = row
    out = {"agents": args.agents, "results": results, "machine": machine_info(), "loadavg": [round(x, 2) for x in os.getloadavg()]}
    if args.json:
        atomic_write_text(args.json, json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
