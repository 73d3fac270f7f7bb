"""``rlbackdoors detect`` end to end on a tiny zoo (issue 17): fit -> score -> infer, TrojAI's
configure, and the CLI's error contract (one ``rlbackdoors: error:`` line, exit 2)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from rlbackdoors.detect.cli import main

pytest_plugins = ("test_detect_helpers",)  # its session fixtures: lava_zoo, world_models


def _trojai_args(zoo: Path, model: str, result: Path, scratch: Path, metaparameters: Path, learned: Path) -> list[str]:
    folder = zoo / "models" / model
    return [
        "infer",
        "--model_filepath",
        str(folder / "model.pt"),
        "--result_filepath",
        str(result),
        "--scratch_dirpath",
        str(scratch),
        "--examples_dirpath",
        str(folder / "clean-example-data"),
        "--round_training_dataset_dirpath",
        str(zoo),
        "--metaparameters_filepath",
        str(metaparameters / "metaparameters.json"),
        "--schema_filepath",
        str(metaparameters / "metaparameters_schema.json"),
        "--learned_parameters_dirpath",
        str(learned),
    ]


def test_fit_score_infer_and_configure(lava_zoo, tmp_path, capsys):
    det, out, meta = tmp_path / "det", tmp_path / "score", tmp_path / "meta"
    assert main(["fit", "--detector", "weights", "--zoo", str(lava_zoo), "--out", str(det), "--param", "min_per_class=1", "--quiet"]) == 0
    assert "weights fitted on 6 models (3 poisoned)" in capsys.readouterr().out
    assert json.loads((det / "fit.json").read_text())["models"] == 6

    assert main(["score", str(det), "--zoo", str(lava_zoo), "--out", str(out), "--resamples", "200", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "AUC [95% CI]" in printed and "world=lavaworld" in printed and "arch=cnn" in printed and "trigger_family=additive" in printed
    result = json.loads((out / "score.json").read_text())
    assert result["all"]["n"] == 6 and result["failed"] == 0 and set(result["by"]) == {"world", "arch", "trigger_family"}
    assert result["by"]["arch"]["fc"]["n"] == 4 and result["seconds_per_model"]["mean"] > 0
    assert all((out / name).read_bytes()[:4] == b"\x89PNG" for name in ("roc.png", "calibration.png"))
    scored = {m["model"]: m["probability"] for m in result["models"]}
    assert {m["model"]: m["true_trigger"] for m in result["models"]}["id-00000001"] == "multiplicative:12"

    assert main(["metaparameters", "--detector", "weights", "--out", str(meta), "--param", "min_per_class=1"]) == 0
    capsys.readouterr()
    result_file = tmp_path / "result.txt"
    assert main(_trojai_args(lava_zoo, "id-00000003", result_file, tmp_path / "scratch", meta, det)) == 0
    assert float(result_file.read_text()) == scored["id-00000003"]
    assert [p.name for p in (tmp_path / "scratch").iterdir()] == ["result.json"]  # the private copy is gone
    assert json.loads((tmp_path / "scratch" / "result.json").read_text())["mismatch"] is None

    learned = tmp_path / "learned"
    configure = [
        "configure",
        "--scratch_dirpath",
        str(tmp_path / "scratch2"),
        "--configure_models_dirpath",
        str(lava_zoo / "models"),
        "--metaparameters_filepath",
        str(meta / "metaparameters.json"),
        "--schema_filepath",
        str(meta / "metaparameters_schema.json"),
        "--learned_parameters_dirpath",
        str(learned),
        "--automatic_configuration",
    ]
    assert main(configure) == 0
    assert {"detector.json", "arrays.npz", "metaparameters.json", "metaparameters_schema.json", "fit.json"} <= {p.name for p in learned.iterdir()}
    other = tmp_path / "result2.txt"
    assert main(_trojai_args(lava_zoo, "id-00000003", other, tmp_path / "scratch", meta, learned)) == 0
    assert other.read_text() == result_file.read_text()  # the same detector, fitted the same way


def test_score_reports_the_found_trigger_beside_the_true_one_and_survives_a_bad_model(lava_zoo, tmp_path, capsys):
    zoo = tmp_path / "zoo"
    shutil.copytree(lava_zoo, zoo)
    (zoo / "models" / "id-00000004" / "model.pt").write_bytes(b"not a torch file")
    det = tmp_path / "det"
    params = ["--param", "candidates=3", "--param", "refine=1", "--param", "confirm=1", "--param", "episodes=2", "--param", "min_per_class=1"]
    assert main(["fit", "--detector", "behaviour", "--zoo", str(lava_zoo), "--out", str(det), *params, "--quiet"]) == 0
    assert main(["score", str(det), "--zoo", str(zoo), "--resamples", "100", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "found trigger" in printed and "true trigger" in printed
    line = next(x for x in printed.splitlines() if x.startswith("id-00000001 "))
    assert line.rstrip().endswith("  multiplicative:12")
    assert "id-00000004: scored 0.5: DetectError: cannot read weights file" in printed
    result = json.loads((det / "score-zoo" / "score.json").read_text())
    assert result["failed"] == 1 and result["all"]["n"] == 6
    bad = next(m for m in result["models"] if m["model"] == "id-00000004")
    assert bad["probability"] == 0.5 and "model.pt" in bad["error"]


def test_search_reports_the_found_trigger_of_one_model_and_never_its_own(lava_zoo, tmp_path, capsys):
    """``detect search`` runs the unfitted behavioural search on one folder: the report is the
    search the behaviour detector runs (same found trigger and features), the folder's own trigger
    and label appear nowhere in it, and a folder without reduced-config.json (a training run's)
    is searched from its weights, with a note."""
    from rlbackdoors.detect.api import make_detector
    from rlbackdoors.detect.handle import open_model

    folder = lava_zoo / "models" / "id-00000001"  # poisoned, multiplicative:12
    params = ["--param", "candidates=3", "--param", "refine=1", "--param", "confirm=1", "--param", "episodes=2"]
    out = tmp_path / "search.json"
    assert main(["search", str(folder), *params, "--top", "2", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    report = json.loads(out.read_text())
    detector = make_detector("behaviour", candidates=3, refine=1, confirm=1, episodes=2)
    features = detector.features(open_model(folder))
    assert report["found"]["spec"] == detector.last_info["found_trigger"] and f"found trigger:  {report['found']['spec']}" in printed
    assert report["features"] == pytest.approx(features)
    assert report["found"]["excess"] == pytest.approx(report["found"]["trojan"] - report["clean"]["trojan"])
    assert len(report["top_screened"]) == 2 and report["candidates_tried"] >= 3 and report["world"] == "lavaworld"
    truth = json.loads((folder / "config.json").read_text())["poison"]
    assert "poisoned" not in json.dumps(report) and truth["trigger"] not in json.dumps(report["params"])

    bare = tmp_path / "run"
    bare.mkdir()
    shutil.copy(folder / "model.pt", bare / "model.pt")
    assert main(["search", str(bare), *params, "--json"]) == 0
    captured = capsys.readouterr()
    assert "no settings file (reduced-config.json" in captured.err and json.loads(captured.out)["found"]["spec"] == report["found"]["spec"]
    assert main(["search", str(tmp_path / "none")]) == 2
    assert "does not exist" in _one_error_line(capsys)


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("rlbackdoors: error: "), err
    return err[0]


def test_errors_are_one_line_and_exit_2(lava_zoo, tmp_path, capsys):
    assert main(["fit", "--detector", "nope", "--zoo", str(lava_zoo), "--out", str(tmp_path / "d")]) == 2
    assert "detector 'nope' is not one of constant" in _one_error_line(capsys)
    assert main(["fit", "--detector", "weights", "--zoo", str(tmp_path / "none"), "--out", str(tmp_path / "d")]) == 2
    assert "does not exist" in _one_error_line(capsys)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("mine")
    assert main(["fit", "--detector", "constant", "--zoo", str(lava_zoo), "--out", str(tmp_path / "full")]) == 2
    assert "holds no detector" in _one_error_line(capsys)
    assert main(["score", str(tmp_path / "full"), "--zoo", str(lava_zoo)]) == 2
    assert "detector.json missing" in _one_error_line(capsys)
    assert main(["fit", "--detector", "weights", "--zoo", str(lava_zoo), "--out", str(tmp_path / "d"), "--param", "top_k"]) == 2
    assert "KEY=VALUE" in _one_error_line(capsys)

    meta, det = tmp_path / "meta", tmp_path / "det"
    assert main(["metaparameters", "--detector", "constant", "--out", str(meta)]) == 0
    assert main(["fit", "--detector", "constant", "--zoo", str(lava_zoo), "--out", str(det), "--quiet"]) == 0
    capsys.readouterr()
    data = json.loads((meta / "metaparameters.json").read_text())
    (meta / "metaparameters.json").write_text(json.dumps({**data, "value": "high"}))
    assert main(_trojai_args(lava_zoo, "id-00000000", tmp_path / "r.txt", tmp_path / "s", meta, det)) == 2
    assert "value" in _one_error_line(capsys) and not (tmp_path / "r.txt").exists()
    with pytest.raises(SystemExit) as stop:
        main(["infer", "--model_filepath", "m.pt"])
    assert stop.value.code == 2 and "required" in _one_error_line(capsys)


def test_infer_scores_a_model_it_cannot_read_half(lava_zoo, tmp_path, capsys):
    meta, det = tmp_path / "meta", tmp_path / "det"
    assert main(["metaparameters", "--detector", "constant", "--out", str(meta), "--param", "value=0.8"]) == 0
    assert main(["fit", "--detector", "constant", "--zoo", str(lava_zoo), "--out", str(det), "--param", "value=0.8", "--quiet"]) == 0
    model = tmp_path / "lonely"
    model.mkdir()
    shutil.copy(lava_zoo / "models" / "id-00000000" / "model.pt", model / "model.pt")  # no reduced-config.json beside it
    result = tmp_path / "r.txt"
    args = _trojai_args(lava_zoo, "id-00000000", result, tmp_path / "s", meta, det)
    args[args.index("--model_filepath") + 1] = str(model / "model.pt")
    capsys.readouterr()
    assert main(args) == 0
    assert float(result.read_text()) == 0.5
    assert "reduced-config.json" in capsys.readouterr().err
    args[args.index("--model_filepath") + 1] = str(lava_zoo / "models" / "id-00000000" / "model.pt")
    assert main(args) == 0 and float(result.read_text()) == 0.8


def test_the_module_runs_on_its_own():
    done = subprocess.run([sys.executable, "-m", "rlbackdoors.detect.cli", "list"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "behaviour" in done.stdout and "attribution" in done.stdout


def test_the_stacks_schema_types_its_member_table(tmp_path):
    """A table-valued parameter (the stack's member_params) is typed "object" in the schema, so a
    string there is refused before any model is read."""
    from rlbackdoors.detect import DetectError
    from rlbackdoors.detect.trojai import validate

    meta = tmp_path / "meta"
    assert main(["metaparameters", "--detector", "stack", "--out", str(meta)]) == 0
    schema = json.loads((meta / "metaparameters_schema.json").read_text())
    assert schema["properties"]["member_params"]["type"] == "object" and schema["properties"]["members"]["type"] == "string"
    data = json.loads((meta / "metaparameters.json").read_text())
    assert validate(meta / "metaparameters.json", meta / "metaparameters_schema.json")["member_params"] == {}
    (meta / "metaparameters.json").write_text(json.dumps({**data, "member_params": "behaviour.candidates=4"}))
    with pytest.raises(DetectError, match="member_params"):
        validate(meta / "metaparameters.json", meta / "metaparameters_schema.json")


def test_score_refuses_an_unknown_factor_and_a_detector_file_of_an_unknown_name(lava_zoo, tmp_path, capsys):
    """Issue 32: `--factor nosuch_column` added a `nosuch_column=?` row, and a detector.json naming
    no registered detector was read; both are one line now, and nothing is written."""
    det = tmp_path / "det"
    assert main(["fit", "--detector", "constant", "--zoo", str(lava_zoo), "--out", str(det), "--quiet"]) == 0
    capsys.readouterr()
    assert main(["score", str(det), "--zoo", str(lava_zoo), "--factor", "nosuch_column", "--quiet", "--out", str(tmp_path / "s")]) == 2
    assert "--factor nosuch_column: not a METADATA.csv column" in _one_error_line(capsys) and not (tmp_path / "s" / "score.json").exists()
    state = json.loads((det / "detector.json").read_text())
    (det / "detector.json").write_text(json.dumps({**state, "detector": "nosuch"}))
    assert main(["score", str(det), "--zoo", str(lava_zoo), "--quiet"]) == 2
    line = _one_error_line(capsys)
    assert "detector.json" in line and "'nosuch' is not one of" in line


def _contradicting_zoo(lava_zoo: Path, root: Path, name: str, arch: str) -> Path:
    """A copy of the zoo whose model ``name`` names ``arch`` in its reduced config around weights of
    another architecture, manifest rewritten to match (a zoo someone else wrote that way, not one
    tampered with after the fact: verification passes)."""
    from rlbackdoors.folder import write_manifest

    zoo = root / "contradicting"
    shutil.copytree(lava_zoo, zoo)
    reduced = zoo / "models" / name / "reduced-config.json"
    data = json.loads(reduced.read_text())
    assert data["arch"] != arch  # the weights are another architecture's
    reduced.write_text(json.dumps({**data, "arch": arch}))
    write_manifest(zoo / "models" / name)
    return zoo


@pytest.mark.parametrize("arch", ["resnet-9000", "other"])
def test_a_folder_that_contradicts_itself_is_refused_or_flagged_on_every_path(lava_zoo, tmp_path, capsys, arch):
    """A model folder whose reduced config names an architecture its weights are not (one the
    product does not know, or the world's other architecture) is refused in one line by fit, cv,
    score and search, and scored 0.5 with a warning by infer (TrojAI's rule for a model it cannot
    read); with --allow-mismatch score, infer and search read it as its weights say and flag it,
    and its probability is the one its weights get in the untouched zoo."""
    name = "id-00000000"
    own = json.loads((lava_zoo / "models" / name / "reduced-config.json").read_text())["arch"]
    arch = {"fc": "cnn", "cnn": "fc"}[own] if arch == "other" else arch
    zoo = _contradicting_zoo(lava_zoo, tmp_path, name, arch)
    said = f"names arch '{arch}'"

    assert main(["fit", "--detector", "weights", "--zoo", str(zoo), "--out", str(tmp_path / "no"), "--param", "min_per_class=1", "--quiet"]) == 2
    line = _one_error_line(capsys)
    assert name in line and said in line and f"its weights fit lavaworld/{own}" in line and not (tmp_path / "no").exists()
    assert main(["cv", "--detector", "weights", "--zoo", str(zoo), "--out", str(tmp_path / "cv"), "--folds", "2", "--quiet"]) == 2
    assert said in _one_error_line(capsys)

    det, meta = tmp_path / "det", tmp_path / "meta"
    assert main(["fit", "--detector", "weights", "--zoo", str(lava_zoo), "--out", str(det), "--param", "min_per_class=1", "--quiet"]) == 0
    assert main(["score", str(det), "--zoo", str(lava_zoo), "--out", str(tmp_path / "s0"), "--resamples", "50", "--quiet"]) == 0
    truth = {m["model"]: m["probability"] for m in json.loads((tmp_path / "s0" / "score.json").read_text())["models"]}
    capsys.readouterr()
    assert main(["score", str(det), "--zoo", str(zoo), "--out", str(tmp_path / "s1"), "--resamples", "50", "--quiet"]) == 2
    line = _one_error_line(capsys)
    assert name in line and said in line and "--allow-mismatch" in line and not (tmp_path / "s1" / "score.json").exists()
    assert main(["score", str(det), "--zoo", str(zoo), "--out", str(tmp_path / "s2"), "--resamples", "50", "--quiet", "--allow-mismatch", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    row = next(m for m in result["models"] if m["model"] == name)
    assert result["mismatched"] == 1 and said in row["mismatch"] and row["probability"] == truth[name]

    assert main(["metaparameters", "--detector", "weights", "--out", str(meta), "--param", "min_per_class=1"]) == 0
    capsys.readouterr()
    args = _trojai_args(zoo, name, tmp_path / "r.txt", tmp_path / "scratch", meta, det)
    assert main(args) == 0
    err = capsys.readouterr().err
    assert float((tmp_path / "r.txt").read_text()) == 0.5 and "scored 0.5" in err and said in err
    assert main([*args, "--allow-mismatch"]) == 0
    err = capsys.readouterr().err
    assert float((tmp_path / "r.txt").read_text()) == pytest.approx(truth[name], abs=1e-12) and "MISMATCH" in err and said in err
    assert said in json.loads((tmp_path / "scratch" / "result.json").read_text())["mismatch"]

    params = ["--param", "candidates=3", "--param", "refine=1", "--param", "confirm=1", "--param", "episodes=2"]
    folder = zoo / "models" / name
    assert main(["search", str(folder), *params, "--json"]) == 2
    assert said in _one_error_line(capsys)
    assert main(["search", str(folder), *params, "--json", "--allow-mismatch"]) == 0
    captured = capsys.readouterr()
    assert "MISMATCH" in captured.err and said in json.loads(captured.out)["mismatch"] and json.loads(captured.out)["arch"] == own
