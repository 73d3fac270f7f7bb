"""The ``rlbackdoors`` command as the detector benchmark scripts call it: one place for the
subprocess, its one-thread environment and the rule for when a score is read back."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path


class Refused(Exception):
    """The command refused its input in one ``rlbackdoors: error: ...`` line (exit status 2): a
    detector asked to fit what it was not built for, say. The line is the message."""


def rlbackdoors(*args: str, quiet: bool = False) -> None:
    """Run the console script beside this interpreter with one BLAS thread (a score's seconds
    per model are then one core's, as the brief asks). Its stderr is passed through as it comes;
    a refusal raises :class:`Refused` with its line, any other failure ``CalledProcessError``."""
    cmd = [str(Path(sys.executable).parent / "rlbackdoors"), *args]
    if not quiet:
        print("+", " ".join(cmd), file=sys.stderr, flush=True)
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL if quiet else None, stderr=subprocess.PIPE, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.stderr is not None
    refusal = ""
    for line in proc.stderr:
        sys.stderr.write(line)
        sys.stderr.flush()
        if line.startswith("rlbackdoors: error:"):
            refusal = line.strip()
    if proc.wait():
        if proc.returncode == 2 and refusal:
            raise Refused(refusal)
        raise subprocess.CalledProcessError(proc.returncode, cmd)


def score(det: Path, zoo: Path | str, out: Path, *, again: bool = False, quiet: bool = False) -> dict:
    """``detect score`` of the fitted detector ``det`` on ``zoo`` into ``out``, read back as
    ``score.json``. It runs when the score is missing or older than the fit, or always with
    ``again`` (a zoo that may have gained models; ``detect score`` resumes, so only those are
    scored)."""
    scored = out / "score.json"
    if again or not scored.is_file() or scored.stat().st_mtime < (det / "detector.json").stat().st_mtime:
        rlbackdoors("detect", "score", str(det), "--zoo", str(zoo), "--out", str(out), "--quiet", quiet=quiet)
    return json.loads(scored.read_text())


def infer(det: Path, folder: Path, out: Path, round_dir: Path, examples: Path | None = None) -> float:
    """``detect infer`` (TrojAI's one-model entry point) of the fitted detector ``det`` on
    ``folder/model.pt``, its files under ``out``; the probability it wrote."""
    rlbackdoors(
        "detect", "infer", "--model_filepath", str(folder / "model.pt"), "--result_filepath", str(out / "result.txt"),
        "--scratch_dirpath", str(out / "scratch"), *(("--examples_dirpath", str(examples)) if examples else ()),
        "--round_training_dataset_dirpath", str(round_dir), "--metaparameters_filepath", str(det / "metaparameters.json"),
        "--schema_filepath", str(det / "metaparameters_schema.json"), "--learned_parameters_dirpath", str(det), quiet=True,
    )  # fmt: skip
    return float((out / "result.txt").read_text())
