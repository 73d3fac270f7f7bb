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


def finish(out: dict, runs: dict[str, list[dict]], load: tuple, ratio: tuple[str, float] | None, json_path: str | None) -> None:
    """Complete a result: whether every measurement scored the same numbers (``digest``), the
    reference's ratio ``(name, value)``, the machine and its load; print its gist, write it."""
    from rlbackdoors.bench.machine import machine_info

    if ratio is not None:
        out["same_numbers"] = len({r["digest"] for rs in runs.values() for r in rs}) == 1
        out[ratio[0]] = round(ratio[1], 3)
    out |= {"loadavg_before": [round(x, 2) for x in load], "loadavg_after": [round(x, 2) for x in os.getloadavg()], "machine": machine_info()}
    print(json.dumps({k: out[k] for k in ("best", "same_numbers", *(ratio[:1] if ratio else ())) if k in out}, indent=1))
    if json_path:
        Path(json_path).write_text(json.dumps(out, indent=2) + "\n")
