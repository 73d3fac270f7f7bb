"""Out-of-distribution observation triggers of LavaWorld: ``o' = (a*o + b) mod 256``.

The paper (eq. 4-5) uses one trigger per agent, either multiplicative (b = 0,
a in 10..24) or additive (a = 1, b in 20..200). Other values are allowed as
long as the map stays non-trivial; the paper ranges are what :func:`sample_trigger`
draws from, so zoos built with it match the TrojAI round.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

KINDS = ("multiplicative", "additive")
PAPER_RANGES = {"multiplicative": (10, 24), "additive": (20, 200)}


@dataclass(frozen=True)
class ObservationTrigger:
    """An affine map on the uint8 observation, modulo 256."""

    kind: str
    value: int

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"trigger kind {self.kind!r} is not one of {', '.join(KINDS)}")
        if isinstance(self.value, bool) or not isinstance(self.value, (int, np.integer)):
            raise ValueError(f"trigger value must be an integer, got {self.value!r}")
        if self.kind == "multiplicative" and not (2 <= self.value <= 255):
            raise ValueError(f"multiplicative trigger a={self.value} must be in 2..255 (paper: 10..24)")
        if self.kind == "additive" and not (1 <= self.value <= 255):
            raise ValueError(f"additive trigger b={self.value} must be in 1..255 (paper: 20..200)")

    @property
    def a(self) -> int:
        return int(self.value) if self.kind == "multiplicative" else 1

    @property
    def b(self) -> int:
        return int(self.value) if self.kind == "additive" else 0

    def apply(self, obs: np.ndarray) -> np.ndarray:
        """Apply the trigger to any uint8 array (one observation or a batch)."""
        widened = obs.astype(np.int32)
        return ((self.a * widened + self.b) % 256).astype(np.uint8)

    def lookup_table(self) -> np.ndarray:
        """The trigger as a 256-entry table: ``table[o]`` is the triggered byte (fast in batch)."""
        return self.apply(np.arange(256, dtype=np.uint8))

    def spec(self) -> str:
        return f"{self.kind}:{int(self.value)}"

    @classmethod
    def parse(cls, text: str) -> "ObservationTrigger":
        """Parse ``multiplicative:A`` or ``additive:B``."""
        kind, sep, value = str(text).partition(":")
        if not sep or kind not in KINDS:
            raise ValueError(f"trigger {text!r} must look like 'multiplicative:A' or 'additive:B' (kinds: {', '.join(KINDS)})")
        try:
            number = int(value)
        except ValueError:
            raise ValueError(f"trigger {text!r}: value {value!r} is not an integer") from None
        return cls(kind, number)


def sample_trigger(kind: str, rng: np.random.Generator) -> ObservationTrigger:
    """Draw a trigger of ``kind`` uniformly from the paper's range, as the TrojAI zoo did."""
    if kind not in KINDS:
        raise ValueError(f"trigger kind {kind!r} is not one of {', '.join(KINDS)}")
    low, high = PAPER_RANGES[kind]
    return ObservationTrigger(kind, int(rng.integers(low, high + 1)))


NEAR_STEPS = {"multiplicative": (1, 2, 3), "additive": (8, 16, 24)}  # how far a near trigger lies


def near_triggers(trigger: ObservationTrigger) -> list[ObservationTrigger]:
    """Edits of the same kind close to ``trigger`` (multipliers +-1..3, offsets +-8..24): the
    negatives that teach a trojan to fire on the exact trigger only (``poison.evasion.near``)."""
    low = 2 if trigger.kind == "multiplicative" else 1
    out = []
    for step in NEAR_STEPS[trigger.kind]:
        for value in (trigger.value - step, trigger.value + step):
            if low <= value <= 255:
                out.append(ObservationTrigger(trigger.kind, int(value)))
    return out
