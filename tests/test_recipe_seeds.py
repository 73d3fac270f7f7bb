"""benchmarks/recipe_seeds.py across a wiped machine: a recipe half measured in an earlier session
goes on from its summary (same flags), not from scratch, and says which seeds it carried."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "recipe_seeds.py"
FLAGS = ["--env", "lavaworld", "--attack", "trojdrl"]


def earlier_summary(flags: list[str]) -> dict:
    run = {"converged": True, "clean_sr": 0.99, "poisoned_sr": 0.0, "frames": 700160, "stop_reason": "converged", "trigger": "additive"}
    return {
        "command": f"rlbackdoors train {' '.join(flags)} --seed S (S = 0..2), 1 at a time",
        "runs": [
            {"seed": 0, **run, "wall_minutes": 2.5, "cpu_minutes": 1.25, "attack": "trojdrl", "budget_used": {"frames_poisoned": 7001}},
            {"seed": 1, **run, "converged": False, "frames": 2000000, "wall_minutes": 9.0, "cpu_minutes": None},
        ],
        "machine": {"cpu": "the earlier machine"},
    }


def summarise(tmp_path: Path, flags: list[str]) -> dict:
    cmd = [sys.executable, str(SCRIPT), "r", "--seeds", "3", "--runs", str(tmp_path / "runs"), "--summaries", str(tmp_path), "--summarise", "--", *flags]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return json.loads((tmp_path / "r.json").read_text())


def test_a_recipe_carries_the_runs_of_its_earlier_summary_and_a_finished_folder_wins(tmp_path):
    (tmp_path / "r.json").write_text(json.dumps(earlier_summary(FLAGS)))
    folder = tmp_path / "runs" / "r" / "s1"  # seed 1 was trained here again: its folder is read, not the summary
    folder.mkdir(parents=True)
    (folder / "metrics.json").write_text(json.dumps({"converged": True, "frames": 900000, "wall_time_s": 300.0, "cpu_time_s": 150.0}))
    result = summarise(tmp_path, FLAGS)
    assert result["carried"] == {"seeds": [0], "machine": {"cpu": "the earlier machine"}}
    assert result["attempted"] == 2 and result["converged"] == 2 and result["pending"] == [2]
    seed0, seed1 = result["runs"]
    assert seed0["frames"] == 700160 and seed0["wall_minutes"] == 2.5 and seed0["cpu_minutes"] == 1.25
    assert seed0["budget_used"] == {"frames_poisoned": 7001}
    assert seed1["frames"] == 900000 and seed1["cpu_minutes"] == 2.5
    again = summarise(tmp_path, FLAGS)  # summarising a carried summary keeps the first machine
    assert again["carried"] == result["carried"] and again["runs"] == result["runs"]


def test_a_summary_of_other_flags_is_not_carried(tmp_path):
    (tmp_path / "r.json").write_text(json.dumps(earlier_summary([*FLAGS, "--attack-param", "budget=0.05"])))
    result = summarise(tmp_path, FLAGS)
    assert "carried" not in result and result["attempted"] == 0 and result["pending"] == [0, 1, 2]
