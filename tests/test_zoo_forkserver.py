"""The local back-end's fork server (rlbackdoors.zoo.forkserver): a job is a process of its own
whose exit code, signal, output and result come back as from a fresh ``python -m
rlbackdoors.zoo.job``. Zoo runs through it are tested in test_zoo.py (bytes equal to lone runs,
kill -9 of a job and of the coordinator)."""

from __future__ import annotations

import copy
import json
import os
import signal
import time
from pathlib import Path

from rlbackdoors.zoo import forkserver
from rlbackdoors.zoo.forkserver import JobProcess
from rlbackdoors.zoo.job import EXIT_INTERRUPTED, is_locked
from rlbackdoors.zoo.plan import plan
from rlbackdoors.zoo.spec import parse_spec
from test_zoo import NEVER, TINY


def _start(tmp_path, argv):
    log = os.open(tmp_path / "train.log", os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    read_fd, write_fd = os.pipe()
    try:
        proc = JobProcess(argv, log, write_fd, dict(os.environ))
    finally:
        os.close(write_fd)
        os.close(log)
    return proc, read_fd


def _result(read_fd) -> dict:
    with os.fdopen(read_fd, "rb") as fh:
        return json.loads(fh.read().decode())


def test_a_failing_job_gives_its_exit_code_result_and_log(tmp_path):
    missing = tmp_path / "zoo" / "models" / "id-00000000"
    proc, read_fd = _start(tmp_path, [str(missing)])
    assert proc.pid != os.getpid()
    assert proc.wait(timeout=60) == 1
    assert proc.poll() == 1
    result = _result(read_fd)
    assert result["status"] == "error"
    assert "Traceback" in (tmp_path / "train.log").read_text()  # the job's stderr went to its log


def _planned_folder(tmp_path) -> Path:
    """One LavaWorld FC model that trains 6 evaluations long (test_zoo's never-converging cell)."""
    spec = {
        "name": "fs",
        "seed": 5,
        "overrides": copy.deepcopy(TINY),
        "cells": [{"world": "lavaworld", "archs": ["fc"], "triggers": ["multiplicative"], "poisoned": 1, "max_attempts": 1, "overrides": NEVER}],
    }
    zoo = tmp_path / "fs"
    plan(parse_spec(spec), zoo)
    return next((zoo / "models").iterdir())


def _wait_until_training(folder: Path, proc: JobProcess) -> None:
    deadline = time.monotonic() + 120
    while not (folder / "checkpoint.pt").is_file():  # training under way, past its first update
        assert proc.poll() is None and time.monotonic() < deadline, "the job ended or never started training"
        time.sleep(0.02)


def test_sigterm_checkpoints_and_kill_9_reports_the_signal_as_popen_does(tmp_path):
    folder = _planned_folder(tmp_path)
    proc, read_fd = _start(tmp_path, [str(folder)])
    _wait_until_training(folder, proc)
    proc.send_signal(signal.SIGTERM)  # the job's own handler (not the server's): checkpoint and stop
    assert proc.wait(timeout=120) == EXIT_INTERRUPTED
    assert _result(read_fd)["status"] == "interrupted"
    assert (folder / "checkpoint.pt").is_file() and not (folder / "metrics.json").exists()
    proc, read_fd = _start(tmp_path, [str(folder)])  # resumes from the checkpoint
    deadline = time.monotonic() + 60
    while not is_locked(folder):  # the resumed run holds its folder
        assert proc.poll() is None and time.monotonic() < deadline
        time.sleep(0.01)
    proc.kill()
    assert proc.wait(timeout=30) == -signal.SIGKILL
    assert proc.poll() == -signal.SIGKILL
    assert os.read(read_fd, 1) == b""  # no result: killed
    os.close(read_fd)
    proc.send_signal(signal.SIGTERM)  # after the end: nothing is sent (the pid may be reused)


def test_jobs_share_one_server_and_a_dead_server_is_replaced(tmp_path):
    first, fd1 = _start(tmp_path, [str(tmp_path / "nothing")])
    server = forkserver._server
    assert server is not None and server.alive()
    assert first.wait(timeout=60) == 1
    second, fd2 = _start(tmp_path, [str(tmp_path / "nothing")])
    assert forkserver._server is server  # the same server forked both
    assert second.wait(timeout=60) == 1
    server.proc.kill()
    server.proc.wait()
    third, fd3 = _start(tmp_path, [str(tmp_path / "nothing")])
    assert forkserver._server is not server and forkserver._server.alive()
    assert third.wait(timeout=60) == 1
    for fd in (fd1, fd2, fd3):
        assert _result(fd)["status"] == "error"


def test_the_server_exits_when_its_coordinator_closes_the_socket():
    server = forkserver._Server()
    try:
        server.sock.close()
        deadline = time.monotonic() + 60
        while server.alive() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not server.alive()
        assert server.proc.returncode == 0
    finally:
        if server.alive():
            server.proc.kill()


def test_a_job_runs_in_the_coordinators_directory_of_the_moment(tmp_path, monkeypatch):
    """The server keeps the directory it was started in; a job gets its coordinator's current one,
    so a relative folder means what it means to the coordinator (the tutorials run zoos so)."""
    (tmp_path / "first").mkdir()
    monkeypatch.chdir(tmp_path / "first")
    first, fd = _start(tmp_path, ["nothing"])  # starts (or reuses) the server; fails fast
    assert first.wait(timeout=60) == 1
    os.close(fd)
    folder = _planned_folder(tmp_path)  # tmp_path/fs/models/id-...
    monkeypatch.chdir(tmp_path)
    proc, read_fd = _start(tmp_path, [str(folder.relative_to(tmp_path))])
    assert proc.wait(timeout=300) == 0
    assert _result(read_fd)["status"] == "done" and (folder / "reduced-config.json").is_file()
