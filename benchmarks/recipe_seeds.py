"""Does a recipe converge on every seed? Train seeds 0..N-1 with the same flags and summarise.

    python benchmarks/recipe_seeds.py NAME --seeds 10 --workers 2 -- --env randomized-lavaworld --arch fc

runs ``rlbackdoors train FLAGS --seed S --out runs/recipes/NAME/sS`` for each seed (``--workers``
at a time, one torch thread each), then writes ``benchmarks/recipes/NAME.json``: converged /
attempted with a Wilson 95 % interval, the distribution (min, median, max) of frames and wall time
of the converged runs, and every run's final clean / poisoned SR on its 200-episode final
evaluation. It resumes: a finished seed is read, not retrained; a killed one resumes from its
checkpoint (``rlbackdoors train`` does that on the same folder). The machine and its load are
recorded beside the numbers.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch

from rlbackdoors.bench.machine import machine_info
from rlbackdoors.io import atomic_write_text
from rlbackdoors.zoo.report import wilson

ROOT = Path(__file__).resolve().parents[1]


def train(flags: list[str], seed: int, out: Path) -> dict:
    if not (out / "metrics.json").is_file():
        log = out.with_suffix(".log")
        out.parent.mkdir(parents=True, exist_ok=True)
        with log.open("ab") as fh:
            cmd = [str(Path(sys.executable).parent / "rlbackdoors"), "train", *flags, "--seed", str(seed), "--out", str(out)]
            subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, check=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    return json.loads((out / "metrics.json").read_text())


def spread(values: list[float]) -> dict | None:
    return {"min": min(values), "median": statistics.median(values), "max": max(values)} if values else None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("name")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--runs", default=str(ROOT / "runs" / "recipes"))
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    args, flags = parser.parse_args(argv[:cut]), argv[cut + 1 :]  # after --: the rlbackdoors train flags
    torch.set_num_threads(1)  # what each run uses (train.torch_threads), so machine_info records it
    started, load_before = time.time(), os.getloadavg()
    with ThreadPoolExecutor(args.workers) as pool:
        metrics = list(pool.map(lambda s: train(flags, s, Path(args.runs) / args.name / f"s{s}"), range(args.seeds)))
    done = [m for m in metrics if m["converged"]]
    low, high = wilson(len(done), len(metrics))
    result = {
        "command": f"rlbackdoors train {' '.join(flags)} --seed S (S = 0..{args.seeds - 1}), {args.workers} at a time",
        "converged": len(done),
        "attempted": len(metrics),
        "wilson95": [round(low, 3), round(high, 3)],
        "frames_converged": spread([m["frames"] for m in done]),
        "wall_minutes_converged": spread([round(m["wall_time_s"] / 60, 2) for m in done]),
        "runs": [
            {
                "seed": s,
                **{k: m.get(k) for k in ("converged", "clean_sr", "poisoned_sr", "frames", "stop_reason", "trigger")},
                "wall_minutes": round(m["wall_time_s"] / 60, 2),
            }
            for s, m in enumerate(metrics)
        ],
        "machine": machine_info(),
        "loadavg_before": load_before,
        "loadavg_after": os.getloadavg(),
        "elapsed_minutes": round((time.time() - started) / 60, 1),
    }
    out = ROOT / "benchmarks" / "recipes" / f"{args.name}.json"
    out.parent.mkdir(exist_ok=True)
    atomic_write_text(out, json.dumps(result, indent=2) + "\n")
    print(f"{args.name}: {len(done)}/{len(metrics)} converged, Wilson 95% [{low:.3f}, {high:.3f}]; median {result['wall_minutes_converged']} min -> {out}")


if __name__ == "__main__":
    main()
