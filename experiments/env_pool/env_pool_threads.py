"""Does stepping K agents' env copies together beat stepping them one agent after another?

    python experiments/env_pool/env_pool_threads.py [--k 4 8] [--workers 2] [--json experiments/env_pool/env_pool_threads_2core.json]

K vector views (:class:`~rlbackdoors.algos.opac2_loop.SingleEnvs`) of 10 Safety Car Goal copies
each, all in one env pool: what an OPAC² group trainer with ``--env-workers`` holds. Each group
step is timed two ways, alternated (serial, threads, serial, threads) so that drift in the
machine's load hits both:

* serial: the views step one after another, so a worker waits for the next agent's message
  (the group trainer before its runs' loops went on in threads);
* threads: each view steps from its own thread (what :func:`rlbackdoors.train.group.train_group`
  does with an env pool), so every worker holds requests of all K agents at once.

The same random actions both ways; the machine and its load are recorded.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from rlbackdoors.algos.opac2_loop import SingleEnvs
from rlbackdoors.bench.machine import machine_info
from rlbackdoors.config import RunConfig
from rlbackdoors.envs.pool import EnvPool

COPIES, STEPS = 10, 300


def measure(k: int, workers: int) -> dict:
    cfg = RunConfig.from_dict({"env": {"name": "safety-car-goal"}})
    factory = functools.partial(cfg.env.make, cfg.poison.trigger)
    actions = np.random.default_rng(0).uniform(-1.0, 1.0, (STEPS, COPIES, 2))
    times: dict[str, list[float]] = {"serial": [], "threads": []}
    with EnvPool(workers) as pool, ThreadPoolExecutor(k) as threads:
        views = [SingleEnvs(pool.make([factory] * COPIES)) for _ in range(k)]
        for view in views:
            view.reset(seed=1)
        ways = {
            "serial": lambda t: [view.step(actions[t]) for view in views],
            "threads": lambda t: list(threads.map(lambda view: view.step(actions[t]), views)),
        }
        for _ in range(2):
            for name, run in ways.items():
                start = time.perf_counter()
                for t in range(STEPS):
                    run(t)
                times[name].append((time.perf_counter() - start) / STEPS)
    ms = {name: round(1e3 * float(np.mean(v)), 2) for name, v in times.items()}
    return {
        "k": k,
        "copies_per_agent": COPIES,
        "env_workers": workers,
        "ms_per_group_step": ms,
        "frames_per_s": {name: round(k * COPIES / (v / 1e3)) for name, v in ms.items()},
        "threads_over_serial": round(ms["serial"] / ms["threads"], 2),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--k", type=int, nargs="+", default=[4, 8])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--json")
    args = parser.parse_args()
    load_before = os.getloadavg()
    rows = []
    for k in args.k:
        rows.append(measure(k, args.workers))
        r = rows[-1]
        print(
            f"K={k} x {COPIES} copies, {args.workers} env workers: serial {r['ms_per_group_step']['serial']} ms, threads {r['ms_per_group_step']['threads']} ms per group step (x{r['threads_over_serial']})",
            flush=True,
        )
    out = {"rows": rows, "steps": STEPS, "machine": machine_info(), "loadavg_before": load_before, "loadavg_after": os.getloadavg()}
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
