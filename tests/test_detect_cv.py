"""``rlbackdoors detect cv`` (issue 17, "what Safety allows"): on a dataset too small to split,
every model is scored by a classifier fitted without it; features are computed once and a killed
run resumes; a model that cannot be read gets 0.5 and the reason; the CLI's error contract."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from rlbackdoors.detect import make_detector
from rlbackdoors.detect.cli import main
from rlbackdoors.detect.dataset import list_models
from rlbackdoors.detect.resume import PARTIAL
from rlbackdoors.detect.score import cross_validate, open_one
from test_detect_helpers import KillAfter

pytest_plugins = ("test_detect_helpers",)  # its session fixtures: lava_zoo

PARAMS = {"min_per_class": 1}


def test_each_probability_comes_from_a_detector_fitted_without_its_model(lava_zoo, tmp_path, capsys):
    out = tmp_path / "cv"
    argv = ["cv", "--detector", "weights", "--param", "min_per_class=1", "--zoo", str(lava_zoo), "--out", str(out), "--folds", "3"]
    assert main([*argv, "--resamples", "200", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert printed.startswith("3-fold cross-validation") and "AUC [95% CI]" in printed and "arch=cnn" in printed
    result = json.loads((out / "score.json").read_text())
    assert result["cv"]["folds"] == 3 and result["all"]["n"] == 6 and result["failed"] == 0
    assert all((out / name).read_bytes()[:4] == b"\x89PNG" for name in ("roc.png", "calibration.png"))
    rows = {r["model"]: r for r in result["models"]}
    folds = sorted({r["fold"] for r in rows.values()})
    assert folds == [0, 1, 2]
    models = list_models(lava_zoo)
    for fold in folds:  # stratified: each fold holds one clean and one poisoned model of the six
        assert sorted(m.label for m in models if rows[m.name]["fold"] == fold) == [0, 1]
    # The same numbers from the public API: fit on the other folds, predict the held-out one.
    for fold in folds:
        train = [m for m in models if rows[m.name]["fold"] != fold]
        test = [m for m in models if rows[m.name]["fold"] == fold]
        detector = make_detector("weights", **PARAMS).fit([open_one(m) for m in train], np.array([m.label for m in train]))
        expected = detector.predict_proba([open_one(m) for m in test])
        assert np.allclose([rows[m.name]["probability"] for m in test], expected, rtol=0, atol=1e-12)
    # Another fold seed deals the models differently; the features kept in the folder are reused.
    again = KillAfter(None)
    other = cross_validate(make_detector("weights", **PARAMS), lava_zoo, out, folds=3, seed=5, resamples=50, progress=again)
    assert [r["fold"] for r in other["models"]] != [rows[m.name]["fold"] for m in models]
    assert again.computed == 0 and other["resumed"] == 6


def test_a_killed_cv_resumes_and_gives_the_uninterrupted_result(lava_zoo, tmp_path):
    whole = cross_validate(make_detector("weights", **PARAMS), lava_zoo, tmp_path / "whole", folds=3, resamples=100)
    out = tmp_path / "cv"
    with pytest.raises(KeyboardInterrupt):
        cross_validate(make_detector("weights", **PARAMS), lava_zoo, out, folds=3, resamples=100, progress=KillAfter(4))
    assert not (out / "score.json").exists() and len(list((out / PARTIAL).rglob("*.json"))) == 4
    again = KillAfter(None)
    result = cross_validate(make_detector("weights", **PARAMS), lava_zoo, out, folds=3, resamples=100, progress=again)
    assert "resuming: features of 4 of 6 models were computed before" in again.lines
    assert again.computed == 2 and result["resumed"] == 4
    assert [r["probability"] for r in result["models"]] == [r["probability"] for r in whole["models"]]
    assert result["all"] == whole["all"]


def test_a_model_it_cannot_read_gets_half_trains_no_fold_and_the_folds_shrink(lava_zoo, tmp_path):
    zoo = tmp_path / "zoo"
    shutil.copytree(lava_zoo, zoo)
    (zoo / "models" / "id-00000001" / "model.pt").write_bytes(b"not a torch file")
    lines: list[str] = []
    result = cross_validate(make_detector("weights", **PARAMS), zoo, tmp_path / "cv", folds=3, resamples=100, progress=lines.append)
    assert "2 folds, not 3: the smaller label has 2 models" in lines
    bad = next(r for r in result["models"] if r["model"] == "id-00000001")
    assert bad["probability"] == 0.5 and bad["fold"] == -1 and "id-00000001" in bad["error"]
    assert result["failed"] == 1 and result["cv"]["folds"] == 2 and result["all"]["n"] == 6
    assert sorted(r["fold"] for r in result["models"] if r["error"] is None) in ([0, 0, 0, 1, 1], [0, 0, 1, 1, 1])  # the five readable


def test_cv_errors_are_one_line(lava_zoo, tmp_path, capsys):
    def error(argv):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("rlbackdoors: error: "), err
        return err[0]

    base = ["cv", "--zoo", str(lava_zoo), "--out", str(tmp_path / "cv"), "--quiet"]
    assert "not a features-and-classifier detector" in error([*base, "--detector", "constant"])
    assert "--folds must be at least 2" in error([*base, "--detector", "weights", "--folds", "1"])
    zoo = tmp_path / "one-label"
    shutil.copytree(lava_zoo, zoo)
    for name in ("id-00000001", "id-00000003"):  # two of the three poisoned models leave
        shutil.rmtree(zoo / "models" / name)
    (zoo / "METADATA.csv").unlink()
    assert "at least 2 models of each label" in error(["cv", "--zoo", str(zoo), "--out", str(tmp_path / "cv2"), "--detector", "weights", "--quiet"])
