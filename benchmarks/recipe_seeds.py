"""Does a recipe converge on every seed? Train seeds 0..N-1 with the same flags and summarise.

    python benchmarks/recipe_seeds.py NAME --seeds 10 --workers 2 -- --env randomized-lavaworld --arch fc

runs ``rlbackdoors train FLAGS --seed S --out runs/recipes/NAME/sS`` for each seed (``--workers``
at a time, one torch thread each), then writes ``benchmarks/results/recipes/NAME.json`` (``--summaries``): converged /
attempted with a Wilson 95 % interval, the distribution (min, median, max) of frames and wall time
of the converged runs, and every run's final clean / poisoned SR on its 200-episode final
evaluation. It resumes: a finished seed is read, not retrained; a killed one resumes from its
checkpoint (``rlbackdoors train`` does that on the same folder); a run that crashes is listed under
``failed`` with its log and the other seeds go on (the script then exits 1). The summary is rewritten after
every finished seed (unfinished ones listed as ``pending``), so a session that ends mid-way still
leaves its numbers; ``--summarise`` writes it from the finished seeds without training. CPU minutes
(what a run costs on one core, however loaded the machine) come from ``metrics.json`` where the run
recorded them. The machine and its load are recorded beside the numbers. A seed whose folder is gone
(a new machine) but whose run the existing summary holds, under the same flags, is carried over from
it, not retrained, and listed under ``carried`` (its figures were measured where that summary says).
``--first S`` trains seeds S..N-1 only.
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


def command(flags: list[str]) -> str:
    return f"rlbackdoors train {' '.join(flags)} --seed S"


def carried_runs(out: Path, flags: list[str]) -> tuple[dict[int, dict], dict | None]:
    """The runs an earlier summary of the same flags holds, as metrics.json-like dicts: a recipe that
    was half measured when its machine was wiped goes on from where it got to."""
    if not out.is_file():
        return {}, None
    old = json.loads(out.read_text())
    if not old.get("command", "").startswith(command(flags) + " ("):
        return {}, None  # other flags: the old numbers are not this recipe's
    runs = {}
    for run in old["runs"]:
        m = {k: run.get(k) for k in ("converged", "clean_sr", "poisoned_sr", "frames", "stop_reason", "trigger")}
        m["wall_time_s"] = run["wall_minutes"] * 60
        m["cpu_time_s"] = None if run.get("cpu_minutes") is None else run["cpu_minutes"] * 60
        if "attack" in run:
            m["attack"], m["attack_budget_used"] = run["attack"], run.get("budget_used")
        runs[run["seed"]] = m
    earlier = old.get("carried", {}).get("machine") or old.get("machine")  # where the carried runs ran
    return runs, earlier


def summary(
    args, flags: list[str], metrics: dict[int, dict], started: float, load_before, failed: dict[int, dict] | None = None, carried: dict | None = None
) -> dict:
    finished = [metrics[s] for s in sorted(metrics)]
    done = [m for m in finished if m["converged"]]
    low, high = wilson(len(done), len(finished)) if finished else (0.0, 1.0)
    cpu = [minutes(m.get("cpu_time_s")) for m in done]
    return {
        "command": f"{command(flags)} (S = {args.first}..{args.seeds - 1}), {args.workers} at a time",
        "converged": len(done),
        "attempted": len(finished),
        "pending": [s for s in range(args.first, args.seeds) if s not in metrics and s not in (failed or {})],
        "failed": [{"seed": s, **why} for s, why in sorted((failed or {}).items())],  # crashed runs: not counted as attempts
        **({"carried": carried} if carried else {}),  # seeds read from the earlier summary, and its machine
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
    parser.add_argument(
        "--summaries", default=str(ROOT / "benchmarks" / "results" / "recipes"), help="where NAME.json is written (and read, to carry runs over)"
    )
    parser.add_argument("--summarise", action="store_true", help="summarise the finished seeds; train nothing")
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    args, flags = parser.parse_args(argv[:cut]), argv[cut + 1 :]  # after --: the rlbackdoors train flags
    torch.set_num_threads(1)  # what each run uses (train.torch_threads), so machine_info records it
    started, load_before = time.time(), os.getloadavg()
    folders = {s: Path(args.runs) / args.name / f"s{s}" for s in range(args.first, args.seeds)}
    metrics = {s: json.loads((f / "metrics.json").read_text()) for s, f in folders.items() if (f / "metrics.json").is_file()}
    out = Path(args.summaries) / f"{args.name}.json"
    earlier, earlier_machine = carried_runs(out, flags)
    kept = sorted(s for s in folders if s not in metrics and s in earlier)
    metrics.update({s: earlier[s] for s in kept})
    carried = {"seeds": kept, "machine": earlier_machine} if kept else None
    out.parent.mkdir(parents=True, exist_ok=True)
    lock = threading.Lock()
    failed: dict[int, dict] = {}

    def write() -> dict:
        result = summary(args, flags, metrics, started, load_before, failed, carried)
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
