"""Stopping a run cleanly: Ctrl-C or SIGTERM (a cluster pre-empting a job) asks the run to stop at
the end of the current step, where its state is consistent, write a checkpoint and exit.

A second Ctrl-C stops at once (the last checkpoint stands). Signal handlers can only be set
from the main thread; elsewhere (a worker thread) nothing is installed and the run stops
only when its process ends.
"""

from __future__ import annotations

import signal
import threading


class Interrupted(KeyboardInterrupt):
    """The run stopped on a signal; ``checkpoint`` says whether it wrote one to resume from."""

    def __init__(self, frames: int, checkpoint: bool, signame: str = "SIGINT"):
        self.frames, self.checkpoint, self.signame = frames, checkpoint, signame
        done = f"checkpoint written at {frames:,} frames" if checkpoint else "no checkpoint written (the last one stands)"
        super().__init__(f"stopped by {signame}: {done}; run the same command again to resume")


class StopRequest:
    """``with StopRequest() as stop:`` ... ``if stop.requested: checkpoint and raise``."""

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.requested: str | None = None
        self._old: dict = {}

    def _handle(self, signum, frame) -> None:
        if self.requested is not None and signum == signal.SIGINT:
            raise KeyboardInterrupt  # the second Ctrl-C: stop now
        self.requested = signal.Signals(signum).name

    def __enter__(self) -> StopRequest:
        if threading.current_thread() is threading.main_thread():
            for sig in self.SIGNALS:
                self._old[sig] = signal.signal(sig, self._handle)
        return self

    def __exit__(self, *exc) -> None:
        for sig, old in self._old.items():
            signal.signal(sig, old)
        self._old = {}
