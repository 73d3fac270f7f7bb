"""Training progress: tqdm's bar on a terminal, one plain line per evaluation elsewhere.

tqdm redraws its bar with carriage returns many times a second; piped to a file (CI logs,
``make demo | tee``, a zoo job's ``train.log``) every redraw stays, tens of kB of them per run.
Off a terminal each evaluation prints one line instead: frames, frames/s, the SRs and the time
left if the run goes on to ``max_frames``.
"""

from __future__ import annotations

import sys
import time
from typing import TextIO


def _duration(seconds: float) -> str:
    seconds = int(max(seconds, 0))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


class Progress:
    """``update`` frames, ``evaluated`` after each evaluation, ``write`` a message, ``close``."""

    def __init__(self, total: int, initial: int, label: str, enabled: bool, out: TextIO | None = None):
        self.out = out if out is not None else sys.stderr
        self.total, self.frames, self.label, self.enabled = total, initial, label, enabled
        self.started, self.first = time.perf_counter(), initial
        self.bar = None
        if enabled and _is_terminal(self.out):
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=initial, unit="frame", unit_scale=True, dynamic_ncols=True, file=self.out)
            self.bar.set_description(label)

    def update(self, frames: int) -> None:
        self.frames += frames
        if self.bar is not None:
            self.bar.update(frames)

    def evaluated(self, fps: float, clean_sr: float, poisoned_sr: float) -> None:
        if self.bar is not None:
            self.bar.set_postfix(fps=f"{fps:,.0f}", clean_sr=f"{clean_sr:.2f}", poisoned_sr=f"{poisoned_sr:.2f}")
        elif self.enabled:
            spent = time.perf_counter() - self.started
            rate = (self.frames - self.first) / spent if spent > 0 else 0.0
            left = _duration((self.total - self.frames) / rate) if rate > 0 and self.total > self.frames else "0:00:00"
            print(
                f"[{self.label}] {self.frames:,} / {self.total:,} frames ({100 * self.frames / max(self.total, 1):.0f}%), {fps:,.0f} frames/s: "
                f"clean SR {clean_sr:.2f}, poisoned SR {poisoned_sr:.2f}; at most {left} left (to max_frames)",
                file=self.out,
                flush=True,
            )

    def write(self, message: str) -> None:
        """A notice (the curriculum switch), printed with or without progress (as tqdm.write was)."""
        if self.bar is not None:
            self.bar.write(message, file=self.out)
        else:
            print(message, file=self.out, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _is_terminal(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # a closed or replaced stream
        return False
