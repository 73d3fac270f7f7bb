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
from typing import NamedTuple

from rlbackdoors import worlds
from rlbackdoors.bench.machine import machine_info
from rlbackdoors.config import UPDATE_BACKENDS


def bench_spec(
    world: str,
    arch: str | None,
    models: int,
    frames: int,
    device: str,
    eval_episodes: int | None = None,
    update_backend: str = "torch",
    attack: str | None = None,
) -> dict:
    """A zoo spec of ``models`` models (half poisoned) of ``world`` that each train ``frames`` frames
    (``eval_episodes``: every evaluation's episodes per condition, the final one's too; default the world's;
    ``update_backend``: PPO's ``ppo.update_backend`` (set in the spec for a PPO world), or
    ``compiled-eval``: the compiled trainer with its evaluations in its program too
    (``train.eval_backend``); ``attack``: the poisoned models' attack with its defaults, None the paper's env mix)."""
    w = worlds.get(world)
    arch = arch or w.arch_names[0]
    trigger = w.default_trigger or w.draw_trigger(None, 0, None)  # a world without a default trigger: one drawn from seed 0
    clean = models // 2
    return {
        "name": f"bench-{world}",
        "seed": 0,
        "examples": {"episodes": 1},
        "overrides": {
            "train": {
                "max_frames": frames,
                "clean_threshold": 1.0,
                "poisoned_threshold": 1.0,
                "video": False,
                "device": device,
                **({"eval_episodes": eval_episodes, "final_eval_episodes": eval_episodes} if eval_episodes else {}),
                **evaluations(update_backend),
            },
            **({"ppo": {"update_backend": trainer(update_backend)}} if w.algorithm == "ppo" else {}),  # named: a new zoo's own pick is auto
        },
        "cells": [
            {
                "world": world,
                "archs": [arch],
                "triggers": [trigger],
                "clean": clean,
                "poisoned": models - clean,
                "max_attempts": max(clean, models - clean),
                **({"attacks": [attack]} if attack else {}),
            }
        ],
    }


def evaluation_steps(folder: Path) -> int:
    """At least the env steps a finished model's evaluations took: each evaluation of its log.csv
    (``train.eval_episodes`` episodes a condition, at the mean lengths it logged) and its final
    one (metrics.json). A confirmation that did not hold is not logged with its lengths, so not
    counted. Why: a benchmark's models are small, and an untrained agent's episodes long (a grid
    world's FC model of 15,360 frames evaluated about 95,000 env steps, docs/zoos.md), so its
    frames/s is mostly evaluation; the share says how much."""
    import csv
    import json
    import math

    def steps(row: dict, episodes: int) -> float:
        lengths = [float(row.get(key) or "nan") for key in ("clean_mean_steps", "poisoned_mean_steps")]
        return episodes * sum(x for x in lengths if not math.isnan(x))

    config = json.loads((folder / "config.json").read_text())
    metrics = json.loads((folder / "metrics.json").read_text())
    with open(folder / "log.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    return round(sum(steps(row, int(config["train"]["eval_episodes"])) for row in rows) + steps(metrics, int(metrics.get("episodes") or 0)))


def run_side(
    spec: dict,
    where: Path,
    group_size: int | str,
    workers: int,
    device: str = "cpu",
    env_workers: int = 0,
    update_backend: str = "torch",
    engine: str = "",
    conv: str = "",
) -> dict:
    """Plan ``spec`` into ``where`` and run it with ``group_size`` (``"auto"``: as ``zoo run
    --group-size auto`` picks for the world's algorithm on ``device``, recorded as the number it
    is; and ``env_workers`` per job for a world of single envs); wall seconds and models per hour.
    ``engine``: what steps a group's grid slots, ``numba`` or ``device`` (the world's device
    engine, where it has one; on CUDA as one CUDA graph a step), set for the side's jobs through
    ``RLBACKDOORS_DEVICE_ENGINE``; empty: the default (numba, ``algos.group.DEVICE_ENGINE``).
    The same bytes either way. ``conv``: how a group computes its CNN's convolutions on ``device``
    (``each``, ``gemm``, ``grouped``: ``models.minigrid.STACKED_CONV``), set through
    ``RLBACKDOORS_STACKED_CONV``; it changes a group's bytes, and each model records it; empty: the default."""
    import json

    from rlbackdoors.algos.group import DEVICE_ENGINE_ENV
    from rlbackdoors.models.minigrid import STACKED_CONV_ENV
    from rlbackdoors.train.group import auto_group_size
    from rlbackdoors.zoo.plan import plan
    from rlbackdoors.zoo.run import run
    from rlbackdoors.zoo.spec import parse_spec

    auto = group_size == "auto"
    if auto:
        world = worlds.get(spec["cells"][0]["world"])
        group_size = auto_group_size(world.algorithm, device, world, trainer(update_backend))
    plan(parse_spec(spec), where)
    saved = {name: os.environ.get(name) for name in (DEVICE_ENGINE_ENV, STACKED_CONV_ENV)}
    if engine:
        os.environ[DEVICE_ENGINE_ENV] = "" if engine == "numba" else device
    if conv:
        os.environ[STACKED_CONV_ENV] = f"{device}:{conv}"
    try:
        load_before = os.getloadavg()
        start = time.perf_counter()
        summary = run(where, workers=workers, group_size=group_size, progress_interval=3600.0, out=io.StringIO(), env_workers=env_workers)
        wall = time.perf_counter() - start
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value
    finished = sorted(p.parent for p in where.glob("models/*/metrics.json"))
    metrics = [json.loads((folder / "metrics.json").read_text()) for folder in finished]
    cpu = [m.get("cpu_time_s") for m in metrics]
    frames = sum(int(m.get("frames") or 0) for m in metrics)  # trained, whole rollouts (a run may pass max_frames by part of one)
    evaluated = sum(evaluation_steps(folder) for folder in finished)
    return {
        "group_size": group_size,
        **({"group_size_from": "auto"} if auto else {}),
        "workers": workers,
        "device": device,
        "env_workers": env_workers,
        "update_backend": trainer(update_backend),
        **evaluations(update_backend),
        **({"engine": engine} if engine else {}),
        **({"conv": conv} if conv else {}),
        "models": summary["done"],
        "failed": summary["failed"],
        "wall_s": round(wall, 2),
        "models_per_hour": round(summary["done"] / wall * 3600, 1),
        # training frames of the finished models over the side's wall time, evaluations and files included
        "frames": frames,
        "frames_per_s": round(frames / wall, 1),
        # and the env steps its evaluations took: at this model size, how much of the work they are
        "eval_steps": evaluated,
        "env_steps_per_s": round((frames + evaluated) / wall, 1),
        "eval_share": round(evaluated / (frames + evaluated), 3) if frames + evaluated else None,
        "cpu_s_per_model": round(sum(c for c in cpu if c is not None) / max(len(cpu), 1), 2),
        "loadavg_before": [round(x, 2) for x in load_before],
        "loadavg_after": [round(x, 2) for x in os.getloadavg()],
    }


class Side(NamedTuple):
    """One side of ``bench zoo``: what a ``--side`` names (:func:`parse_side`)."""

    k: int | str  # group size ("auto": the measured one)
    device: str = "cpu"
    workers: int | None = None  # None: the run's
    env_workers: int = 0  # per job, for a world of single envs
    backend: str = "torch"  # PPO's update backend (or compiled-eval: the compiled trainer, its evaluations in its program)
    engine: str = ""  # what steps a group's grid slots ("": the default)
    conv: str = ""  # how a group computes its convolutions ("": the default)


COMPILED_EVAL = "compiled-eval"  # a side's BACKEND: ppo.update_backend and train.eval_backend compiled
SIDE_BACKENDS = (*UPDATE_BACKENDS, COMPILED_EVAL)


def trainer(backend: str) -> str:
    """A side's BACKEND as ``ppo.update_backend``."""
    return "compiled" if backend == COMPILED_EVAL else backend


def evaluations(backend: str) -> dict:
    """A side's BACKEND's ``train.eval_backend``, where it is not torch's (as spec overrides and result fields)."""
    return {"eval_backend": "compiled"} if backend == COMPILED_EVAL else {}


SIDE_FORMAT = "K[:DEVICE[:WORKERS[:ENV_WORKERS[:BACKEND[:ENGINE[:CONV]]]]]]"


def parse_side(text: str) -> Side:
    """``K[:DEVICE[:WORKERS[:ENV_WORKERS[:BACKEND[:ENGINE[:CONV]]]]]]`` (``--side``): a group size (``auto``: what
    ``zoo run --group-size auto`` picks for the world on that device, the best CPU setting measured), its device
    (default cpu), workers (default: the run's ``--workers``), each job's env workers for a world
    of single envs (default 0: in the job's process), PPO's ``ppo.update_backend`` (default
    torch; ``compiled-eval``: compiled, the evaluations too), what steps a group's grid slots (``numba``, ``device``; default: numba) and how it
    computes its convolutions (``each``, ``gemm``, ``grouped``; default each; see :func:`run_side`).
    Raises ValueError naming the allowed values."""
    from rlbackdoors.models.minigrid import CONV_WAYS

    parts = text.split(":")
    try:
        if not 1 <= len(parts) <= 7:
            raise ValueError
        k: int | str = parts[0] if parts[0] == "auto" else int(parts[0])
        device = parts[1] if len(parts) > 1 else "cpu"
        workers = int(parts[2]) if len(parts) > 2 and parts[2] else None
        env_workers = int(parts[3]) if len(parts) > 3 and parts[3] else 0
        backend = parts[4] if len(parts) > 4 and parts[4] else "torch"
        engine = parts[5] if len(parts) > 5 else ""
        conv = parts[6] if len(parts) > 6 else ""
        if (
            (isinstance(k, int) and k < 1)
            or device not in ("cpu", "cuda", "auto")
            or (workers is not None and workers < 1)
            or env_workers < 0
            or backend not in SIDE_BACKENDS
            or engine not in ("", "numba", "device")
            or (engine == "device" and device == "auto")
            or conv not in ("", *CONV_WAYS)
            or (conv and device == "auto")
        ):
            raise ValueError
    except ValueError:
        raise ValueError(
            f"--side {text!r}: expected {SIDE_FORMAT}, K a positive integer or auto, WORKERS a positive integer (empty: the run's), "
            f"ENV_WORKERS >= 0, DEVICE one of cpu, cuda, auto, BACKEND one of {', '.join(SIDE_BACKENDS)}, ENGINE one of numba, device (device: with DEVICE cpu or cuda), "
            f"CONV one of {', '.join(CONV_WAYS)} (with DEVICE cpu or cuda)"
        ) from None
    return Side(k, device, workers, env_workers, backend, engine, conv)


def side_plan(group_sizes, workers: int, device: str, sides: list[Side] | None) -> list[Side]:
    """The sides to run: ``sides`` as given (workers defaulting to ``workers``; a shorter tuple
    takes :class:`Side`'s defaults), else one process per model and then each of ``group_sizes``,
    all on ``device`` with torch's update, the default engine and convolutions."""
    if sides:
        return [side._replace(workers=side.workers or workers) for side in (Side(*s) for s in sides)]
    return [Side(k, device, workers) for k in (1, *group_sizes)]


def bench_zoo(
    world: str,
    arch: str | None = None,
    models: int = 16,
    frames: int = 100_000,
    group_sizes=(8,),
    workers: int | None = None,
    device: str = "cpu",
    keep: str | None = None,
    sides: list[Side] | None = None,
    on_side=None,
    eval_episodes: int | None = None,
    attack: str | None = None,
) -> dict:
    """Models per hour for one process per model and for each group size, in this order, same run.

    ``sides`` replaces that plan with explicit sides (:class:`Side`), the first the
    reference (say one process per model on the CPU cores against groups on a GPU); ``on_side``
    is called with the result so far after each side (a partial result survives a time limit)."""
    from rlbackdoors.zoo.run import default_workers

    plan_sides = side_plan(group_sizes, workers or default_workers(), device, sides)
    result = {
        "world": world,
        "arch": bench_spec(world, arch, models, frames, plan_sides[0][1])["cells"][0]["archs"][0],
        "models": models,
        "frames_per_model": frames,
        "eval_episodes": eval_episodes or "the world's",
        **({"attack": attack} if attack else {}),
        "device": device if not sides else sorted({side[1] for side in plan_sides}),
        "machine": machine_info(),
        "sides": [],
    }
    with tempfile.TemporaryDirectory(prefix="rlbackdoors-bench-zoo-") as tmp:
        root = Path(keep) if keep else Path(tmp)
        for i, (k, side_device, side_workers, env_workers, backend, engine, conv) in enumerate(plan_sides):
            where = root / (
                f"side{i}-k{k}-{side_device}-w{side_workers}"
                + (f"-e{env_workers}" if env_workers else "")
                + (f"-{backend}" if backend != "torch" else "")
                + (f"-{engine}" if engine else "")
                + (f"-conv-{conv}" if conv else "")
            )
            assert side_workers is not None  # (side_plan fills it in)
            spec = bench_spec(world, arch, models, frames, side_device, eval_episodes, backend, attack)
            side = run_side(spec, where, k, side_workers, side_device, env_workers, backend, engine, conv)
            base = result["sides"][0]["models_per_hour"] if result["sides"] else side["models_per_hour"]
            side["ratio"] = round(side["models_per_hour"] / base, 3) if base else None
            result["sides"].append(side)
            if on_side is not None:
                on_side(result)
    return result
