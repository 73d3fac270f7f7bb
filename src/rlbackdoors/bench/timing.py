"""The timing loop every single-env benchmark uses, so reference and subject are timed alike."""

from __future__ import annotations

import time
from typing import Callable


def steps_per_second(env, sample_action: Callable[[], object], seconds: float) -> tuple[float, int, float]:
    """Step ``env`` (already reset) with ``sample_action()`` for about ``seconds``, resetting on
    episode end; returns (steps/s, steps, elapsed). Closes the env. Actions are drawn inside the
    clock, in batches of 64 steps between clock reads."""
    steps = 0
    start = time.perf_counter()
    while True:
        for _ in range(64):
            _, _, terminated, truncated, _ = env.step(sample_action())
            if terminated or truncated:
                env.reset()
        steps += 64
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            env.close()
            return steps / elapsed, steps, elapsed
