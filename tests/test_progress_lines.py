"""Training progress (issue 32): off a terminal one plain line per evaluation (frames, frames/s,
SRs, time left), never tqdm's carriage-return redraws; on a terminal (a real pseudo-terminal
here) the bar as before."""

from __future__ import annotations

import csv
import fcntl
import json
import os
import struct
import subprocess
import sys
import termios
from pathlib import Path

from rlbackdoors.train.progress import Progress

CLI = [sys.executable, "-m", "rlbackdoors.cli"]


def test_training_piped_to_a_file_prints_one_plain_line_per_evaluation(tmp_path, tiny_run_dict):
    config = tmp_path / "config.json"
    config.write_text(json.dumps({**tiny_run_dict, "train": {**tiny_run_dict["train"], "video": False}}))
    log = tmp_path / "train.log"
    with open(log, "wb") as fh:
        proc = subprocess.run(
            [*CLI, "train", "--env", "lavaworld", "--config", config, "--out", tmp_path / "m"], stdout=fh, stderr=subprocess.STDOUT, timeout=600
        )
    assert proc.returncode == 0
    text = log.read_bytes().decode()
    assert "\r" not in text and "\x1b[" not in text  # no redraws, no cursor movement
    lines = [line for line in text.splitlines() if line.startswith("[fc poisoned] ")]
    with open(tmp_path / "m" / "log.csv", newline="") as fh:
        evaluations = list(csv.DictReader(fh))
    assert len(lines) == len(evaluations) == 2
    last = lines[-1]
    assert "3,200 / 3,200 frames (100%)" in last and "frames/s" in last and "clean SR" in last and "poisoned SR" in last and "left" in last
    assert f"clean SR {float(evaluations[-1]['clean_sr']):.2f}" in last


def test_a_terminal_gets_the_bar_and_a_file_plain_lines(tmp_path):
    main, child = os.openpty()
    fcntl.ioctl(child, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))  # a terminal 100 columns wide
    with open(child, "w", closefd=True) as terminal:
        bar = Progress(1000, 0, "fc clean", True, out=terminal)
        assert bar.bar is not None  # tqdm on a real (pseudo-)terminal
        bar.update(500)
        bar.evaluated(1234.0, 0.5, 0.25)
        bar.close()
    chunks = []
    while True:  # a pty hands its buffer over in pieces: read until the closed side says EIO
        try:
            data = os.read(main, 65536)
        except OSError:
            break
        if not data:
            break
        chunks.append(data)
    shown = b"".join(chunks).decode()
    os.close(main)
    assert "\r" in shown and "fc clean" in shown
    with open(tmp_path / "out.txt", "w") as fh:
        bar = Progress(1000, 0, "fc clean", True, out=fh)
        assert bar.bar is None
        bar.update(500)
        bar.evaluated(1234.0, 0.5, 0.25)
        bar.write("curriculum: switched")
        bar.close()
    lines = Path(tmp_path / "out.txt").read_text().splitlines()
    assert lines[0].startswith("[fc clean] 500 / 1,000 frames (50%), 1,234 frames/s: clean SR 0.50, poisoned SR 0.25; at most ")
    assert lines[1] == "curriculum: switched" and len(lines) == 2
    with open(tmp_path / "quiet.txt", "w") as fh:
        quiet = Progress(1000, 0, "fc clean", False, out=fh)
        quiet.evaluated(1.0, 0.5, 0.5)
        quiet.write("a notice")
    # no progress line when quiet; a notice (the curriculum switch) still shows, as tqdm.write did
    assert Path(tmp_path / "quiet.txt").read_text() == "a notice\n"
