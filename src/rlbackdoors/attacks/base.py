"""The :class:`Attack` record, its parameters and the registry it lives in.

The world decides *what* the trigger is (an observation edit, a lava pattern, wall colours, a
cube formation); an attack decides *when and how* training data is poisoned: which collected
frames carry the trigger, how their rewards (and actions) are rewritten, and how evaluation
scores its success. Each attack is one module in this package that builds an :class:`Attack`
and registers it; config, training and evaluation ask the registry and name no attack.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from rlbackdoors.validate import ConfigError

_ATTACKS: dict[str, Attack] = {}

# How an attack's success is scored on triggered episodes (E-bar: the trigger in every frame):
# "outcome": ending in the world's trojan outcome (the paper's poisoned SR);
# "action": the rate of the target action over all triggered steps;
# "disrupt": not reaching the clean goal (an untargeted attack wants the task broken, nothing more).
SUCCESS_KINDS = ("outcome", "action", "disrupt")


@dataclass(frozen=True)
class Param:
    """One attack parameter: a number in ``[low, high]``, a flag, or one of ``choices``."""

    name: str
    default: Any
    low: float | None = None
    high: float | None = None
    integer: bool = False
    choices: tuple = ()
    help: str = ""

    def allowed(self) -> str:
        if self.choices:
            return ", ".join(map(str, self.choices))
        if isinstance(self.default, bool):
            return "true, false"
        return f"{'an integer' if self.integer else 'a number'} in [{self.low}, {self.high}]"

    def check(self, where: str, value):
        """The value as the config will hold it; ConfigError naming ``where`` and what is allowed."""
        bad = ConfigError(f"{where}={value!r} is not allowed (allowed: {self.allowed()})")
        if self.choices:
            if value not in self.choices:
                raise bad
            return value
        if isinstance(self.default, bool):
            if not isinstance(value, bool):
                raise bad
            return value
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise bad
        if self.integer and value != int(value):
            raise bad
        if not self.low <= value <= self.high:  # type: ignore[operator]
            raise bad
        return int(value) if self.integer else float(value)


@dataclass(frozen=True)
class Attack:
    """Everything about one poisoning method.

    ``schedule``: "episodes" poisons whole env copies (E-bar beside E, as the paper's mix does);
    "steps" stamps the trigger into a budgeted share of the frames collected from clean copies.
    ``poisoner``: (resolved params, the target test ``World.target_hits``) -> the per-run rule the
    collection seam calls (:class:`rlbackdoors.attacks.seam.Poisoner`); None: the world's E-bar copies as they are.
    ``unsupported``: (world, model arch, resolved params) -> why this attack cannot serve that
    run (one line), or None.
    """

    name: str
    title: str
    source: str  # the paper it follows
    schedule: str  # "episodes" or "steps"
    success: str | Callable[[dict], str]  # one of SUCCESS_KINDS, or params -> one of them
    params: tuple[Param, ...] = ()
    poisoner: Callable[[dict, Callable], Any] | None = None
    unsupported: Callable[[Any, str, dict], str | None] | None = None
    success_threshold: float | None = None  # None: the world's poisoned threshold
    algorithms: tuple[str, ...] = ("ppo",)
    doc: str = ""  # the docs page
    notes: dict = field(default_factory=dict)

    def resolve(self, params: dict | None, where: str = "poison.attack_params") -> dict:
        """``params`` checked and completed with the defaults, in declared order (what config.json holds)."""
        params = dict(params or {})
        known = {p.name: p for p in self.params}
        for key in params:
            if key not in known:
                allowed = ", ".join(known) or "none"
                raise ConfigError(f"{where}.{key} is not a parameter of attack {self.name!r} (allowed: {allowed})")
        return {p.name: p.check(f"{where}.{p.name}", params.get(p.name, p.default)) for p in self.params}

    def success_kind(self, params: dict) -> str:
        return self.success(params) if callable(self.success) else self.success

    def refuse(self, world, algorithm: str, arch: str, params: dict) -> str | None:
        """Why this attack cannot poison a run of ``world`` with ``arch``; None when it can."""
        if algorithm not in self.algorithms:
            return f"attack {self.name!r} is built for {', '.join(self.algorithms)} collection, not {algorithm} ({world.name} trains with {algorithm})"
        return self.unsupported(world, arch, params) if self.unsupported is not None else None


def describe(attack: Attack, worlds: list) -> dict:
    """What ``rlbackdoors attacks`` prints: the attack, its parameters, and per world either the
    architectures it serves (with its default parameters) or why it serves none."""
    params = attack.resolve({})
    served: dict[str, list[str] | str] = {}
    for world in worlds:
        archs = list(world.arch_names) or [world.algorithm]
        reasons = {arch: attack.refuse(world, world.algorithm, arch, params) for arch in archs}
        ok = [arch for arch, why in reasons.items() if why is None]
        served[world.name] = ok if ok else next(iter(reasons.values()))  # type: ignore[assignment]
    return {
        "name": attack.name,
        "title": attack.title,
        "source": attack.source,
        "schedule": attack.schedule,
        "success": attack.success_kind(params),
        "success_threshold": attack.success_threshold,
        "params": [{"name": p.name, "default": p.default, "allowed": p.allowed(), "help": p.help} for p in attack.params],
        "worlds": served,
        "doc": attack.doc,
    }


def register(attack: Attack) -> Attack:
    if attack.name in _ATTACKS:
        raise ValueError(f"attack {attack.name!r} is registered twice")
    if attack.schedule not in ("episodes", "steps"):
        raise ValueError(f"attack {attack.name!r}: schedule must be 'episodes' or 'steps'")
    _ATTACKS[attack.name] = attack
    return attack


def get(name: str) -> Attack:
    """The attack called ``name``; a ValueError lists the registered names."""
    try:
        return _ATTACKS[name]
    except (KeyError, TypeError):
        raise ValueError(f"attack {name!r} is not one of {', '.join(_ATTACKS)}") from None


def registered() -> list[Attack]:
    return list(_ATTACKS.values())


def names() -> tuple[str, ...]:
    return tuple(_ATTACKS)
