"""The TrojAI tutorial (docs/tutorials/trojai.md) runs as written (issue 58): the page's commands, in
order, each as the page gives it. ``rlbackdoors ...`` goes through the same ``main`` a shell runs,
``python container/entrypoint.py ...`` runs the container's own entry point file with TrojAI's
flags, ``container/build.sh`` runs as a script. The default run makes the round from the tutorial's
spec at a tiny budget (2 + 2 models of 3,200 frames, thresholds 0 so every model converges) and
checks what each step must leave behind and print; ``-m slow`` runs the page at its own scale.

The container image itself is built by neither: that needs apptainer and a Docker Hub base image
(``Bootstrap: docker``), neither of which this machine or CI has. What is checked instead: the
fitted folder holds everything ``build.sh`` copies, ``build.sh`` stops in one line when no builder is
installed, and the image's runscript is the ``entrypoint.py`` run here, with the paths the page's
``singularity run`` line gives.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import os
import re
import runpy
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from cli_helpers import cli

ROOT = Path(__file__).resolve().parent.parent
PAGE = ROOT / "docs" / "tutorials" / "trojai.md"
SPEC = ROOT / "examples" / "tutorial-trojai.toml"
ENTRYPOINT = "container/entrypoint.py"
BUILD = "container/build.sh"
# the detector tutorial's tiny budget (tests/test_tutorials.py): a model in a few seconds, every one converged
TINY_TRAIN = "max_frames = 3_200\neval_interval = 1_600\neval_episodes = 4\nfinal_eval_episodes = 4\nclean_threshold = 0.0\npoisoned_threshold = 0.0\nvideo = false\n\n[overrides.ppo]\nrollout = 32\n"
PROBABILITY = re.compile(r"^trojan probability (\d\.\d{6}) written to (\S+)$")
MODEL = re.compile(r"runs/trojai/round/models/(id-\d{8})/")


def blocks(language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", PAGE.read_text(encoding="utf-8"), flags=re.S)


def shell_lines() -> list[str]:
    """The lines of the page's bash blocks, a line ending in ``\\`` joined to the next, as a shell reads them."""
    return [line for block in blocks("bash") for line in block.replace("\\\n", " ").splitlines() if line.strip()]


def steps() -> list[tuple[str, list[str]]]:
    """The page's commands the test runs, in order: (kind, arguments), kind one of ``rlbackdoors``,
    ``entrypoint`` (``python container/entrypoint.py``), ``build`` (``container/build.sh``), and
    ``image`` (the ``singularity run`` of the built image, checked, not run)."""
    found = []
    for line in shell_lines():
        words = shlex.split(line)
        if words[0] == "rlbackdoors":
            found.append(("rlbackdoors", words[1:]))
        elif words[:2] == ["python", ENTRYPOINT]:
            found.append(("entrypoint", words[2:]))
        elif words[0] == BUILD:
            found.append(("build", words[1:]))
        elif words[:2] in (["singularity", "run"], ["apptainer", "run"]):
            found.append(("image", words[2:]))
    return found


def flags(args: list[str]) -> dict[str, str]:
    """``--flag=value`` arguments (the form TrojAI's harness uses) as a dict; a bare flag maps to ''."""
    return dict((a[2:].split("=", 1) + [""])[:2] for a in args if a.startswith("--"))


def page_models() -> tuple[str, str]:
    """The two model folders the page runs the entry point on: a poisoned one, then a clean one."""
    ids = list(dict.fromkeys(MODEL.findall(" ".join(" ".join(a) for kind, a in steps() if kind == "entrypoint"))))
    assert len(ids) == 2, ids
    return ids[0], ids[1]


def labels(folder: Path) -> dict[str, int]:
    """Each model folder's ground truth, as TrojAI ships it: ``models/id-X/ground_truth.csv``."""
    return {p.parent.name: int(p.read_text().strip()) for p in sorted((folder / "models").glob("*/ground_truth.csv"))}


def tiny_spec(tmp_path: Path) -> Path:
    """The tutorial's spec, its training cut to seconds and 2 + 2 models (world, arch, trigger and seed unchanged)."""
    text = SPEC.read_text()
    head, sep, _ = text.partition("[overrides.train]\n")
    cells = text[text.index("[[cells]]") :]
    assert sep and "clean = 3\npoisoned = 3\n" in cells
    path = tmp_path / "tutorial-trojai.toml"
    path.write_text(head + sep + TINY_TRAIN + "\n" + cells.replace("clean = 3\npoisoned = 3\n", "clean = 2\npoisoned = 2\n"))
    return path


def run_entrypoint(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """``python container/entrypoint.py ARGS``: the container's file itself, run as ``__main__`` in this
    process (its imports are already loaded; tests/test_trojai_interop.py runs it as a real process)."""
    out, err = io.StringIO(), io.StringIO()
    argv, sys.argv = sys.argv, [ENTRYPOINT, *args]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), contextlib.chdir(cwd):
            try:
                runpy.run_path(str(ROOT / ENTRYPOINT), run_name="__main__")
                code = 0
            except SystemExit as stop:
                code = stop.code if isinstance(stop.code, int) else 2
    finally:
        sys.argv = argv
    return subprocess.CompletedProcess(args, code, out.getvalue(), err.getvalue())


def run_page(cwd: Path, spec: Path, rename: bool) -> tuple[list[tuple[str, list[str], subprocess.CompletedProcess]], str, str]:
    """Every step of the page in ``cwd``, the spec path replaced by ``spec``; the image's ``singularity
    run`` is checked, not run. ``rename``: the page's two model ids stand for the first poisoned and
    the first clean model of this round (known once it is trained). Every step must exit 0 but the
    build, whose exit says whether a builder is installed. Returns the steps run and the two ids."""
    poisoned, clean = page_models()
    done, ids = [], None
    for kind, args in steps():
        args = [a.replace("examples/tutorial-trojai.toml", str(spec)) for a in args]
        if any(MODEL.search(a) for a in args):
            if ids is None:
                truth = labels(cwd / "runs" / "trojai" / "round")
                ids = (
                    {poisoned: min(k for k, v in truth.items() if v == 1), clean: min(k for k, v in truth.items() if v == 0)}
                    if rename
                    else {poisoned: poisoned, clean: clean}
                )
            args = [MODEL.sub(lambda m: m.group(0).replace(m.group(1), ids[m.group(1)]), a) for a in args]
        if kind == "rlbackdoors":
            result = cli(*args, cwd=cwd)
        elif kind == "entrypoint":
            result = run_entrypoint(args, cwd)
        elif kind == "build":
            if shutil.which("apptainer") or shutil.which("singularity"):
                continue  # a real build: it needs Docker Hub, which no test reaches
            result = subprocess.run(["bash", str(ROOT / BUILD), *args], cwd=cwd, capture_output=True, text=True, timeout=60)
        else:
            continue
        if kind != "build":
            assert result.returncode == 0, (kind, args, result.stderr[-2000:])
        done.append((kind, args, result))
    assert ids is not None
    return done, ids[poisoned], ids[clean]


def page_output(after: str) -> str:
    """The page's ``text`` block that shows what the step starting with ``after`` printed (the first
    text block after the bash block that holds it)."""
    text = PAGE.read_text(encoding="utf-8")
    start = text.index(after)
    return re.search(r"```text\n(.*?)```", text[start:], flags=re.S).group(1)


def check(cwd: Path, done: list[tuple[str, list[str], subprocess.CompletedProcess]], poisoned: str, clean: str) -> None:
    """What the page says each step leaves and prints, at any scale."""
    runs = cwd / "runs" / "trojai"
    round_, zoo = runs / "round", runs / "zoo"
    printed = {" ".join(a[:2]): r for kind, a, r in done if kind == "rlbackdoors"}

    # 1. the zoo is laid out as a TrojAI round: models/id-XXXXXXXX/ with the files a round ships, METADATA.csv
    truth = labels(round_)
    assert truth and set(truth.values()) == {0, 1} and (round_ / "METADATA.csv").is_file()
    for name in truth:
        assert re.fullmatch(r"id-\d{8}", name)
        for file in ("model.pt", "reduced-config.json", "config.json", "ground_truth.csv"):
            assert (round_ / "models" / name / file).is_file(), (name, file)
    assert truth[poisoned] == 1 and truth[clean] == 0
    trained = re.compile(r"^runs/trojai/round: (\d+) of \1 models finished, \1 converged, 0 failed; \1 trained in \d+ s$", flags=re.M)
    assert int(trained.search(printed["zoo run"].stdout).group(1)) == len(truth)
    assert trained.search(page_output("rlbackdoors zoo run"))

    # 2. imported: every model of the round, each with its label; status counts them per label as the page does
    assert labels(zoo) == truth
    imported = re.compile(r"^runs/trojai/zoo: (\d+) TrojAI models \(lavaworld/fc\): \1 imported, 0 already there$", flags=re.M)
    assert int(imported.search(printed["zoo import-trojai"].stdout).group(1)) == len(truth)
    assert imported.search(page_output("rlbackdoors zoo status"))
    with (zoo / "METADATA.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert {r["model_name"]: r["poisoned"] for r in rows} == {k: str(bool(v)) for k, v in truth.items()}
    assert {json.loads((zoo / "models" / k / "trojai.json").read_text())["source"] for k in truth} == {f"models/{k}" for k in truth}
    status = printed["zoo status"].stdout
    for label, value in (("clean", 0), ("poisoned", 1)):
        count = sum(v == value for v in truth.values())
        assert re.search(rf"^lavaworld\s+fc\s+{label}\s+{count}\s+\d\.\d{{3}}\s*$", status, flags=re.M), status
    header = [line.split() for line in status.splitlines() if line.startswith("world ")]
    assert header and header == [line.split() for line in page_output("rlbackdoors zoo status").splitlines() if line.startswith("world ")]
    assert (zoo / "report" / "report.md").is_file()

    # 3. fitted; the entry point wrote a probability in [0, 1], alone in the result file, as the page shows it
    fitted = runs / "weights"
    assert json.loads((fitted / "detector.json").read_text())["detector"] == "weights"
    assert json.loads((fitted / "metaparameters.json").read_text())["detector"] == "weights"
    infers = [(a, r) for kind, a, r in done if kind == "entrypoint" and a[0] == "infer"]
    assert len(infers) == 2
    for (args, result), model in zip(infers, (poisoned, clean), strict=True):
        given = flags(args)
        assert f"/{model}/model.pt" in given["model_filepath"]
        (line,) = result.stdout.splitlines()
        match = PROBABILITY.match(line)
        assert match and match.group(2) == given["result_filepath"], line
        written = (cwd / given["result_filepath"]).read_text()
        assert re.fullmatch(r"\d\.\d+(e-\d+)?", written.strip()), written
        probability = float(written)
        assert 0.0 <= probability <= 1.0 and f"{probability:.6f}" == match.group(1)
    # SCRATCH/result.json keeps the last call's probability (both calls share the scratch folder)
    kept = json.loads((cwd / given["scratch_dirpath"] / "result.json").read_text())
    assert kept["probability"] == probability and kept["error"] is None and kept["mismatch"] is None
    assert PROBABILITY.match(page_output("python container/entrypoint.py infer").strip())

    # configure mode, on the round's own folders: the same learned parameters as detect fit on the imported zoo
    (configure,) = [a for kind, a, _ in done if kind == "entrypoint" and a[0] == "configure"]
    learned = cwd / flags(configure)["learned_parameters_dirpath"]
    assert flags(configure)["configure_models_dirpath"] == "runs/trojai/round/models"
    for file in ("detector.json", "arrays.npz", "metaparameters.json", "metaparameters_schema.json"):
        assert (learned / file).read_bytes() == (fitted / file).read_bytes(), file
    assert json.loads((learned / "fit.json").read_text())["models"] == len(truth)
    (configured,) = [r.stdout for kind, a, r in done if kind == "entrypoint" and a[0] == "configure"]
    fitted_line = re.compile(rf"^runs/trojai/learned: fitted on {len(truth)} models \({sum(truth.values())} poisoned\) in [\d.]+ s$")
    assert fitted_line.match(configured.strip()), configured
    assert re.match(
        r"^runs/trojai/learned: fitted on \d+ models \(\d+ poisoned\) in [\d.]+ s$", page_output("python container/entrypoint.py configure").splitlines()[0]
    )

    # 4. the build: the fitted folder holds what build.sh needs, and without a builder it stops in one line
    builds = [(a, r) for kind, a, r in done if kind == "build"]
    if builds:
        ((args, result),) = builds
        assert result.returncode == 2 and result.stderr.splitlines() == ["rlbackdoors: error: neither apptainer nor singularity is installed"], result.stderr
        assert result.stderr.strip() == page_output("container/build.sh").strip()
        assert not (cwd / args[1]).exists()


def test_the_image_runs_the_entry_point_the_page_runs(tmp_path):
    """What the image holds and runs, from container/ itself: the runscript hands TrojAI's arguments to
    container/entrypoint.py, the learned parameters, metaparameters and schema sit where the page's
    ``singularity run`` line points, and that line passes the flags of the page's own infer call."""
    definition = (ROOT / "container" / "detector.def").read_text()
    runscript = definition.split("%runscript", 1)[1].strip().splitlines()
    assert runscript[0].strip() == 'exec python3 /entrypoint.py "$@"'
    files = {tuple(line.split()) for line in definition.split("%files", 1)[1].split("%post", 1)[0].strip().splitlines()}
    assert {("./entrypoint.py", "/"), ("./metaparameters.json", "/"), ("./metaparameters_schema.json", "/"), ("./learned_parameters", "/")} <= files
    # the build context build.sh hands the builder holds that entry point and this definition
    det = tmp_path / "det"
    det.mkdir()
    for name in ("detector.json", "metaparameters.json", "metaparameters_schema.json"):
        (det / name).write_text("{}")
    done = subprocess.run(["bash", str(ROOT / BUILD), str(det)], env={**os.environ, "RLBACKDOORS_STAGE": str(tmp_path / "ctx")}, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    for name in ("entrypoint.py", "detector.def"):
        assert (tmp_path / "ctx" / name).read_bytes() == (ROOT / "container" / name).read_bytes()

    (image,) = [a for kind, a in steps() if kind == "image"]
    local = next(a for kind, a in steps() if kind == "entrypoint" and a[0] == "infer")
    given = flags(image[image.index("infer") + 1 :])  # after the runtime's own options (--nv, --bind)
    assert set(given) == set(flags(local))  # the same TrojAI flags, every one
    assert (given["metaparameters_filepath"], given["schema_filepath"], given["learned_parameters_dirpath"]) == (
        "/metaparameters.json",
        "/metaparameters_schema.json",
        "/learned_parameters",
    )


def test_the_build_refuses_a_folder_that_is_not_a_fitted_detector(tmp_path):
    """build.sh checks the folder before it looks for a builder: one line naming the missing file."""
    done = subprocess.run(["bash", str(ROOT / BUILD), str(tmp_path), str(tmp_path / "x.sif")], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert done.stderr.splitlines() == [f"rlbackdoors: error: {tmp_path} holds no detector.json (fit it with rlbackdoors detect fit)"]


def test_the_trojai_tutorial_runs_as_written(tmp_path):
    """The page's eleven commands, in order, on the tutorial's round at a tiny budget (4 models)."""
    kinds = [kind for kind, _ in steps()]
    assert kinds == ["rlbackdoors"] * 6 + ["entrypoint"] * 3 + ["build", "image"], kinds
    done, poisoned, clean = run_page(tmp_path, tiny_spec(tmp_path), rename=True)
    check(tmp_path, done, poisoned, clean)
    assert len(labels(tmp_path / "runs" / "trojai" / "zoo")) == 4


@pytest.mark.slow
def test_the_trojai_tutorial_runs_at_its_own_scale(tmp_path):
    """The same commands on the tutorial's own spec, the page's model ids as written (451 and 513 s
    on 2 busy cores): the models it names have the labels it gives, and the import holds the models the
    page's status table counts."""
    done, poisoned, clean = run_page(tmp_path, SPEC, rename=False)
    check(tmp_path, done, poisoned, clean)
    shown = page_output("rlbackdoors zoo status")
    truth = labels(tmp_path / "runs" / "trojai" / "zoo")
    for label, value in (("clean", 0), ("poisoned", 1)):
        assert re.search(rf"^lavaworld\s+fc\s+{label}\s+{sum(v == value for v in truth.values())}\s", shown, flags=re.M), shown
