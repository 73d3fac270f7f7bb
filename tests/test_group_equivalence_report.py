"""experiments/group_equivalence/group_equivalence.py's tests, on committed reports' per-run rows
(the Randomized LavaWorld CNN's 20 lone and 20 grouped runs, 2026-11-28)."""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HERE = ROOT / "experiments" / "group_equivalence"
spec = importlib.util.spec_from_file_location("group_equivalence", HERE / "group_equivalence.py")
assert spec and spec.loader
equivalence = importlib.util.module_from_spec(spec)
spec.loader.exec_module(equivalence)


def rows(name: str) -> dict:
    return json.loads((HERE / name).read_text())["runs"]


def test_compare_gives_a_reports_difference_tests_again_and_its_equivalence_within_the_margins():
    runs = rows("group_equivalence_rlw_cnn_2026-11-28.json")
    tests = equivalence.compare(runs["alone"], runs["group"])
    recorded = json.loads((HERE / "group_equivalence_rlw_cnn_2026-11-28.json").read_text())["tests"]
    for key in ("converged_fisher_p", "frames_to_converge_mannwhitney_p", "clean_sr_mannwhitney_p", "poisoned_sr_mannwhitney_p"):
        assert tests[key] == pytest.approx(recorded[key], rel=1e-12)
    # within 0.02 SR and a quarter of the median frames, at the 0.05 level: every outcome
    assert all(tests[f"{key}_tost_p"] < 0.05 for key in ("frames_to_converge", "clean_sr", "poisoned_sr")), tests


def test_tost_refuses_equivalence_for_a_side_moved_past_the_margin_and_grants_it_for_the_same_side():
    """The grouped side's clean SR moved by 0.03 (past the 0.02 margin) is not equivalent; the lone
    side against itself is; a shift inside the margin needs enough runs to show it."""
    alone = equivalence.column(rows("group_equivalence_rlw_cnn_2026-11-28.json")["alone"], "clean_sr")
    assert equivalence.tost_p(alone, alone, 0.02) < 1e-4
    assert equivalence.tost_p(alone, [x - 0.03 for x in alone], 0.02) > 0.5
    assert equivalence.tost_p(alone, [x + 0.03 for x in alone], 0.02) > 0.5
    # 3 runs a side cannot show it: the smallest one-sided Mann-Whitney p of 3 against 3 is 1/20
    assert equivalence.tost_p(alone[:3], alone[:3], 0.02) == pytest.approx(0.05)


def test_retest_rewrites_only_the_tests_of_a_committed_report(tmp_path):
    report = tmp_path / "report.json"
    shutil.copy(HERE / "group_equivalence_cm.json", report)
    before = json.loads(report.read_text())
    done = subprocess.run([sys.executable, str(HERE / "group_equivalence.py"), "--retest", str(report)], capture_output=True, text=True, check=True)
    after = json.loads(report.read_text())
    assert done.stdout.startswith("report.json: {") and after["margins"] == equivalence.MARGINS
    assert {k: v for k, v in after.items() if k not in ("tests", "margins")} == {k: v for k, v in before.items() if k not in ("tests", "margins")}
    assert after["tests"] == before["tests"]  # (committed retested: the same again)
    before["tests"] = {k: v for k, v in before["tests"].items() if "tost" not in k}  # a report from before the TOST
    report.write_text(json.dumps(before))
    subprocess.run([sys.executable, str(HERE / "group_equivalence.py"), "--retest", str(report)], capture_output=True, text=True, check=True)
    assert json.loads(report.read_text())["tests"] == after["tests"]
    assert sorted(k for k in after["tests"] if "tost" in k) == ["clean_sr_tost_p", "frames_to_converge_tost_p", "poisoned_sr_tost_p"]


def test_plot_draws_a_row_per_report_and_the_same_bytes_twice(tmp_path):
    reports = [str(HERE / "group_equivalence_rlw_cnn_2026-11-28.json"), str(HERE / "group_equivalence_cm.json")]
    for name in ("a.png", "b.png"):
        subprocess.run([sys.executable, str(HERE / "group_equivalence.py"), "--plot", *reports, "--png", str(tmp_path / name)], check=True, capture_output=True)
    import matplotlib.image

    image = matplotlib.image.imread(tmp_path / "a.png")
    assert image.shape[0] == round(2 * 2.3 * 90) and image.shape[1] == 10 * 90  # two rows of panels, at 90 dpi
    assert (tmp_path / "a.png").read_bytes() == (tmp_path / "b.png").read_bytes()
