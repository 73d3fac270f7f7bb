"""Issue 55's round, measured: what ``zoo run`` made of a round's zoo in the wall time it had.

    python benchmarks/round_summary.py ZOO --wall-s SECONDS --exit STATUS [--json OUT/round.json]

``gpu_checks.sh OUT round`` plans ``examples/zoo-lavaworld-round-300.toml`` (300 LavaWorld FC
models, 150 clean and 150 poisoned, converged) and gives ``zoo run --device cuda --group-size
auto`` a lease's time (a lease of its own). This reads the zoo as it was left: per cell and label the converged models
against those wanted, the models finished, the frames trained (finished models' and, for a
model cut short, its checkpoint's: read as data) and, from the models' ``log.csv`` and
``metrics.json``, their evaluation steps. The round is **met** only if every cell has its
converged models and the wall time is within the 15 minutes. If the time ran out first, the
projection is the frames the round still needs (each model short of its cell's count at the
median frames to converge of the lone LavaWorld FC runs, the equivalence report's) at the
frames/s it trained at, evaluations included: a projection, labelled as one. A zoo run that
ended by itself short of models (every attempt used, or failures) gets none.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

from gpu_summary import EQUIVALENCE, ROUND_LIMIT_S  # (a sibling script: its directory is on the path)


def summarise(zoo_path: Path, wall_s: float, exit_status: int) -> dict:
    import torch

    from rlbackdoors.bench.machine import machine_info
    from rlbackdoors.bench.zoo import evaluation_steps
    from rlbackdoors.zoo.index import group_counts, scan
    from rlbackdoors.zoo.plan import Zoo

    zoo = Zoo.open(zoo_path)
    states = scan(zoo)
    cells = [
        {"cell": c.group.key, "wanted": c.group.wanted, "converged": c.converged, "not_converged": c.not_converged, "failed": c.failed, "planned": c.planned}
        for c in group_counts(zoo, states)
    ]
    finished = [s for s in states if s.status == "done"]
    trained = sum(int(s.metrics["frames"]) for s in finished if s.metrics)
    cut, cut_models, unreadable = 0, 0, []
    for s in states:
        if s.status != "done" and (s.folder / "checkpoint.pt").is_file():
            cut_models += 1
            try:  # (written atomically; a kill mid-write leaves the one before)
                cut += int(torch.load(s.folder / "checkpoint.pt", map_location="cpu", weights_only=True)["frames"])
            except (OSError, RuntimeError, KeyError, ValueError) as error:  # counted as no frames, and named
                unreadable.append(f"{s.folder.name}: {error}"[:200])
    eval_steps = sum(evaluation_steps(s.folder) for s in finished)
    devices = sorted({str(s.metrics.get("device")) for s in finished if s.metrics})
    short = sum(max(c["wanted"] - c["converged"], 0) for c in cells)
    rate = (trained + cut) / wall_s if wall_s > 0 else 0.0
    converged_frames = [int(s.metrics["converged_at_frames"] or s.metrics["frames"]) for s in finished if s.converged and s.metrics]
    result: dict = {
        "zoo": zoo.spec.name,
        "models_wanted": sum(c["wanted"] for c in cells),
        "models_converged": sum(c["converged"] for c in cells),
        "models_finished": len(finished),
        "models_cut_with_checkpoints": cut_models,
        "cells": cells,
        "frames_trained": trained + cut,
        "frames_of_cut_models": cut,
        "unreadable_checkpoints": unreadable,
        "eval_steps_of_finished_models": eval_steps,
        "frames_to_converge_median": statistics.median(converged_frames) if converged_frames else None,
        "wall_s": round(wall_s, 1),
        "frames_per_s": round(rate, 1),
        "models_per_hour": round(len(finished) / wall_s * 3600, 1) if wall_s > 0 else 0.0,
        "zoo_run_exit": exit_status,
        "devices": devices,
        "limit_s": ROUND_LIMIT_S,
        "complete": short == 0,
        "met": short == 0 and wall_s <= ROUND_LIMIT_S,
        "machine": machine_info(),
    }
    if eval_steps:
        result["eval_share_of_finished_models"] = round(eval_steps / (eval_steps + trained), 3)
    if short and rate > 0 and exit_status == 124:  # cut by its limit (not: every attempt used, or a failure)
        per_model = json.loads(EQUIVALENCE.read_text())["sides"]["alone"]["frames_to_converge_median"]
        result["projection"] = {
            "models_short": short,
            "frames_per_model": per_model,
            "round_s": round(wall_s + short * per_model / rate, 1),
            "how": "the models each cell still lacks, at the lone runs' median frames to converge, at this run's frames/s (evaluations included)",
        }
    return result


def markdown(r: dict) -> str:
    line = (
        f"Round ({r['zoo']}, {r['models_wanted']} converged models wanted) on {', '.join(r['devices']) or '?'}: "
        f"{r['models_converged']} converged of {r['models_finished']} finished in {r['wall_s']:,.0f} s "
        f"({r['frames_trained']:,} frames, {r['frames_per_s']:,.0f} frames/s, {r['models_per_hour']:,.0f} models/h; zoo run exit {r['zoo_run_exit']})"
    )
    if r["complete"]:
        return line + f": complete, target <= 15 min {'met' if r['met'] else 'not met'}\n"
    projection = r.get("projection")
    if projection:
        more = f"; at that rate the round would take about {projection['round_s'] / 60:.0f} min (a projection: {projection['how']})"
    else:
        more = f"; zoo run ended (exit {r['zoo_run_exit']}) with cells short of converged models: no projection"
    return line + f": not complete, target <= 15 min not met{more}\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("zoo", type=Path)
    parser.add_argument("--wall-s", type=float, required=True, help="the wall seconds zoo run had")
    parser.add_argument("--exit", type=int, required=True, help="zoo run's exit status (124: cut by its limit)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    result = summarise(args.zoo, args.wall_s, args.exit)
    if args.json:
        from rlbackdoors.io import atomic_write_text

        atomic_write_text(args.json, json.dumps(result, indent=2) + "\n")
    sys.stdout.write(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
