"""One compiled iteration of 8 LavaWorld FC agents (10 copies each, rollout 128) per attack of the
seam, after its warm-up: what each attack adds to the program.

    python experiments/compiled_attacks/iteration.py [--iterations 5] [--out experiments/compiled_attacks/iteration.json]

Each side in this process on one core (JAX's one thread), the compilation cache off, one after
another; a queue of 64 layouts a slot so that no timed iteration runs again deeper (a new program).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("RLBACKDOORS_JAX_CACHE", "off")  # the compile times are part of the table
ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

from test_compiled import Group  # noqa: E402
from test_compiled_attacks import seam_learner  # noqa: E402

from rlbackdoors.algos.compiled import iterate  # noqa: E402
from rlbackdoors.bench.machine import machine_info  # noqa: E402

SIDES = {
    "envmix (no seam)": None,
    "trojdrl (forced)": {"attack": "trojdrl", "attack_params": {"force_action": True}},
    "badrl (window 10,000)": {"attack": "badrl"},
    "sleepernets (compensated)": {"attack": "sleepernets", "attack_params": {"compensate": True}},
    "action_target": {"attack": "action_target"},
    "envmix + near 1.0": {"evasion": {"near": 1.0}},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path(__file__).with_name("iteration.json"))
    args = parser.parse_args()
    rows = []
    for name, poison in SIDES.items():
        learners = Group(list(range(8)), depth=64).learners if poison is None else [seam_learner(poison, seed=s, depth=64) for s in range(8)]
        start = time.perf_counter()
        iterate(learners)
        first = time.perf_counter() - start
        for _ in range(2):  # warm-up
            iterate(learners)
        start = time.perf_counter()
        for _ in range(args.iterations):
            iterate(learners)
        each = (time.perf_counter() - start) / args.iterations
        rows.append({"side": name, "compile_and_first_s": round(first, 2), "iteration_ms": round(1000 * each, 1), "frames_per_s": round(8 * 1280 / each)})
        print(f"{name}: compile + first {first:.1f} s, an iteration {1000 * each:.0f} ms, {8 * 1280 / each:,.0f} frames/s", flush=True)
    base = rows[0]["iteration_ms"]
    for row in rows:
        row["x_envmix"] = round(base / row["iteration_ms"], 2)
    args.out.write_text(json.dumps({"machine": machine_info(), "load_1min": os.getloadavg()[0], "agents": 8, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
