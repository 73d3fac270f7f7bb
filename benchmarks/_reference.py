"""Measuring this checkout against another in the same run (``--reference SRC``): each measurement
a fresh process of the calling script (``--one``, one JSON line on stdout), the sides taken in
turn so that a change of the machine's load hits both."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path


def sides(reference: str | None) -> dict[str, str]:
    """Side name -> the ``src/`` it imports: this checkout, and the reference if given."""
    here = str(Path(__file__).resolve().parents[1] / "src")
    return {"this checkout": here} | ({"reference": str(Path(reference).resolve())} if reference else {})


def alternate(script: str, what: list[str], reference: str | None, repeats: int) -> dict[str, list[dict]]:
    """``repeats`` measurements per side of ``script --one *what``, alternately: side -> results."""
    runs: dict[str, list[dict]] = {name: [] for name in sides(reference)}
    for _ in range(repeats):
        for name, src in sides(reference).items():
            env = {**os.environ, "PYTHONPATH": src + os.pathsep + os.environ.get("PYTHONPATH", "")}
            done = subprocess.run([sys.executable, script, "--one", *what], env=env, check=True, capture_output=True, text=True)
            runs[name].append(json.loads(done.stdout.splitlines()[-1]))
    return runs
