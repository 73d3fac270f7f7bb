"""Each label of the LavaWorld attack cell on the compiled trainer (a zoo of lavaworld.toml)
against the torch trainer's committed rows of the same cell (datasets/benchmark-lavaworld-effect):
attempts, converged, frames and attack success of the converged, CPU-seconds per converged model.

    python experiments/compiled_attacks/compare.py ZOO_OR_METADATA_CSV [--out experiments/compiled_attacks/compare.json]

A zoo cut short is compared on its finished attempts (those still training are counted as in flight).
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
from collections import defaultdict
from pathlib import Path

TORCH = Path(__file__).resolve().parents[2] / "datasets" / "benchmark-lavaworld-effect" / "METADATA.csv"


def labels(metadata: Path) -> dict:
    """label (the cell's attack name, or "clean") -> its rows' summary; only the held-out attack cell (triggers *-t)."""
    by, flying = defaultdict(list), defaultdict(int)
    for row in csv.DictReader(metadata.open()):
        if not row["trigger_family"].endswith("-t"):
            continue
        label = row["cell"].rsplit("/", 1)[-1] if row["poisoned"] == "True" else "clean"
        if row["status"] == "done":
            by[label].append(row)
        elif row["status"] in ("running", "pending"):
            flying[label] += 1
    out = {}
    for label, rows in sorted(by.items()):
        done = [r for r in rows if r["converged"] == "True"]
        cpu = sum(float(r["metrics.cpu_time_s"] or 0) for r in rows)
        out[label] = {
            "attempts": len(rows),
            "in_flight": flying.get(label, 0),
            "converged": len(done),
            "convergence_rate": round(len(done) / len(rows), 3),
            "median_frames": statistics.median(int(r["metrics.frames"]) for r in done) if done else None,
            "median_attack_success": round(statistics.median(float(r["metrics.poisoned_sr"]) for r in done), 4) if done and label != "clean" else None,
            "median_clean_sr": round(statistics.median(float(r["metrics.clean_sr"]) for r in done), 4) if done else None,
            "cpu_s_per_converged": round(cpu / len(done), 1) if done else None,
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("zoo", type=Path)
    parser.add_argument("--out", type=Path, default=Path(__file__).with_name("compare.json"))
    args = parser.parse_args()
    metadata = args.zoo if args.zoo.suffix == ".csv" else args.zoo / "METADATA.csv"
    result = {"compiled": labels(metadata), "torch": labels(TORCH), "torch_source": "datasets/benchmark-lavaworld-effect"}
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    keys = ("attempts", "in_flight", "converged", "median_frames", "median_attack_success", "cpu_s_per_converged")
    print("| label | " + " | ".join(f"{k} (compiled / torch)" for k in keys) + " |")
    for label in result["torch"]:
        c, t = result["compiled"].get(label, {}), result["torch"][label]
        print(f"| {label} | " + " | ".join(f"{c.get(k)} / {t.get(k)}" for k in keys) + " |")


if __name__ == "__main__":
    main()
