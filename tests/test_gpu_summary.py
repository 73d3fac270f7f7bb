"""benchmarks/gpu_summary.py: issue 55's judged table from what gpu_checks.sh wrote, read from a
real H200 lease's bench JSON (2026-11-27) and a bench.log of the script's format."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
H200 = ROOT / "benchmarks" / "results" / "bench_zoo_lavaworld_100k_h200_lockstep.json"


def test_summary_judges_a_leases_sides_and_says_why_a_world_is_missing(tmp_path):
    shutil.copy(H200, tmp_path / "bench_zoo_lavaworld_fc.json")
    (tmp_path / "bench.log").write_text(
        "== lavaworld fc: 64 models x 100000 frames, sides: 8:cpu:16 64:cuda:1 (limit 420 s)\n"
        "== end lavaworld fc: exit 0 at 140 s (124: its limit)\n"
        "== randomized-lavaworld cnn: 64 models x 30000 frames, sides: 8:cpu:16 64:cuda:1 (limit 100 s)\n"
        "== end randomized-lavaworld cnn: exit 124 at 240 s (124: its limit)\n"
        "== colorful-memory cnn-gru-small-onehot: 32 models x 30000 frames, sides: 8:cpu:16 32:cuda:1 (limit 100 s)\n"
        "== end colorful-memory cnn-gru-small-onehot: exit 1 at 250 s (124: its limit)\n"
    )
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "gpu_summary.py"), str(tmp_path)], capture_output=True, text=True, check=True)
    result = json.loads((tmp_path / "summary.json").read_text())
    rows = {row["world"]: row for row in result["worlds"]}
    lava = rows["lavaworld"]
    # that JSON predates frames_per_s: the planned frames over the wall time, 64 x 100,000 / 102.61 s
    assert lava["sides"][0]["frames_per_s"] == pytest.approx(64 * 100_000 / 102.61, rel=1e-3)
    assert lava["reference"]["group_size"] == 8 and lava["best"] == 64
    assert lava["met"] == {"frames_per_s": False, "ratio": False, "k": False}  # x0.35 at K = 64: none of the targets
    # the round: 300 models x the median frames to converge at that rate, far over 15 minutes
    per_model = json.loads((ROOT / "experiments" / "group_equivalence" / "group_equivalence_2026-11-28.json").read_text())["sides"]["alone"][
        "frames_to_converge_median"
    ]
    assert result["round"]["estimated_s"] == pytest.approx(300 * per_model / lava["sides"][0]["frames_per_s"], rel=1e-3)
    assert result["round"]["met"] is False
    # out of time: the rate it stayed below; failed: the exit status, never a figure
    assert rows["randomized-lavaworld"]["missing"] == "no side finished within its 100 s: below 19,200 frames/s, evaluations included"
    assert rows["colorful-memory"]["missing"] == "no side finished: bench zoo exited with 1 (bench.log)"
    assert "K=64 on cuda" in done.stdout and (tmp_path / "summary.md").read_text() == done.stdout


def test_the_gpu_script_runs_through_on_a_cpu(tmp_path):
    """benchmarks/gpu_checks.sh as a lease runs it, dry (``ON_CPU=1``: its ":cuda" sides on the CPU;
    two LavaWorld models of 1,024 frames, no time left for the CUDA tests): the bench JSON, the
    log (with the CNNs' stacked convolutions timed both ways) and the judged table land in OUT, at most the 8 files a lease brings back. Two GPU sides
    of one K (torch's update and JAX's) are told apart, and only the one with more models an hour
    carries the verdict."""
    env = {
        **os.environ,
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",  # its python3 is this one
        "ON_CPU": "1",
        "WORLDS": "lavaworld/fc:2:1024:300",
        "SIDES_lavaworld": "1:cpu:1 2:cuda:1 2:cuda:1:0:jax",
        "EVAL_EPISODES": "2",
        "DEADLINE_S": "0",
    }
    out = tmp_path / "out"
    done = subprocess.run(["bash", str(ROOT / "benchmarks" / "gpu_checks.sh"), str(out)], capture_output=True, text=True, env=env, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    files = sorted(p.name for p in out.iterdir())
    assert files == ["bench.log", "bench_zoo_lavaworld_fc.json", "summary.json", "summary.md"] and len(files) <= 8
    log = (out / "bench.log").read_text()
    assert "== end lavaworld fc: exit 0" in log and "tests: not run" in log and "== stacked_conv: exit 0" in log
    (conv,) = [json.loads(line.split(" ", 1)[1]) for line in log.splitlines() if line.startswith("stacked_conv ")]
    assert set(conv["randomized-lavaworld/cnn/K=2"]) == {"each", "gemm", "gemm_speedup"}  # both ways timed (a GPU's: K = 64)
    (row,) = json.loads((out / "summary.json").read_text())["worlds"]
    assert [(s["group_size"], s["update_backend"]) for s in row["sides"]] == [(2, "torch"), (2, "jax")] and row["reference"]["group_size"] == 1
    best = row["best_side"]
    assert row["sides"][best]["models_per_hour"] == max(s["models_per_hour"] for s in row["sides"])
    assert row["sides"][best]["frames_per_s"] > 0 and row["met"]["frames_per_s"] is False  # a CPU is not the 1 M frames/s GPU
    table = [line for line in (out / "summary.md").read_text().splitlines() if line.startswith("| lavaworld fc")]
    assert len(table) == 2 and table[0].split("|")[3].strip() == "K=2 on cpu" and table[1].split("|")[3].strip() == "K=2 on cpu, jax update"
    assert [line.split("|")[6].strip().startswith("no: frames_per_s") for line in table] == [best == 0, best == 1]  # the verdict on one row only
