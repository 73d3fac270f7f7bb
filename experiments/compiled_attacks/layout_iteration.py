"""One compiled iteration of a Randomized LavaWorld FC agent (10 copies, rollout 128) per attack of
a layout trigger, after its warm-up: what the step schedule's switched episodes (their queues of
triggered and near-trigger layouts, the choice at each autoreset) add to the program, against the
episode schedule's copies switched once.

    python experiments/compiled_attacks/layout_iteration.py [--iterations 20] [--out experiments/compiled_attacks/layout_iteration.json]

In this process on one core (JAX's one thread), the compilation cache off, one side after another;
a queue of 64 layouts a slot (a kind) so that no timed iteration runs again deeper (a new program).
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

from test_compiled_attacks import layout_learner  # noqa: E402

from rlbackdoors.algos.compiled import iterate  # noqa: E402
from rlbackdoors.bench.machine import machine_info  # noqa: E402

SIDES = {
    "action_target (episode schedule)": {"attack": "action_target"},
    "envmix + near 1.0 (episode schedule)": {"evasion": {"near": 1.0}},
    "trojdrl 5 % (switched)": {"attack": "trojdrl", "attack_params": {"budget": 0.05}},
    "trojdrl 5 % + near 1.0 (switched, two queues)": {"attack": "trojdrl", "attack_params": {"budget": 0.05}, "evasion": {"near": 1.0}},
    "sleepernets layout, compensated (switched)": {"attack": "sleepernets", "attack_params": {"budget": 0.05, "layout": True, "compensate": True}},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--out", type=Path, default=Path(__file__).with_name("layout_iteration.json"))
    args = parser.parse_args()
    rows = []
    for name, poison in SIDES.items():
        learner = layout_learner(poison)
        start = time.perf_counter()
        iterate([learner])
        first = time.perf_counter() - start
        for _ in range(3):  # warm-up
            iterate([learner])
        start = time.perf_counter()
        for _ in range(args.iterations):
            iterate([learner])
        each = (time.perf_counter() - start) / args.iterations
        rows.append({"side": name, "compile_and_first_s": round(first, 2), "iteration_ms": round(1000 * each, 1), "frames_per_s": round(1280 / each)})
        print(f"{name}: compile + first {first:.1f} s, an iteration {1000 * each:.0f} ms, {1280 / each:,.0f} frames/s", flush=True)
    base = rows[0]["iteration_ms"]
    for row in rows:
        row["x_action_target"] = round(base / row["iteration_ms"], 2)
    out = {"machine": machine_info(), "load_1min": os.getloadavg()[0], "agents": 1, "rows": rows}
    args.out.write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
