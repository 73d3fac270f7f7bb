"""A killed ``detect fit`` / ``detect score`` resumes (issue 17, "nothing is lost"): models done
before are read back, not redone, only for the same detector and the same model bytes; the
result is the one an uninterrupted job gives; a second process is refused by the folder's lock."""

from __future__ import annotations

import json
import shutil

import pytest

from rlbackdoors.detect import DetectError, load_detector, make_detector
from rlbackdoors.detect.cli import main
from rlbackdoors.detect.resume import PARTIAL
from rlbackdoors.detect.score import fit_into, score
from rlbackdoors.io import FolderLock
from test_detect_helpers import KillAfter

pytest_plugins = ("test_detect_helpers",)  # its session fixtures: lava_zoo

PARAMS = {"min_per_class": 1}


def _fitted(zoo, folder):
    fit_into(make_detector("weights", **PARAMS), zoo, folder)
    return load_detector(folder)


def test_a_killed_score_resumes_and_gives_the_uninterrupted_result(lava_zoo, tmp_path):
    detector = _fitted(lava_zoo, tmp_path / "det")
    whole = score(detector, lava_zoo, tmp_path / "whole", resamples=200)
    out = tmp_path / "score"
    with pytest.raises(KeyboardInterrupt):
        score(detector, lava_zoo, out, resamples=200, progress=KillAfter(2))
    assert not (out / "score.json").exists() and len(list((out / PARTIAL).rglob("*.json"))) == 2
    again = KillAfter(None)
    result = score(detector, lava_zoo, out, resamples=200, progress=again)
    assert again.lines[0] == "resuming: 2 of 6 models were scored before" and again.computed == 4
    assert result["resumed"] == 2 and not (out / PARTIAL).exists()
    assert [m["probability"] for m in result["models"]] == [m["probability"] for m in whole["models"]]
    assert result["all"] == whole["all"] and json.loads((out / "score.json").read_text())["all"]["n"] == 6


def test_stored_results_count_only_for_the_same_detector_and_model_bytes(lava_zoo, tmp_path):
    zoo = tmp_path / "zoo"
    shutil.copytree(lava_zoo, zoo)
    detector = _fitted(zoo, tmp_path / "det")
    out = tmp_path / "score"
    with pytest.raises(KeyboardInterrupt):
        score(detector, zoo, out, resamples=50, progress=KillAfter(3))
    other = make_detector("weights", **PARAMS, top_k=2)  # other parameters: another job, nothing reused
    fit_into(other, zoo, tmp_path / "other")
    fresh = KillAfter(None)
    assert score(other, zoo, tmp_path / "score-other", resamples=50, progress=fresh)["resumed"] == 0 and fresh.computed == 6
    first = zoo / "models" / "id-00000000" / "reduced-config.json"
    first.write_text(first.read_text() + "\n")  # the model's files changed: its stored result is stale
    again = KillAfter(None)
    assert score(detector, zoo, out, resamples=50, progress=again)["resumed"] == 2 and again.computed == 4


def test_a_killed_fit_resumes_from_its_folder_and_saves_the_same_detector(lava_zoo, tmp_path, capsys):
    whole, det = tmp_path / "whole", tmp_path / "det"
    fit_into(make_detector("weights", **PARAMS), lava_zoo, whole)
    with pytest.raises(KeyboardInterrupt):
        fit_into(make_detector("weights", **PARAMS), lava_zoo, det, progress=KillAfter(4))
    assert not (det / "detector.json").exists() and len(list((det / PARTIAL).rglob("*.json"))) == 4
    # the CLI resumes a folder that holds only a killed fit's work instead of refusing it
    assert main(["fit", "--detector", "weights", "--zoo", str(lava_zoo), "--out", str(det), "--param", "min_per_class=1"]) == 0
    assert "resuming: features of 4 of 6 models were computed before" in capsys.readouterr().err
    assert json.loads((det / "fit.json").read_text())["resumed"] == 4 and not (det / PARTIAL).exists()
    for name in ("detector.json", "arrays.npz"):
        assert (det / name).read_bytes() == (whole / name).read_bytes()


def test_a_second_process_is_refused_while_a_job_holds_the_folder(lava_zoo, tmp_path, capsys):
    detector = _fitted(lava_zoo, tmp_path / "det")
    with FolderLock(tmp_path / "score", "score folder"):
        with pytest.raises(DetectError, match=r"score folder .* is in use by process \d+ on "):
            score(detector, lava_zoo, tmp_path / "score", resamples=50)
    with FolderLock(tmp_path / "det2", "detector folder"):
        code = main(["fit", "--detector", "weights", "--zoo", str(lava_zoo), "--out", str(tmp_path / "det2"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("rlbackdoors: error: detector folder ") and "is in use by process" in err[0]


def test_the_source_digest_follows_every_python_file_of_the_package(tmp_path):
    """Stored results are keyed by the package's source too: a search whose code changed within
    one version (a new candidate grid) must not read back features of the old code."""
    from pathlib import Path

    import rlbackdoors
    from rlbackdoors.detect.resume import ResultStore, source_digest

    package = tmp_path / "rlbackdoors"
    shutil.copytree(Path(rlbackdoors.__file__).parent, package, ignore=shutil.ignore_patterns("__pycache__"))
    assert source_digest(package) == source_digest()  # the copy is the installed code
    family = package / "detect" / "baselines" / "search_formation.py"
    family.write_text(family.read_text().replace("CANDIDATES = 216", "CANDIDATES = 48"))
    assert source_digest(package) != source_digest()
    (package / "notes.txt").write_text("not code")
    family.write_text(family.read_text().replace("CANDIDATES = 48", "CANDIDATES = 216"))
    assert source_digest(package) == source_digest()  # only .py files count
    # the same job and key map to one folder; another detector key to another
    assert ResultStore(tmp_path, "fit", {"detector": "weights"}).folder == ResultStore(tmp_path, "fit", {"detector": "weights"}).folder
    assert ResultStore(tmp_path, "fit", {"detector": "weights"}).folder != ResultStore(tmp_path, "fit", {"detector": "behaviour"}).folder
