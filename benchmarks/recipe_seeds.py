"""Does a recipe converge on every seed? Train seeds 0..N-1 with the same flags and summarise.

    python benchmarks/recipe_seeds.py NAME --seeds 10 --workers 2 -- --env randomized-lavaworld --arch fc

runs ``rlbackdoors train FLAGS --seed S --out runs/recipes/NAME/sS`` for each seed (``--workers``
at a time, one torch thread each), then writes ``benchmarks/recipes/NAME.json``: converged /
attempted with a Wilson 95 % interval, the distribution (min, median, max) of frames and wall time
of the converged runs, and every run's final clean / poisoned SR on its 200-episode final
evaluation. It resumes: a finished seed is read, not retrained; a killed one resumes from its
checkpoint (``rlbackdoors train`` does that on the same folder); a run that crashes is listed under
``failed`` with its log and the other seeds go on (the script then exits 1). The summary is rewritten after
every finished seed (unfinished ones listed as ``pending``), so a session that ends mid-way still
leaves its numbers; ``--summarise`` writes it from the finished seeds without training. CPU minutes
(what a run costs on one core, however loaded the machine) come from ``metrics.json`` where the run
recorded them. The machine and its load are recorded beside the numbers. ``--first S`` trains seeds
S..N-1 only, when seeds below S ran in an earlier session whose folders are gone.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import threading
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


def minutes(seconds) -> float | None:
    return None if seconds is None else round(seconds / 60, 2)


def summary(args, flags: list[str], metrics: dict[int, dict], started: float, load_before, failed: dict[int, dict] | None = None) -> dict:
    finished = [metrics[s] for s in sorted(metrics)]
    done = [m for m in finished if m["converged"]]
    low, high = wilson(len(done), len(finished)) if finished else (0.0, 1.0)
    cpu = [minutes(m.get("cpu_time_s")) for m in done]
    return {
        "command": f"rlbackdoors train {' '.join(flags)} --seed S (S = {args.first}..{args.seeds - 1}), {args.workers} at a time",
        "converged": len(done),
        "attempted": len(finished),
        "pending": [s for s in range(args.first, args.seeds) if s not in metrics and s not in (failed or {})],
        "failed": [{"seed": s, **why} for s, why in sorted((failed or {}).items())],  # crashed runs: not counted as attempts
        "wilson95": [round(low, 3), round(high, 3)],
        "frames_converged": spread([m["frames"] for m in done]),
        "wall_minutes_converged": spread([minutes(m["wall_time_s"]) for m in done]),
        "cpu_minutes_converged": spread([c for c in cpu if c is not None]) if None not in cpu else None,
        "runs": [
            {
                "seed": s,
                **{k: metrics[s].get(k) for k in ("converged", "clean_sr", "poisoned_sr", "frames", "stop_reason", "trigger")},
                "wall_minutes": minutes(metrics[s]["wall_time_s"]),
                "cpu_minutes": minutes(metrics[s].get("cpu_time_s")),
                **({"attack": metrics[s]["attack"], "budget_used": metrics[s].get("attack_budget_used")} if "attack" in metrics[s] else {}),
            }
            for s in sorted(metrics)
        ],
        "machine": machine_info(),
        "loadavg_before": load_before,
        "loadavg_after": os.getloadavg(),
        "elapsed_minutes": round((time.time() - started) / 60, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("name")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--first", type=int, default=0, help="first seed (earlier ones ran elsewhere and are summarised there)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--runs", default=str(ROOT / "runs" / "recipes"))
    parser.add_argument("--summarise", action="store_true", help="summarise the finished seeds; train nothing")
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    args, flags = parser.parse_args(argv[:cut]), argv[cut + 1 :]  # after --: the rlbackdoors train flags
    torch.set_num_threads(1)  # what each run uses (train.torch_threads), so machine_info records it
    started, load_before = time.time(), os.getloadavg()
    folders = {s: Path(args.runs) / args.name / f"s{s}" for s in range(args.first, args.seeds)}
    metrics = {s: json.loads((f / "metrics.json").read_text()) for s, f in folders.items() if (f / "metrics.json").is_file()}
    out = ROOT / "benchmarks" / "recipes" / f"{args.name}.json"
    out.parent.mkdir(exist_ok=True)
    lock = threading.Lock()
    failed: dict[int, dict] = {}

    def write() -> dict:
        result = summary(args, flags, metrics, started, load_before, failed)
        atomic_write_text(out, json.dumps(result, indent=2) + "\n")
        return result

    def one(seed: int) -> None:
        try:
            m = train(flags, seed, folders[seed])
        except subprocess.CalledProcessError as err:  # recorded, and the other seeds still run
            with lock:
                failed[seed] = {"returncode": err.returncode, "log": str(folders[seed].with_suffix(".log"))}
                write()
            return
        with lock:
            metrics[seed] = m
            write()

    if not args.summarise:
        with ThreadPoolExecutor(args.workers) as pool:
            list(pool.map(one, [s for s in folders if s not in metrics]))
    result = write()
    low, high = result["wilson95"]
    pending = f", {len(result['pending'])} pending" if result["pending"] else ""
    crashed = f", {len(failed)} failed (seeds {', '.join(map(str, sorted(failed)))}: see their .log)" if failed else ""
    print(
        f"{args.name}: {result['converged']}/{result['attempted']} converged, Wilson 95% [{low:.3f}, {high:.3f}]"
        f"{pending}{crashed}; median {result['wall_minutes_converged']} min -> {out}"
    )
    if failed:
        sys.exit(1)


if __name__ == "__main__":
    main()
