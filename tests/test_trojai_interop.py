"""TrojAI interoperability without silent wrong scores (issue 31).

Each numbered case of the issue, on model folders trained here and laid out the way each round
shipped them (built by hand below, so these always run; the real example files are read where
the cache of ``experiments/trojai_examples/trojai_examples.py`` has them, and skipped with the reason otherwise):
a right result or one ``rlbackdoors: error:`` line, never a quiet number. The container's entry
point runs as TrojAI's harness runs it: a subprocess with TrojAI's exact arguments.
"""

from __future__ import annotations

import json
import os
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from test_trojai_import import one_error_line as one_error
from test_trojai_import import run_cli as run

ROOT = Path(__file__).resolve().parents[1]
pytest_plugins = ("test_detect_helpers",)  # session fixtures: lava_zoo, world_models
ENV_STRING = "MiniGrid-LavaCrossingS9N1-v0"
CLI = [sys.executable, "-c", "import sys; from rlbackdoors.cli import main; sys.exit(main())"]


def lay_out(source: Path, target: Path, files: dict[str, object], env_string: str | None = ENV_STRING) -> Path:
    """``target`` as a TrojAI round folder: the weights and the label of ``source`` (a folder
    trained here), and only the settings files ``files`` (name -> JSON), as that round shipped."""
    target.mkdir(parents=True)
    shutil.copy(source / "model.pt", target / "model.pt")
    shutil.copy(source / "ground_truth.csv", target / "ground_truth.csv")
    for name, content in files.items():
        (target / name).write_text(json.dumps(content))
    if env_string is not None:
        (target / "clean-example-data").mkdir()
        (target / "clean-example-data" / "env-string.txt").write_text(env_string + "\n")
    return target


JUL_2023 = {"reduced-config.json": {"arch": "basicfc"}, "model.info.json": {"model": "BasicFCModel", "test_max_steps": 100, "poison": "multiplier"}}


@pytest.fixture(scope="module")
def jul_round(lava_zoo, tmp_path_factory) -> Path:
    """The four FC models of the tiny LavaWorld zoo, laid out as d969b25 shipped its example:
    reduced-config.json naming ``basicfc``, model.info.json, the env string; no config.json."""
    root = tmp_path_factory.mktemp("jul-round") / "round"
    for i, name in enumerate(["id-00000000", "id-00000001", "id-00000002", "id-00000003"]):
        lay_out(lava_zoo / "models" / name, root / "models" / f"id-{i:08d}", JUL_2023)
    return root


def harness_args(model: Path, result: Path, scratch: Path, meta: Path, learned: Path, round_dir: Path) -> list[str]:
    """TrojAI's inference call, word for word (``--flag=value``, as its README's singularity run)."""
    return [
        "infer",
        f"--model_filepath={model / 'model.pt'}",
        f"--result_filepath={result}",
        f"--scratch_dirpath={scratch}",
        f"--examples_dirpath={model / 'clean-example-data'}",
        f"--round_training_dataset_dirpath={round_dir}",
        f"--metaparameters_filepath={meta / 'metaparameters.json'}",
        f"--schema_filepath={meta / 'metaparameters_schema.json'}",
        f"--learned_parameters_dirpath={learned}",
    ]


def configure(capsys, models: Path, meta: Path, learned: Path, scratch: Path) -> None:
    code, _, err = run(
        capsys,
        "detect",
        "configure",
        "--scratch_dirpath",
        scratch,
        "--configure_models_dirpath",
        models,
        "--metaparameters_filepath",
        meta / "metaparameters.json",
        "--schema_filepath",
        meta / "metaparameters_schema.json",
        "--learned_parameters_dirpath",
        learned,
    )
    assert code == 0, err


# ----- 1, 2, 7: the Jul 2023 layout, configure and infer, metaparameters -------------------------
def test_the_jul_2023_layout_configures_infers_and_refuses_other_metaparameters(jul_round, tmp_path, capsys):
    meta, learned = tmp_path / "meta", tmp_path / "learned"
    assert run(capsys, "detect", "metaparameters", "--detector", "weights", "--out", meta, "--param", "min_per_class=1")[0] == 0
    configure(capsys, jul_round / "models", meta, learned, tmp_path / "s0")
    fitted_on = json.loads((learned / "detector.json").read_text())["fitted_on"]
    # the settings came from model.info.json (100 steps) and the env string (9x9, one river)
    assert fitted_on["worlds"] == ["lavaworld"] and fitted_on["groups"] == ["lavaworld/fc"]
    assert {k: fitted_on["env"]["lavaworld"][0][k] for k in ("size", "num_crossings", "max_steps")} == {"size": 9, "num_crossings": 1, "max_steps": 100}

    model = jul_round / "models" / "id-00000001"
    result = tmp_path / "result.txt"
    code, out, err = run(capsys, "detect", *harness_args(model, result, tmp_path / "s1", meta, learned, jul_round))
    assert code == 0 and not err, err
    probability = float(result.read_text())
    assert 0.0 <= probability <= 1.0 and f"{probability:.6f}" in out

    # 2: a metaparameter that changes the features is refused, named, and writes no result
    changed = tmp_path / "changed"
    changed.mkdir()
    data = json.loads((meta / "metaparameters.json").read_text())
    (changed / "metaparameters.json").write_text(json.dumps({**data, "statistics": False}))
    shutil.copy(meta / "metaparameters_schema.json", changed)
    other = tmp_path / "other.txt"
    code, _, err = run(capsys, "detect", *harness_args(model, other, tmp_path / "s2", changed, learned, jul_round))
    line = one_error(code, err)
    assert "statistics=False (fitted with True)" in line and "--allow-mismatch" in line and not other.exists()
    code, _, err = run(capsys, "detect", *harness_args(model, other, tmp_path / "s2", changed, learned, jul_round), "--allow-mismatch")
    assert code == 0 and "MISMATCH" in err and "statistics" in err
    assert json.loads((tmp_path / "s2" / "result.json").read_text())["mismatch"].startswith("parameters other than")
    # a fit-only parameter (how the classifier was fitted) changes nothing, and is not a mismatch
    (changed / "metaparameters.json").write_text(json.dumps({**data, "min_per_class": 5}))
    code, _, err = run(capsys, "detect", *harness_args(model, other, tmp_path / "s3", changed, learned, jul_round))
    assert code == 0 and float(other.read_text()) == probability, err


# ----- 3: schemas with ranges and enums from each parameter's own rule ----------------------------
def test_the_schema_carries_every_parameters_range_and_refuses_out_of_range_values(tmp_path, capsys):
    from rlbackdoors.detect import DetectError
    from rlbackdoors.detect.api import detector_names, get_detector
    from rlbackdoors.detect.trojai import schema_for, validate

    for name in detector_names():  # every number has a range, every range reaches the schema
        cls = get_detector(name)
        _, schema = schema_for(name)
        for key, default in cls.defaults.items():
            if isinstance(default, (int, float)) and not isinstance(default, bool):
                assert {"minimum", "maximum"} <= set(schema["properties"][key]), (name, key)
    meta = tmp_path / "meta"
    assert run(capsys, "detect", "metaparameters", "--detector", "weights", "--out", meta)[0] == 0
    schema = json.loads((meta / "metaparameters_schema.json").read_text())
    assert schema["properties"]["top_k"]["minimum"] == 1
    data = json.loads((meta / "metaparameters.json").read_text())
    (meta / "metaparameters.json").write_text(json.dumps({**data, "top_k": -5}))
    with pytest.raises(DetectError, match="top_k"):
        validate(meta / "metaparameters.json", meta / "metaparameters_schema.json")
    _, beh = schema_for("behaviour")
    assert beh["properties"]["policy"]["enum"] == ["sample", "greedy"]
    # the same rules refuse a bad --param everywhere, with one line and no file written
    for argv in (
        ("detect", "metaparameters", "--detector", "weights", "--out", tmp_path / "m2", "--param", "top_k=abc"),
        ("detect", "fit", "--detector", "weights", "--zoo", tmp_path, "--out", tmp_path / "d2", "--param", "top_k=-3"),
        ("detect", "fit", "--detector", "behaviour", "--zoo", tmp_path, "--out", tmp_path / "d3", "--param", "policy=random"),
    ):
        assert "rlbackdoors: error: detector" in one_error(*run(capsys, *argv)[::2])
    assert not (tmp_path / "m2").exists() and not (tmp_path / "d2").exists() and not (tmp_path / "d3").exists()


# ----- 4: a detector fitted on one world refuses another world's model ----------------------------
def test_a_detector_fitted_on_one_world_refuses_other_worlds_and_settings(lava_zoo, world_models, tmp_path, capsys):
    det = tmp_path / "det"
    code, _, err = run(capsys, "detect", "fit", "--detector", "weights", "--zoo", lava_zoo, "--out", det, "--param", "min_per_class=1", "--quiet")
    assert code == 0, err
    meta = det  # fit writes the metaparameters it was fitted with, and their schema
    for world in ("colorful-memory", "safety-car-goal", "randomized-lavaworld"):
        folder = world_models[world]
        result = tmp_path / f"{world}.txt"
        code, _, err = run(capsys, "detect", *harness_args(folder, result, tmp_path / "s", meta, det, folder.parent))
        line = one_error(code, err)
        assert f"it is a {world} model" in line and "fitted on lavaworld models only" in line and not result.exists()
    # the same model in other env settings (a 7x7 room) is outside the fit too
    other = tmp_path / "small" / "models" / "id-00000000"
    shutil.copytree(lava_zoo / "models" / "id-00000001", other)
    reduced = json.loads((other / "reduced-config.json").read_text())
    (other / "reduced-config.json").write_text(json.dumps({**reduced, "env": {**reduced["env"], "size": 7}}))
    code, _, err = run(capsys, "detect", "score", det, "--zoo", other.parents[1], "--quiet")
    line = one_error(code, err)
    assert "size=7" in line and "size=9" in line
    code, out, err = run(capsys, "detect", "score", det, "--zoo", other.parents[1], "--quiet", "--allow-mismatch", "--resamples", "50", "--json")
    assert code == 0, err
    scored = json.loads(out)
    assert scored["mismatched"] == 1 and "size=7" in scored["models"][0]["mismatch"]


# ----- 5: the behaviour search refuses a setting its family cannot play -------------------------
def test_the_behaviour_search_refuses_the_aug_2023_setting_with_one_line(world_models, tmp_path, capsys):
    source = world_models["randomized-lavaworld"]
    round_dir = tmp_path / "aug"
    for i in range(2):  # TrojAI's Aug 2023 layout: config.json with class and grid size, the env string
        folder = lay_out(source, round_dir / "models" / f"id-{i:08d}", {"config.json": {"arch": "FCModel", "grid_size": 9}})
        (folder / "ground_truth.csv").write_text(f"{i}\n")
    code, _, err = run(
        capsys, "detect", "fit", "--detector", "behaviour", "--zoo", round_dir, "--out", tmp_path / "det", "--param", "min_per_class=1", "--quiet"
    )
    line = one_error(code, err)
    assert "cannot play randomized-lavaworld" in line and "num_lava=1" in line and not (tmp_path / "det").exists()
    code, _, err = run(capsys, "detect", "search", round_dir / "models" / "id-00000000")
    assert "num_lava=1" in one_error(code, err)
    # the weights baseline fits there, on the settings the round's files give
    code, _, err = run(capsys, "detect", "fit", "--detector", "weights", "--zoo", round_dir, "--out", tmp_path / "w", "--param", "min_per_class=1", "--quiet")
    assert code == 0, err
    env = json.loads((tmp_path / "w" / "detector.json").read_text())["fitted_on"]["env"]["randomized-lavaworld"]
    assert [(e["size"], e["num_lava"]) for e in env] == [(9, 1)]


# ----- 6 and 7: the importer reads each round's settings, with no flags --------------------------
def test_the_import_plays_each_round_in_its_own_settings_and_says_where_they_came_from(lava_zoo, world_models, jul_round, tmp_path, capsys):
    from rlbackdoors.zoo.index import read_metadata

    aug = lay_out(world_models["randomized-lavaworld"], tmp_path / "aug" / "id-00000000", {"config.json": {"arch": "FCModel", "grid_size": 9}})
    code, _, err = run(capsys, "zoo", "import-trojai", aug.parent, "--out", tmp_path / "aug-zoo", "--episodes", "4", "--examples", "0")
    assert code == 0, err
    config = json.loads((tmp_path / "aug-zoo" / "models" / "id-00000000" / "config.json").read_text())
    assert (config["env"]["size"], config["env"]["num_lava"]) == (9, 1)
    sources = json.loads((tmp_path / "aug-zoo" / "models" / "id-00000000" / "trojai.json").read_text())["env_sources"]
    assert sources == {"size": "config.json: grid_size", "num_lava": f"clean-example-data/env-string.txt: {ENV_STRING}"}
    # 7: d969b25's layout (reduced config names "basicfc") imports with no flags, and again
    for _ in range(2):
        code, _, err = run(capsys, "zoo", "import-trojai", jul_round, "--out", tmp_path / "jul-zoo", "--episodes", "0", "--examples", "0")
        assert code == 0, err
    rows = read_metadata(tmp_path / "jul-zoo" / "METADATA.csv")
    assert {r["trojai.model_class"] for r in rows} == {"BasicFCModel"} and {r["env.max_steps"] for r in rows} == {"100"}
    assert all(not r["trojai.source"].startswith("/") for r in rows)  # nothing of this machine in a dataset
    assert "max_steps=model.info.json: test_max_steps" in rows[0]["trojai.env_sources"]


def test_the_real_example_folders_import_with_no_flags(tmp_path, capsys):
    from test_trojai_import import BENCH, example

    folders = {
        "lavaworld": (example(BENCH.LAVAWORLD_EXAMPLE), {"size": 9, "num_crossings": 1, "max_steps": 100}),
        "randomized-lavaworld": (example(BENCH.FC_EXAMPLE_AUG), {"size": 9, "num_lava": 1}),
        "colorful-memory": (example(BENCH.CM_EXAMPLE), {"size": 7, "max_steps": 250}),
        "safety-car-goal": (example(BENCH.SAFETY_EXAMPLE), {"num_cubes": 2, "max_steps": 1000}),
    }
    for world, (folder, settings) in folders.items():
        out = tmp_path / world
        code, _, err = run(capsys, "zoo", "import-trojai", folder, "--out", out, "--episodes", "0", "--examples", "0")
        assert code == 0, (world, err)
        config = json.loads((out / "models" / "id-00000000" / "config.json").read_text())
        assert config["env"]["name"] == world and {k: config["env"][k] for k in settings} == settings


# ----- 8, 9: an unreadable weights file is named first; no warning with a path -------------------
def test_an_unreadable_weights_file_is_named_first_and_torch_prints_no_path(tmp_path, capsys):
    garbage = tmp_path / "model.pt"
    garbage.write_bytes(b"not a zip archive at all")
    line = one_error(*run(capsys, "evaluate", "--weights", garbage)[::2])
    assert "cannot read weights file" in line and "--arch" not in line
    raw = tmp_path / "raw.pt"
    raw.write_bytes(pickle.dumps({"a": [1, 2]}, protocol=4))  # a raw pickle, no zip archive: torch warns of its protocol
    done = subprocess.run([*CLI, "evaluate", "--weights", str(raw)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and "Warning" not in done.stderr and "site-packages" not in done.stderr, done.stderr


# ----- the container's entry point, as the harness runs it ---------------------------------------
@pytest.mark.slow  # (over 20 s on 2 cores: out of the default run, `make test-slow`)
def test_the_container_entry_point_runs_as_the_harness_calls_it_on_every_world(world_models, tmp_path):
    """``python entrypoint.py infer --flag=value ...`` (the runscript of container/detector.def),
    in a subprocess, on a model folder of each world made here: one float in the result file; the
    legacy call without the sub-command does the same (on the first world: it differs in its argv
    only); a detector fitted on all four worlds."""
    zoo = tmp_path / "zoo" / "models"
    zoo.mkdir(parents=True)
    for world, folder in world_models.items():
        shutil.copytree(folder, zoo / folder.name)
    entry = [sys.executable, str(ROOT / "container" / "entrypoint.py")]
    meta, learned = tmp_path / "meta", tmp_path / "learned"
    assert subprocess.run([*CLI, "detect", "metaparameters", "--detector", "constant", "--out", str(meta), "--param", "value=0.7"], timeout=300).returncode == 0
    done = subprocess.run(
        [
            *entry,
            "configure",
            f"--scratch_dirpath={tmp_path / 'scratch'}",
            f"--configure_models_dirpath={zoo}",
            f"--metaparameters_filepath={meta / 'metaparameters.json'}",
            f"--schema_filepath={meta / 'metaparameters_schema.json'}",
            f"--learned_parameters_dirpath={learned}",
            "--automatic_configuration",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    assert sorted(json.loads((learned / "detector.json").read_text())["fitted_on"]["worlds"]) == sorted(world_models)
    for n, world in enumerate(world_models):
        folder = zoo / world_models[world].name
        for legacy in (False, True)[: 2 if n == 0 else 1]:
            result = tmp_path / f"{world}-{legacy}.txt"
            args = harness_args(folder, result, tmp_path / "scratch", meta, learned, zoo.parent)
            done = subprocess.run([*entry, *(args[1:] if legacy else args)], capture_output=True, text=True, timeout=300)
            assert done.returncode == 0, (world, done.stderr)
            assert float(result.read_text()) == 0.7
    text = (ROOT / "container" / "detector.def").read_text()
    assert 'exec python3 /entrypoint.py "$@"' in text and "./learned_parameters /\n" in text


def test_a_plugin_detector_goes_into_the_image_and_its_entry_point_loads_it(lava_zoo, tmp_path, capsys):
    """``container/build.sh DET --plugin FILE`` puts the file in ``plugins/`` beside the image's
    ``entrypoint.py`` (``RLBACKDOORS_STAGE``: the image's build context, written without a builder,
    which this machine lacks); that entry point, run as the image's runscript runs it, reads the
    plugin's detector back from the learned parameters. Staged without the plugin, it refuses the
    model in one line naming the detector."""
    plugin = ROOT / "examples" / "tutorial_detector.py"
    det = tmp_path / "det"
    code, _, err = run(capsys, "detect", "fit", "--plugin", plugin, "--detector", "last-layer", "--zoo", lava_zoo, "--out", det)
    assert code == 0, err
    model = sorted((lava_zoo / "models").iterdir())[0]
    for staged in (True, False):
        ctx = tmp_path / f"image-{staged}"
        done = subprocess.run(
            ["bash", str(ROOT / "container" / "build.sh"), str(det), *(["--plugin", str(plugin)] if staged else [])],
            env={**os.environ, "RLBACKDOORS_STAGE": str(ctx)},
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert done.returncode == 0, done.stderr
        assert sorted(p.name for p in (ctx / "plugins").iterdir()) == (["tutorial_detector.py"] if staged else [])
        assert (ctx / "entrypoint.py").read_bytes() == (ROOT / "container" / "entrypoint.py").read_bytes()
        result = tmp_path / f"result-{staged}.txt"
        args = harness_args(model, result, tmp_path / "scratch", ctx, ctx / "learned_parameters", lava_zoo)
        done = subprocess.run([sys.executable, str(ctx / "entrypoint.py"), *args], capture_output=True, text=True, timeout=300)
        if staged:
            assert done.returncode == 0, done.stderr
            assert 0.0 <= float(result.read_text()) <= 1.0
        else:
            assert done.returncode == 2 and not result.exists()
            line = one_error(2, done.stderr)
            assert "'last-layer'" in line
    text = (ROOT / "container" / "detector.def").read_text()
    assert "./plugins /\n" in text and "/plugins" in text.split("%post")[1]
    done = subprocess.run(["bash", str(ROOT / "container" / "build.sh"), str(det), "--plugin", str(tmp_path / "none.py")], capture_output=True, text=True)
    assert done.returncode == 2 and done.stderr == f"rlbackdoors: error: --plugin {tmp_path / 'none.py'} is not a file\n"


def test_an_imported_zoo_verifies_and_detect_leaves_out_a_tampered_model_only_when_asked(jul_round, tmp_path, capsys):
    """The import writes each folder's manifest before its completion mark, so `zoo verify` passes
    on an untouched import; a model edited afterwards stops `detect fit` with a line naming it, and
    `--skip-unverified` fits on the others and records which one it left out, and why."""
    zoo = tmp_path / "zoo"
    code, _, err = run(capsys, "zoo", "import-trojai", jul_round, "--out", zoo, "--episodes", "0", "--examples", "0")
    assert code == 0, err
    code, _, err = run(capsys, "zoo", "verify", zoo)
    assert code == 0, err
    (zoo / "models" / "id-00000003" / "metrics.json").write_text("{}\n")
    fit = ("detect", "fit", "--detector", "weights", "--zoo", zoo, "--param", "min_per_class=1", "--quiet")
    assert "id-00000003" in one_error(*run(capsys, *fit, "--out", tmp_path / "d0")[::2])
    code, _, err = run(capsys, *fit, "--out", tmp_path / "d1", "--skip-unverified")
    assert code == 0, err
    record = json.loads((tmp_path / "d1" / "fit.json").read_text())
    assert record["models"] == 3 and list(record["skipped"]) == ["id-00000003"] and "metrics.json" in record["skipped"]["id-00000003"]
