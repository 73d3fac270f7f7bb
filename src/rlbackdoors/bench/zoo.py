"""Zoo throughput: models per hour with one process per model against the group trainer, in
the same run on the same machine (``rlbackdoors bench zoo``).

Both sides train the same planned zoo (the same configs, drawn from one spec) through
``zoo run``: once with ``--group-size 1`` (today's back-end: a child process per model), once per
group size K (a child process per worker, K models at a time in each, their networks stacked).
Every model trains a fixed number of frames (thresholds at 1.0: nothing stops early, so the
sides do the same work), evaluations and dataset files included, as a zoo would. The machine,
device and load average before and after each side are recorded with the figures.
"""

from __future__ import annotations

import io
import os
import tempfile
import time
from pathlib import Path

from rlbackdoors import worlds
from rlbackdoors.bench.machine import machine_info


def bench_spec(world: str, arch: str | None, models: int, frames: int, device: str) -> dict:
    """A zoo spec of ``models`` models (half poisoned) of ``world`` that each train ``frames`` frames."""
    w = worlds.get(world)
    arch = arch or w.arch_names[0]
    trigger = w.default_trigger or w.draw_trigger(None, 0, None)  # a world without a default trigger: one drawn from seed 0
    clean = models // 2
    return {
        "name": f"bench-{world}",
        "seed": 0,
        "examples": {"episodes": 1},
        "overrides": {"train": {"max_frames": frames, "clean_threshold": 1.0, "poisoned_threshold": 1.0, "video": False, "device": device}},
        "cells": [
            {"world": world, "archs": [arch], "triggers": [trigger], "clean": clean, "poisoned": models - clean, "max_attempts": max(clean, models - clean)}
        ],
    }


def run_side(spec: dict, where: Path, group_size: int, workers: int) -> dict:
    """Plan ``spec`` into ``where`` and run it with ``group_size``; wall seconds and models per hour."""
    import json

    from rlbackdoors.zoo.plan import plan
    from rlbackdoors.zoo.run import run
    from rlbackdoors.zoo.spec import parse_spec

    plan(parse_spec(spec), where)
    load_before = os.getloadavg()
    start = time.perf_counter()
    summary = run(where, workers=workers, group_size=group_size, progress_interval=3600.0, out=io.StringIO())
    wall = time.perf_counter() - start
    cpu = [json.loads(p.read_text()).get("cpu_time_s") for p in sorted(where.glob("models/*/metrics.json"))]
    return {
        "group_size": group_size,
        "workers": workers,
        "models": summary["done"],
        "failed": summary["failed"],
        "wall_s": round(wall, 2),
        "models_per_hour": round(summary["done"] / wall * 3600, 1),
        "cpu_s_per_model": round(sum(c for c in cpu if c is not None) / max(len(cpu), 1), 2),
        "loadavg_before": [round(x, 2) for x in load_before],
        "loadavg_after": [round(x, 2) for x in os.getloadavg()],
    }


def bench_zoo(
    world: str,
    arch: str | None = None,
    models: int = 16,
    frames: int = 100_000,
    group_sizes=(8,),
    workers: int | None = None,
    device: str = "cpu",
    keep: str | None = None,
) -> dict:
    """Models per hour for one process per model and for each group size, in this order, same run."""
    from rlbackdoors.zoo.run import default_workers

    workers = workers or default_workers()
    spec = bench_spec(world, arch, models, frames, device)
    with tempfile.TemporaryDirectory(prefix="rlbackdoors-bench-zoo-") as tmp:
        root = Path(keep) if keep else Path(tmp)
        sides = [run_side(spec, root / f"k{k}", k, workers) for k in (1, *group_sizes)]
    base = sides[0]["models_per_hour"]
    for side in sides:
        side["ratio"] = round(side["models_per_hour"] / base, 3) if base else None
    cell = spec["cells"][0]
    return {
        "world": world,
        "arch": cell["archs"][0],
        "models": models,
        "frames_per_model": frames,
        "device": device,
        "machine": machine_info(),
        "sides": sides,
    }
