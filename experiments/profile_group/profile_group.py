"""Where a training group's time goes: ``--agents`` models of ``--frames`` frames each, trained in
one group in this process (``train_group``, the zoo's group job without the zoo) under cProfile.

Prints the share of the wall time spent stepping the agents' envs, in the stacked forward while
collecting, in the batched update, in evaluations and in the rest, then the functions with the
most own time; ``--json`` writes the figures with the machine. Why: on a GPU the group trainer
was measured no faster than one process per CPU core (docs/zoos.md), and the fix depends on
which part bounds it.

    python experiments/profile_group/profile_group.py --device cuda --agents 64 --frames 20000 --json out.json
"""

from __future__ import annotations

import argparse
import cProfile
import io
import json
import os
import pstats
import sys
import tempfile
import time
from pathlib import Path

# (label, module path suffix, function): cumulative time of these calls, as shares of the wall time
PARTS = (
    ("env steps", "algos/ppo.py", "env_step"),
    ("stacked forward (collect)", "algos/group.py", "forward"),
    ("collect in all", "algos/group.py", "collect"),
    ("update", "algos/group.py", "update"),
    ("OPAC² update (group)", "algos/group_opac2.py", "update"),
    ("OPAC² act (group)", "algos/group_opac2.py", "act"),
    ("OPAC² update (alone)", "algos/opac2.py", "update"),
    ("evaluations (final included)", "train/driver.py", "evaluate_runs"),
    ("agent steps in lone evaluations", "rlbackdoors/agent.py", "act"),
    ("stacked act in group evaluations", "algos/group.py", "act"),
    ("finish (files, curve)", "train/driver.py", "finish"),
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="lavaworld")
    parser.add_argument("--agents", type=int, default=16)
    parser.add_argument("--frames", type=int, default=20_000)
    parser.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    parser.add_argument("--top", type=int, default=20)
    parser.add_argument("--json")
    args = parser.parse_args(argv)

    from rlbackdoors.bench.machine import machine_info
    from rlbackdoors.bench.zoo import bench_spec
    from rlbackdoors.config import RunConfig
    from rlbackdoors.train.group import train_group
    from rlbackdoors.zoo.plan import plan
    from rlbackdoors.zoo.spec import parse_spec

    with tempfile.TemporaryDirectory(prefix="rlbackdoors-profile-group-") as tmp:
        root = Path(tmp) / "zoo"
        plan(parse_spec(bench_spec(args.env, None, args.agents, args.frames, args.device)), root)
        runs = [(f.name, RunConfig.load(f / "config.json"), f) for f in sorted((root / "models").iterdir())]
        profiler = cProfile.Profile()
        load = os.getloadavg()
        start = time.perf_counter()
        profiler.enable()
        result = train_group(runs, args.agents)
        profiler.disable()
        wall = time.perf_counter() - start
    if result.errors:
        print(f"errors: {result.errors}", file=sys.stderr)
        return 1
    stats = pstats.Stats(profiler)
    parts = {}
    for label, path, name in PARTS:
        cum = sum(v[3] for (file, _, func), v in stats.stats.items() if func == name and file.replace(os.sep, "/").endswith(path))  # type: ignore[attr-defined]
        parts[label] = round(cum / wall, 3)
    frames = args.agents * args.frames
    print(f"{args.agents} agents x {args.frames:,} frames on {args.device}: {wall:.1f} s, {frames / wall:,.0f} frames/s in all, load {load[0]:.1f}")
    for label, share in parts.items():
        print(f"  {label:34s} {share:6.1%} of the wall time")
    text = io.StringIO()
    pstats.Stats(profiler, stream=text).sort_stats("tottime").print_stats(args.top)
    print(text.getvalue())
    if args.json:
        out = {"agents": args.agents, "frames_per_agent": args.frames, "device": args.device, "wall_s": round(wall, 2)}
        out |= {"frames_per_s": round(frames / wall), "shares_of_wall": parts, "loadavg_before": [round(x, 2) for x in load], "machine": machine_info()}
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
