"""The tutorials under docs/tutorials/ run as written (issue 58): each tutorial's ``rlbackdoors``
commands, in order, through the same ``main`` a shell runs. The default run trains the tutorial's
zoo at a tiny budget (3,200 frames a model, thresholds 0 so every model converges) and checks what
each step must leave behind; ``-m slow`` runs them at the tutorial's own scale."""

from __future__ import annotations

import json
import re
import shlex
import sys
from pathlib import Path

import pytest

from cli_helpers import cli

ROOT = Path(__file__).resolve().parent.parent
DETECTORS = ROOT / "docs" / "tutorials" / "detectors.md"
ATTACKS = ROOT / "docs" / "tutorials" / "attacks.md"
# the attack tutorial's step 5 mitigates a model shipped in the repository (the tests run in a scratch folder)
SHIPPED = {p: str(ROOT / p) for p in ("datasets/benchmark-lavaworld-effect-envmix/models/id-00000000",)}
# a tiny training budget for the attack tutorial's runs (each a few seconds), added to its train commands
TINY_RUN = ["--eval-interval", "1600", "--eval-episodes", "4", "--final-eval-episodes", "4", "--checkpoint-minutes", "0"]
TINY_TRAIN = "max_frames = 3_200\neval_interval = 1_600\neval_episodes = 4\nfinal_eval_episodes = 4\nclean_threshold = 0.0\npoisoned_threshold = 0.0\nvideo = false\n\n[overrides.ppo]\nrollout = 32\n"


@pytest.fixture(autouse=True)
def own_registry():
    """A plugin registers its detectors in this process: each test leaves the registry, and the
    imported plugin modules, as it found them (the other test files share the process)."""
    from rlbackdoors.detect import api

    api.detector_names()  # the built-in detectors first: importing them registers them once per process
    registry, modules = set(api._REGISTRY), {k for k in sys.modules if k.startswith("rlbackdoors_plugin_")}
    yield
    for name in set(api._REGISTRY) - registry:
        del api._REGISTRY[name]
    for key in [k for k in sys.modules if k.startswith("rlbackdoors_plugin_") and k not in modules]:
        del sys.modules[key]


def blocks(page: Path, language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", page.read_text(encoding="utf-8"), flags=re.S)


def commands(page: Path) -> list[list[str]]:
    """Every ``rlbackdoors ...`` line of the page's bash blocks, split as a shell would."""
    return [shlex.split(line)[1:] for block in blocks(page, "bash") for line in block.splitlines() if line.startswith("rlbackdoors ")]


def tiny_spec(tmp_path: Path) -> Path:
    """The tutorial's spec with its training budget cut to seconds and 1 + 1 models a cell (its cells'
    worlds, triggers and seed unchanged)."""
    text = (ROOT / "examples" / "tutorial-detectors.toml").read_text()
    head, sep, _ = text.partition("[overrides.train]\n")
    cells = text[text.index("[[cells]]") :]
    assert sep, "the tutorial's spec has no [overrides.train] table"
    assert "clean = 3\npoisoned = 3\n" in cells
    cells = cells.replace("clean = 3\npoisoned = 3\n", "clean = 1\npoisoned = 1\n")  # 4 models, not 12: a process each costs seconds
    path = tmp_path / "tutorial-detectors.toml"
    path.write_text(head + sep + TINY_TRAIN + "\n" + cells)
    return path


def run_tutorial(page: Path, cwd: Path, replace: dict[str, str], extra: dict[str, list[str]] | None = None) -> list[str]:
    """Run the page's commands in ``cwd``, each argument through ``replace``; ``extra``: arguments
    appended to the commands of a sub-command (say, a smaller evaluation for ``train``)."""
    outputs = []
    for argv in commands(page):
        argv = [replace.get(a, a) for a in argv] + (extra or {}).get(argv[0], [])
        done = cli(*argv, cwd=cwd)
        assert done.returncode == 0, (argv, done.stderr[-2000:])
        outputs.append(done.stdout)
    return outputs


def test_the_detector_tutorials_code_is_the_example_file():
    (code,) = blocks(DETECTORS, "python")
    assert code == (ROOT / "examples" / "tutorial_detector.py").read_text()


def check_detector_tutorial(cwd: Path, outputs: list[str]) -> None:
    """What the tutorial says each step leaves: a verified zoo, a split sharing no trigger, and for
    the baseline and the tutorial's own detector a fitted folder and a score of every test model."""
    runs = cwd / "runs" / "tutorial"
    test = [json.loads(p.read_text()) for p in (runs / "test" / "models").glob("*/config.json")]
    train = [json.loads(p.read_text()) for p in (runs / "train" / "models").glob("*/config.json")]
    assert test and train and not {c["poison"]["trigger"] for c in test} & {c["poison"]["trigger"] for c in train}
    for det, name in (("weights", "weights"), ("mine", "last-layer")):
        assert json.loads((runs / det / "detector.json").read_text())["detector"] == name
        score = json.loads((runs / det / "score-test" / "score.json").read_text())
        assert score["detector"] == name and score["all"]["n"] == len(test) and score["failed"] == 0
        assert 0.0 <= score["all"]["auc"]["value"] <= 1.0
        assert (runs / det / "score-test" / "roc.png").read_bytes()[:4] == b"\x89PNG"
    assert sum("AUC" in out for out in outputs) == 2  # the two score tables


def test_the_detector_tutorial_runs_as_written(tmp_path):
    """Its eight commands, in order, on the tutorial's zoo at a tiny budget (4 models, a process
    each, as the tutorial's own zoo run trains them)."""
    replace = {
        "examples/tutorial-detectors.toml": str(tiny_spec(tmp_path)),
        "examples/tutorial_detector.py": str(ROOT / "examples" / "tutorial_detector.py"),
    }
    assert len(commands(DETECTORS)) == 8
    outputs = run_tutorial(DETECTORS, tmp_path, replace)
    check_detector_tutorial(tmp_path, outputs)


@pytest.mark.slow
def test_the_detector_tutorial_runs_at_its_own_scale(tmp_path):
    """The same commands on the tutorial's own spec (about 10 minutes on 2 cores)."""
    outputs = run_tutorial(
        DETECTORS,
        tmp_path,
        {
            "examples/tutorial_detector.py": str(ROOT / "examples" / "tutorial_detector.py"),
            "examples/tutorial-detectors.toml": str(ROOT / "examples" / "tutorial-detectors.toml"),
        },
    )
    check_detector_tutorial(tmp_path, outputs)


def test_a_plugin_registers_its_detectors_and_a_bad_one_is_refused_in_one_line(tmp_path):
    listed = cli("detect", "list", "--plugin", ROOT / "examples" / "tutorial_detector.py")
    assert listed.returncode == 0 and "last-layer" in listed.stdout
    missing = cli("detect", "list", "--plugin", tmp_path / "nope.py")
    assert missing.returncode == 2 and missing.stderr.strip().splitlines() == [
        f"rlbackdoors: error: --plugin {str(tmp_path / 'nope.py')!r} is not a file (a Python file that registers detectors with @register)"
    ]
    (tmp_path / "bad.py").write_text("raise RuntimeError('boom')\n")
    bad = cli("detect", "fit", "--plugin", tmp_path / "bad.py", "--detector", "weights", "--zoo", tmp_path, "--out", tmp_path / "o")
    assert bad.returncode == 2 and bad.stderr.strip().splitlines() == [f"rlbackdoors: error: --plugin {str(tmp_path / 'bad.py')!r} failed: RuntimeError: boom"]
    assert not (tmp_path / "o").exists()


def test_the_attack_tutorial_runs_as_written(tmp_path):
    """Its six commands, in order, at a tiny budget: two runs of 3,200 frames (TrojDRL and
    SleeperNets, seed 0; each stops at the update that passes the budget, 10 envs x 128 frames),
    their evaluations, and the near-trigger evaluation."""
    assert len(commands(ATTACKS)) == 8
    tiny_mitigation = ["--frames", "20000", "--episodes", "8", "--search-seconds", "5"]
    outputs = run_tutorial(ATTACKS, tmp_path, {"3000000": "3200", "200": "4", "50": "2", **SHIPPED}, {"train": TINY_RUN, "mitigate": tiny_mitigation})
    runs = tmp_path / "runs" / "attacks"
    for attack in ("trojdrl", "sleepernets"):
        metrics = json.loads((runs / attack / "metrics.json").read_text())
        assert metrics["attack"] == attack and 3200 <= metrics["frames"] < 3200 + 10 * 128 and metrics["attack_budget_used"]["frames_poisoned"] > 0
        assert (runs / attack / "clean_vs_triggered.gif").read_bytes()[:6] == b"GIF89a"
        assert (runs / attack / "training_curve.png").read_bytes()[:4] == b"\x89PNG"
    assert "trojdrl" in outputs[0] and "sleepernets" in outputs[0]  # the registry's listing
    assert "near" in outputs[3].lower()  # evaluate --near: the success under each near trigger
    mitigated = runs / "mitigated"  # step 5: a new model folder with its lineage, evaluated under the true trigger
    assert json.loads((mitigated / "mitigation.json").read_text())["source"]["folder"] == "id-00000000"
    assert "poisoned_sr" in outputs[7] and "multiplicative:17" in outputs[7]


@pytest.mark.slow
def test_the_attack_tutorial_runs_at_its_own_scale(tmp_path):
    """The same commands as written (a minute or two per training on one core)."""
    outputs = run_tutorial(ATTACKS, tmp_path, SHIPPED)
    for attack in ("trojdrl", "sleepernets"):
        assert json.loads((tmp_path / "runs" / "attacks" / attack / "metrics.json").read_text())["converged"] is True
    sr = float(re.search(r"poisoned_sr\s+([0-9.]+)", outputs[7]).group(1))
    assert sr <= 0.05, outputs[7]  # 0.030 measured (evaluate's seeds, 200 episodes; docs/tutorials/attacks.md)
