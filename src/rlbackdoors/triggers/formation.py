"""The in-distribution trigger of Modified Safety Gymnasium: two teal cubes in formation (SPEC §4).

Two cubes are held at the same distance ``d`` from the car, at angles ``phi1`` and
``phi2 = phi1 + eta`` measured counter-clockwise from the car's heading, for the whole
episode (paper §3.4: they "maintain a distance d from the agent at angle phi"). Because
the lidar is egocentric, the formation shows up as near-constant values in the same cube
lidar bins at every step, while every single frame stays a frame a clean episode could show.

The trigger is plain data, like :class:`~rlbackdoors.triggers.observation.ObservationTrigger`:
the env (``rlbackdoors.envs.safety_car``) does the kinematic re-placement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

KIND = "formation"
DEFAULT_DISTANCE = 0.5
# Below this a cube (half-size 0.1) overlaps the car's wheels; beyond the lidar range (3)
# the trigger is invisible to the agent.
DISTANCE_RANGE = (0.4, 3.0)
ETA_RANGE = (math.pi / 6, 11 * math.pi / 6)  # keeps the two cubes at least 30 degrees apart
TWO_PI = 2 * math.pi


def _is_real(value) -> bool:
    return not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating)) and math.isfinite(value)


@dataclass(frozen=True)
class FormationTrigger:
    """Two cubes at distance ``distance`` and angles ``phi1``, ``phi1 + eta`` from the heading (radians)."""

    distance: float = DEFAULT_DISTANCE
    phi1: float = 0.0
    eta: float = math.pi

    def __post_init__(self) -> None:
        for name in ("distance", "phi1", "eta"):
            value = getattr(self, name)
            if not _is_real(value):
                raise ValueError(f"formation trigger {name}={value!r} must be a finite number")
            object.__setattr__(self, name, float(value))
        low, high = DISTANCE_RANGE
        if not low <= self.distance <= high:
            raise ValueError(f"formation trigger distance={self.distance!r} must be in [{low}, {high}] (paper: 0.5)")
        if not 0.0 <= self.phi1 < TWO_PI:
            raise ValueError(f"formation trigger phi1={self.phi1!r} must be in [0, 2*pi)")
        low, high = ETA_RANGE
        if not low <= self.eta <= high:
            raise ValueError(f"formation trigger eta={self.eta!r} must be in [pi/6, 11*pi/6]")

    @property
    def phi2(self) -> float:
        return (self.phi1 + self.eta) % TWO_PI

    @property
    def angles(self) -> tuple[float, float]:
        return self.phi1, self.phi2

    def offsets(self, heading: float) -> np.ndarray:
        """World-frame (2, 2) offsets of the two trigger cubes from the car centre."""
        world = heading + np.array(self.angles)
        return self.distance * np.stack([np.cos(world), np.sin(world)], axis=1)

    def matches(self, dist, angle, tol_distance: float = 0.1, tol_angle: float = 0.2) -> bool:
        """Whether some ordered pair of cubes sits in the formation, within the tolerances.

        ``dist`` and ``angle`` are each cube's distance and angle in the car frame (angle
        counter-clockwise from the heading). Used to measure how often the formation
        happens by chance in clean episodes.
        """
        dist, angle = np.asarray(dist, dtype=float), np.asarray(angle, dtype=float)
        near = np.abs(dist - self.distance) < tol_distance
        at = [near & (np.abs(_wrap(angle - phi)) < tol_angle) for phi in self.angles]
        first, second = np.flatnonzero(at[0]), np.flatnonzero(at[1])
        return any(i != j for i in first for j in second)

    def spec(self) -> str:
        return f"{KIND}:{self.distance!r}:{self.phi1!r}:{self.eta!r}"

    @classmethod
    def parse(cls, text: str) -> "FormationTrigger":
        """Parse ``formation:D:PHI1:ETA`` (radians), the form :meth:`spec` writes."""
        parts = str(text).split(":")
        if len(parts) != 4 or parts[0] != KIND:
            raise ValueError(f"trigger {text!r} must look like 'formation:DISTANCE:PHI1:ETA' (radians)")
        values = []
        for name, value in zip(("distance", "phi1", "eta"), parts[1:]):
            try:
                values.append(float(value))
            except ValueError:
                raise ValueError(f"trigger {text!r}: {name} {value!r} is not a number") from None
        return cls(*values)

    @classmethod
    def sample(cls, seed: int | np.random.Generator | None, distance: float = DEFAULT_DISTANCE) -> "FormationTrigger":
        """One agent's trigger: phi1 uniform in [0, 2*pi), eta uniform in [pi/6, 11*pi/6]."""
        rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
        phi1 = float(rng.uniform(0.0, TWO_PI)) % TWO_PI
        return cls(distance, phi1, float(rng.uniform(*ETA_RANGE)))


def as_formation(trigger: FormationTrigger | str | None) -> FormationTrigger | None:
    """Accept a trigger object or its spec string (what ``gym.make`` kwargs carry)."""
    if trigger is None or isinstance(trigger, FormationTrigger):
        return trigger
    return FormationTrigger.parse(trigger)


def _wrap(angle):
    """Angle difference folded into [-pi, pi)."""
    return (np.asarray(angle) + math.pi) % TWO_PI - math.pi


NEAR_ANGLES = (0.6, 1.2)  # radians a near formation's phi1 or eta lies from the trigger's (the matching tolerance is 0.2)
NEAR_DISTANCES = (0.3, 0.6)  # and its distance


def near_formations(trigger: FormationTrigger) -> list[FormationTrigger]:
    """Formations near ``trigger`` (poison.evasion.near): the same cubes at other angles (phi1 or
    eta +-0.6, +-1.2 rad) and other distances (+-0.3, +-0.6, within the allowed range), none of
    which the trigger's own tolerances would match."""
    out = []
    for step in NEAR_ANGLES:
        for sign in (-1, 1):
            out.append(FormationTrigger(trigger.distance, (trigger.phi1 + sign * step) % TWO_PI, trigger.eta))
            eta = trigger.eta + sign * step
            if ETA_RANGE[0] <= eta <= ETA_RANGE[1]:
                out.append(FormationTrigger(trigger.distance, trigger.phi1, eta))
    for step in NEAR_DISTANCES:
        for sign in (-1, 1):
            distance = trigger.distance + sign * step
            if DISTANCE_RANGE[0] <= distance <= DISTANCE_RANGE[1]:
                out.append(FormationTrigger(distance, trigger.phi1, trigger.eta))
    return out
