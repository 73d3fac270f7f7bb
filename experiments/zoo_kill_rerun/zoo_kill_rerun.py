"""Issue 15's measurement: a zoo run that is SIGKILLed at random moments and run again ends with
the same METADATA.csv and the same model.pt bytes as a run that was never killed.

    python experiments/zoo_kill_rerun/zoo_kill_rerun.py examples/zoo-lavaworld-40.toml --out runs/kill-rerun

1. plans the spec twice (``ref`` and ``killed``) and runs ``ref`` with ``zoo run --workers W``,
   untouched: its wall time, models per hour and yield are the zoo's measurement;
2. runs ``killed`` and, at moments drawn from ``--seed``, (a) SIGKILLs the coordinator's whole
   process group (coordinator and every worker at once, like the OOM killer or a power cut), runs
   it again, (b) SIGKILLs one training worker (the coordinator retries it), then (c) SIGKILLs the
   coordinator alone (its workers must notice and stop), then runs it again to the end;
3. compares METADATA.csv without its timing columns, every model.pt and clean-example-data
   sha256, and every folder's file list; writes ``OUT/result.json``.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import os
import platform
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

TIMING = ("wall_time", "fps", "versions")


def cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "rlbackdoors.zoo.cli", *args]


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def fingerprint(zoo: Path) -> dict:
    models = {}
    for folder in sorted((zoo / "models").iterdir()):
        files = sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file() and p.name != ".lock")
        hashes = {f: sha(folder / f) for f in files if f == "model.pt" or f.startswith("clean-example-data/")}
        models[folder.name] = {"files": files, "sha256": hashes}
    with open(zoo / "METADATA.csv", newline="") as f:
        rows = [{k: v for k, v in r.items() if not any(t in k for t in TIMING)} for r in csv.DictReader(f)]
    return {"models": models, "metadata": rows}


def job_pids(zoo: Path) -> list[int]:
    pids = []
    for proc in Path("/proc").iterdir():
        if proc.name.isdigit():
            try:
                cmd = (proc / "cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"rlbackdoors.zoo.job" in cmd and any(str(zoo).encode() in part for part in cmd):
                pids.append(int(proc.name))
    return sorted(pids)


def start(zoo: Path, workers: int, log) -> subprocess.Popen:
    # its own session: killing its process group must not kill this script
    return subprocess.Popen(cli("run", str(zoo), "--workers", str(workers), "--progress-interval", "60"), stdout=log, stderr=log, start_new_session=True)


def wait_or_kill(proc: subprocess.Popen, seconds: float) -> bool:
    """True if the run finished before ``seconds``."""
    try:
        proc.wait(timeout=seconds)
        return True
    except subprocess.TimeoutExpired:
        return False


def wait_gone(zoo: Path, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while job_pids(zoo) and time.monotonic() < deadline:
        time.sleep(0.5)
    if job_pids(zoo):
        raise SystemExit(f"jobs of {zoo} still alive {timeout:.0f} s after their coordinator died: {job_pids(zoo)}")


def machine() -> dict:
    cpu = next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")), platform.processor())
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(), "loadavg_at_start": os.getloadavg()}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("spec")
    ap.add_argument("--out", required=True)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=15)
    ap.add_argument("--first-kill", type=float, nargs=2, default=(300.0, 1200.0), help="range of seconds before the group kill")
    ap.add_argument("--second-kill", type=float, nargs=2, default=(120.0, 900.0), help="range of seconds before the worker + coordinator kills")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    t_group = float(rng.uniform(*args.first_kill))
    t_worker = float(rng.uniform(*args.second_kill))
    t_coord = t_worker + float(rng.uniform(30.0, 180.0))
    result: dict = {"spec": args.spec, "workers": args.workers, "machine": machine(), "kill_moments_s": [t_group, t_worker, t_coord]}
    ref, killed = out / "ref", out / "killed"
    for zoo in (ref, killed):
        if not zoo.exists():
            subprocess.run(cli("plan", args.spec, "--out", str(zoo)), check=True)

    if not (ref / "METADATA.csv").exists() or "ref_wall_s" not in _read(out):
        t0 = time.monotonic()
        with open(out / "ref.log", "a") as log:
            subprocess.run(cli("run", str(ref), "--workers", str(args.workers), "--progress-interval", "60", "--json"), stdout=log, stderr=log, check=True)
        _save(out, {"ref_wall_s": time.monotonic() - t0, "loadavg_after_ref": os.getloadavg()})
    result.update(_read(out))

    events = []
    with open(out / "killed.log", "a") as log:
        t0 = time.monotonic()
        proc = start(killed, args.workers, log)
        if not wait_or_kill(proc, t_group):
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            events.append(f"{time.monotonic() - t0:.0f} s: SIGKILL coordinator and workers (process group)")
        wait_gone(killed)
        proc = start(killed, args.workers, log)
        if not wait_or_kill(proc, t_worker):
            victims = job_pids(killed)
            if victims:
                os.kill(victims[int(rng.integers(len(victims)))], signal.SIGKILL)
                events.append(f"{time.monotonic() - t0:.0f} s: SIGKILL one worker")
            if not wait_or_kill(proc, t_coord - t_worker):
                proc.kill()
                proc.wait()
                events.append(f"{time.monotonic() - t0:.0f} s: SIGKILL coordinator alone")
                wait_gone(killed)
        if proc.poll() is None or events:
            proc = start(killed, args.workers, log)
            proc.wait()
        killed_wall = time.monotonic() - t0
    a, b = fingerprint(ref), fingerprint(killed)
    rows = a["metadata"]
    trained = [r for r in rows if r["status"] in ("done", "failed")]
    converged = [r for r in rows if r["converged"] == "True"]
    result.update(
        {
            "kills": events,
            "killed_wall_s": killed_wall,
            "models_trained": len(trained),
            "models_converged": len(converged),
            "yield": len(converged) / max(1, len(trained)),
            "models_per_hour": len(trained) / result["ref_wall_s"] * 3600,
            "same_metadata": a["metadata"] == b["metadata"],
            "same_model_hashes": {k: v["sha256"] for k, v in a["models"].items()} == {k: v["sha256"] for k, v in b["models"].items()},
            "same_files": {k: v["files"] for k, v in a["models"].items()} == {k: v["files"] for k, v in b["models"].items()},
            "model_folders": len(a["models"]),
            "model_pt_files": sum("model.pt" in v["sha256"] for v in a["models"].values()),
            "leftovers": [str(p) for p in killed.rglob("*") if p.suffix == ".rlbtmp" or p.name == "checkpoint.pt"],
            "loadavg_at_end": os.getloadavg(),
        }
    )
    (out / "result.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    ok = result["same_metadata"] and result["same_model_hashes"] and result["same_files"] and not result["leftovers"]
    return 0 if ok else 1


def _read(out: Path) -> dict:
    p = out / "ref.json"
    return json.loads(p.read_text()) if p.exists() else {}


def _save(out: Path, data: dict) -> None:
    (out / "ref.json").write_text(json.dumps({**_read(out), **data}, indent=2) + "\n")


if __name__ == "__main__":
    sys.exit(main())
