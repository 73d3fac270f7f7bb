"""The zoo spec: which worlds, architectures and trigger families, how many converged models of
each ground-truth label, the budgets, and the master seed every model is drawn from.

Read from TOML (stdlib ``tomllib``) and validated here, at the edge: every problem is one
:class:`~rlbackdoors.validate.ConfigError` naming the dotted field and what is allowed, before
anything is written. World names, architectures and trigger drawing come from the World
registry, so a new world needs no change here.

A spec entry (``[[cells]]``) expands into cells = its archs x its trigger families x its attacks
(``attacks = ["NAME", {attack = "NAME", name = "LABEL", params = {budget = 0.05}, evasion = {finetune = true}}]``, names from the attack registry;
default: the paper's env mix alone); each cell
holds two *groups* (clean, poisoned), the unit the runner tops up: a group wants ``clean`` or
``poisoned`` converged models and trains at most ``max_attempts`` of them.
"""

from __future__ import annotations

import copy
import math
import string
import tomllib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np

from rlbackdoors import attacks, worlds
from rlbackdoors.validate import MAX_EPISODES, ConfigError, check_seed

SPEC_FORMAT = 1
# Model ids are 8 digits; the id space of a zoo is the sum of its groups' max_attempts.
MAX_ID_SPACE = 10_000_000
MAX_ATTEMPTS = 100_000
# Fields each model's config gets from the zoo itself; an override may not set them.
ZOO_FIELDS = ("env.name", "model.arch", "poison.poisoned", "poison.trigger", "train.seed")
TOP_KEYS = ("format", "name", "seed", "max_attempts", "matched", "examples", "overrides", "cells")
CELL_KEYS = (
    "world",
    "archs",
    "triggers",
    "attacks",
    "models",
    "poisoned_share",
    "clean",
    "poisoned",
    "max_attempts",
    "overrides",
    "ranges",
    "clean_ranges",
    "block",
)
ATTACK_KEYS = ("attack", "name", "params", "ranges", "evasion")
FAMILY_KEYS = ("name", "trigger", "template", "ranges")
EXAMPLE_KEYS = ("episodes", "seed", "policy")
EXAMPLE_POLICIES = ("sample", "greedy")
DRAWN = "drawn"  # the family name of "no trigger given: the world draws one from the seed"
EVASION = "evasion."  # an attack's ranges key that draws an evasive variant's knob


class ZooError(ValueError):
    """A zoo folder cannot be used as asked (not a zoo, planned from another spec, in use, ...).

    A ValueError, so the CLI reports it as one ``rlbackdoors: error: ...`` line; the zoo's
    modules import no training code until a job runs.
    """


def _type(where: str, value, kind, what: str):
    if kind is int and (isinstance(value, bool) or not isinstance(value, int)):
        raise ConfigError(f"{where} must be {what}, got {value!r}")
    if kind is not int and not isinstance(value, kind):
        raise ConfigError(f"{where} must be {what}, got {value!r}")
    return value


def _keys(where: str, data: dict, allowed: tuple[str, ...]) -> None:
    unknown = sorted(set(data) - set(allowed))
    if unknown:
        raise ConfigError(f"{where}{'.' if where else ''}{unknown[0]} is not a spec field (allowed{' in ' + where if where else ''}: {', '.join(allowed)})")


def _int(where: str, value, low: int, high: int) -> int:
    _type(where, value, int, f"an integer in {low}..{high:,}")
    if not low <= value <= high:
        raise ConfigError(f"{where} must be in {low}..{high:,}, got {value!r}")
    return value


def deep_merge(base: dict, top: dict) -> dict:
    """``top`` over ``base``, tables merged key by key (copies: neither input changes)."""
    out = copy.deepcopy(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def flatten(data: dict, prefix: str = "") -> dict[str, Any]:
    """``{"train": {"seed": 1}}`` -> ``{"train.seed": 1}`` (what METADATA.csv's columns are named)."""
    out: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict) and value:
            out.update(flatten(value, name + "."))
        else:
            out[name] = value
    return out


def _check_overrides(where: str, data) -> dict:
    if not isinstance(data, dict):
        raise ConfigError(f"{where} must be a table of config sections (e.g. [overrides.train]), got {data!r}")
    for section, values in data.items():
        if not isinstance(values, dict):
            raise ConfigError(f"{where}.{section} must be a table of config fields, got {values!r}")
    for dotted in flatten(data):
        if dotted in ZOO_FIELDS:
            raise ConfigError(f"{where}.{dotted} is set by the zoo for every model (the zoo sets: {', '.join(ZOO_FIELDS)}); remove it")
    return data


@dataclass(frozen=True)
class TriggerFamily:
    """How a cell's triggers are drawn: by the world (``trigger`` None or a bare kind), fixed
    (an exact trigger), or from a ``template`` whose ``{placeholders}`` are drawn uniformly from
    ``ranges`` (integers where both bounds are integers) and then read by the world."""

    name: str
    trigger: str | None = None
    template: str | None = None
    ranges: tuple[tuple[str, float | int, float | int], ...] = ()

    def draw(self, world: worlds.World, rng: np.random.Generator, size: int | None) -> str:
        """The trigger string of one model; ``rng`` is the model's own generator."""
        seed = int(rng.integers(0, 2**31))
        if self.template is None:
            return world.draw_trigger(self.trigger, seed, size)
        values: dict[str, float | int] = {}
        for name, low, high in self.ranges:
            if isinstance(low, int) and isinstance(high, int):
                values[name] = int(rng.integers(low, high + 1))
            else:
                values[name] = float(rng.uniform(low, high))
        return world.draw_trigger(self.template.format(**values), seed, size)

    def to_dict(self) -> dict:
        out: dict[str, Any] = {"name": self.name}
        if self.template is not None:
            out["template"] = self.template
            out["ranges"] = {name: [low, high] for name, low, high in self.ranges}
        elif self.trigger is not None:
            out["trigger"] = self.trigger
        return out


Value = bool | int | float | str


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class Draw:
    """One setting drawn per model, as a TrojAI round draws it: uniform in ``[low, high]``
    (integers where both bounds are), or ``{ one_of = [...] }``: one of its options, uniformly,
    each a value (a number, a boolean, a string) or a ``[low, high]`` range drawn in turn, e.g.
    ``{ one_of = [0, [1_500_000, 4_000_000]] }``: half the models 0, half a length drawn from the range."""

    options: tuple[tuple, ...]  # ("range", low, high) or ("value", v)
    one_of: bool = False

    def sample(self, rng: np.random.Generator) -> Value:
        # a bare range draws exactly as ranges always drew (one number), so older specs keep their bytes
        option = self.options[int(rng.integers(len(self.options)))] if self.one_of else self.options[0]
        if option[0] == "value":
            return option[1]
        _, low, high = option
        if isinstance(low, int) and isinstance(high, int):
            return int(rng.integers(low, high + 1))
        return float(rng.uniform(low, high))

    def corners(self) -> list[Value]:
        """Every value a check must accept: each option's value, or its range's two ends."""
        return [x for o in self.options for x in ((o[1],) if o[0] == "value" else o[1:])]

    def to_data(self):
        def one(o):
            return o[1] if o[0] == "value" else [o[1], o[2]]

        return {"one_of": [one(o) for o in self.options]} if self.one_of else one(self.options[0])


def _parse_range(where: str, bounds) -> tuple:
    if not (isinstance(bounds, list) and len(bounds) == 2 and all(_number(b) for b in bounds)) or bounds[0] > bounds[1]:
        raise ConfigError(f"{where} must be [low, high] with low <= high, got {bounds!r}")
    return ("range", bounds[0], bounds[1])


def parse_draw(where: str, raw) -> Draw:
    """A :class:`Draw` from ``[low, high]`` or ``{ one_of = [value or [low, high], ...] }``."""
    if isinstance(raw, dict):
        if set(raw) != {"one_of"} or not isinstance(raw["one_of"], list) or not raw["one_of"]:
            raise ConfigError(f"{where} must be [low, high] or {{ one_of = [values or [low, high] ranges] }}, got {raw!r}")
        options = []
        for j, item in enumerate(raw["one_of"]):
            if isinstance(item, list):
                options.append(_parse_range(f"{where}.one_of[{j}]", item))
            elif isinstance(item, (bool, str)) or _number(item):
                options.append(("value", item))
            else:
                raise ConfigError(f"{where}.one_of[{j}] must be a number, a boolean, a string or [low, high], got {item!r}")
        return Draw(tuple(options), one_of=True)
    return Draw((_parse_range(where, raw),))


def draw_all(ranges: tuple[tuple[str, Draw], ...], rng: np.random.Generator, written: bool = False) -> dict:
    """One model's values of ``ranges``, drawn in name order (as a trigger's placeholders are): the
    order a spec writes them in (TOML's as written, zoo.json's sorted) must not change a draw.
    ``written``: in the spec's order instead, as ``zoo plan`` drew a first attempt before 2026-12-08
    (its top-ups, from zoo.json, were drawn sorted): what a planned folder is checked against too."""
    return {name: draw.sample(rng) for name, draw in (ranges if written else sorted(ranges, key=lambda r: r[0]))}


@dataclass(frozen=True)
class AttackChoice:
    """How a cell's poisoned models are poisoned: an attack of the registry and its parameters
    (the attack's defaults for those not given). Its clean models are trained clean, as always."""

    name: str  # the label in cell keys and reports
    attack: str = attacks.DEFAULT_ATTACK
    params: dict = field(default_factory=dict, hash=False, compare=False)
    # (parameter, Draw): drawn per model after its trigger; ``evasion.KNOB`` draws an evasive variant's knob
    ranges: tuple[tuple[str, Draw], ...] = ()
    # evasive variants of its poisoned models (poison.evasion; rlbackdoors.attacks.evasion)
    evasion: dict = field(default_factory=dict, hash=False, compare=False)

    @property
    def is_default(self) -> bool:
        return self.attack == attacks.DEFAULT_ATTACK and not self.params and not self.ranges and not self.evasion

    def overrides(self) -> dict:
        if self.is_default:
            return {}
        return {"poison": {"attack": self.attack, "attack_params": dict(self.params), **({"evasion": dict(self.evasion)} if self.evasion else {})}}

    def draw(self, rng: np.random.Generator, written: bool = False) -> dict:
        """The poison overrides drawn for one model (after its trigger, from the model's own
        generator): ``attack_params`` and, for ``evasion.*`` keys, ``evasion`` on top of the cell's
        (``written``: :func:`draw_all`)."""
        drawn = draw_all(self.ranges, rng, written)
        out: dict[str, dict] = {"attack_params": {k: v for k, v in drawn.items() if not k.startswith(EVASION)}}
        knobs = {k[len(EVASION) :]: v for k, v in drawn.items() if k.startswith(EVASION)}
        if knobs:
            from rlbackdoors.attacks import evasion

            out["evasion"] = evasion.resolve({**self.evasion, **knobs})
        return out

    def to_dict(self) -> dict:
        out: dict[str, Any] = {"attack": self.attack, "name": self.name, "params": dict(self.params)}
        if self.ranges:
            out["ranges"] = {name: draw.to_data() for name, draw in self.ranges}
        if self.evasion:
            out["evasion"] = dict(self.evasion)
        return out


DEFAULT_CHOICE = AttackChoice(attacks.DEFAULT_ATTACK)


def _parse_attack(where: str, raw) -> AttackChoice:
    if isinstance(raw, str):
        raw = {"attack": raw}
    if not isinstance(raw, dict):
        raise ConfigError(f"{where} must be an attack name or a table (attack, name, params), got {raw!r}")
    _keys(where, raw, ATTACK_KEYS)
    name = raw.get("attack")
    if name not in attacks.names():
        raise ConfigError(f"{where}.attack={name!r} is not allowed (allowed: {', '.join(attacks.names())})")
    params = raw.get("params", {})
    if not isinstance(params, dict):
        raise ConfigError(f"{where}.params must be a table of the attack's parameters, got {params!r}")
    attack = attacks.get(name)
    attack.resolve(params, f"{where}.params")
    raw_ranges = raw.get("ranges", {})
    if not isinstance(raw_ranges, dict):
        raise ConfigError(f"{where}.ranges must be a table of parameter = [low, high] or {{ one_of = [...] }}, got {raw_ranges!r}")
    from rlbackdoors.attacks import evasion

    fixed_evasion = raw.get("evasion")
    ranges = []
    for key, bounds in raw_ranges.items():
        draw = parse_draw(f"{where}.ranges.{key}", bounds)
        if key.startswith(EVASION):  # an evasive variant's knob: every value must be one the variants accept
            knob = key[len(EVASION) :]
            if isinstance(fixed_evasion, dict) and knob in fixed_evasion:
                raise ConfigError(f"{where}.ranges.{key}: {knob} is also fixed in evasion (give it in one of them)")
            for value in draw.corners():
                evasion.resolve({**(fixed_evasion or {}), knob: value}, f"{where}.ranges.evasion")
        else:
            if key in params:
                raise ConfigError(f"{where}.ranges.{key}: {key} is also fixed in params (give it in one of them)")
            for value in draw.corners():  # every end and option must be a value the attack accepts
                attack.resolve({**params, key: value}, f"{where}.ranges")
        ranges.append((key, draw))
    label = _type(f"{where}.name", raw.get("name", name), str, "a string")

    variants = evasion.resolve(fixed_evasion, f"{where}.evasion")
    # a drawn knob is the ranges' alone (resolve fills in every knob's default), so the normal form reads back
    variants = {k: v for k, v in variants.items() if EVASION + k not in raw_ranges}
    return AttackChoice(label, name, dict(params), tuple(ranges), variants)


@dataclass(frozen=True)
class Cell:
    """One world x architecture x trigger family x attack, and what it wants."""

    entry: int  # index of its [[cells]] entry
    world: str
    arch: str | None  # None: the world has no named architectures (its network is set in overrides)
    trigger: TriggerFamily
    clean: int  # converged clean models wanted
    poisoned: int  # converged poisoned models wanted
    max_attempts: int  # per label
    overrides: dict = field(hash=False, compare=False)
    attack: AttackChoice = DEFAULT_CHOICE
    # (dotted config field, Draw): drawn per model of both labels after the attack's ranges, so
    # a round's clean and poisoned models share e.g. one distribution of training lengths
    ranges: tuple[tuple[str, Draw], ...] = field(default=(), hash=False, compare=False)
    # the clean models' own draws of some of those fields (a field of ``ranges`` in its place, with
    # the same random numbers; another after them): clean models converge sooner, so a round gives
    # them longer training lengths to draw from, and frames trained tell no label
    clean_ranges: tuple[tuple[str, Draw], ...] = field(default=(), hash=False, compare=False)
    # its models' ids: block 0 shares one permutation; a later block's ids follow every earlier
    # block's, so cells added to a planned zoo (zoo replan) leave the older models their ids
    block: int = field(default=0, hash=False, compare=False)

    def label_ranges(self, poisoned: bool) -> tuple[tuple[str, Draw], ...]:
        """The cell's draws for a model of this label (:attr:`ranges`, :attr:`clean_ranges`)."""
        if poisoned or not self.clean_ranges:
            return self.ranges
        own = dict(self.clean_ranges)
        return tuple((key, own.pop(key, draw)) for key, draw in self.ranges) + tuple(own.items())

    @property
    def arch_label(self) -> str:
        return self.arch if self.arch is not None else worlds.get(self.world).algorithm

    @property
    def key(self) -> str:
        """``world/arch/family``, and ``/attack`` for a cell not poisoned by the paper's env mix."""
        base = f"{self.world}/{self.arch_label}/{self.trigger.name}"
        return base if self.attack.is_default else f"{base}/{self.attack.name}"


@dataclass(frozen=True)
class Group:
    """A cell's models of one ground-truth label: the runner tops a group up until ``wanted`` of
    its models have converged or ``max_attempts`` were trained."""

    index: int
    cell: Cell
    poisoned: bool
    id_offset: int  # its first slot in the zoo's id space

    @property
    def wanted(self) -> int:
        return self.cell.poisoned if self.poisoned else self.cell.clean

    @property
    def max_attempts(self) -> int:
        return self.cell.max_attempts

    @property
    def label(self) -> str:
        return "poisoned" if self.poisoned else "clean"

    @property
    def key(self) -> str:
        return f"{self.cell.key}/{self.label}"


@dataclass(frozen=True)
class Examples:
    """The clean episodes each model folder carries in ``clean-example-data/``."""

    episodes: int = 5
    seed: int = 2_000_000  # apart from the evaluation layouts (train.eval_seed, 1,000,000 + i)
    policy: str = "sample"


@dataclass(frozen=True)
class ZooSpec:
    seed: int
    cells: tuple[Cell, ...]
    name: str = "zoo"
    examples: Examples = Examples()
    overrides: dict = field(default_factory=dict, hash=False, compare=False)
    normalized: dict = field(default_factory=dict, hash=False, compare=False)
    # Matched budgets: a cell's poisoned model k trains from the seed (so the initial weights) of
    # its clean model k, and every model trains at least overrides.train.min_frames, so neither
    # where a model starts nor how long it trains gives its label away (docs/zoos.md).
    matched: bool = False

    def twin(self, group: Group) -> Group | None:
        """The clean group of a poisoned group's cell (None: a clean group, or a cell without clean models)."""
        if not group.poisoned:
            return None
        return next((g for g in self.groups if g.cell is group.cell and not g.poisoned), None)

    @cached_property
    def groups(self) -> list[Group]:
        """Every cell's groups with a model wanted, clean before poisoned, in spec order."""
        out: list[Group] = []
        offset = 0
        for cell in self.cells:
            for poisoned in (False, True):
                if (cell.poisoned if poisoned else cell.clean) > 0:
                    out.append(Group(len(out), cell, poisoned, offset))
                    offset += cell.max_attempts
        return out

    @property
    def id_space(self) -> int:
        return sum(g.max_attempts for g in self.groups)

    def to_dict(self) -> dict:
        return copy.deepcopy(self.normalized)


def _parse_family(where: str, raw, world: worlds.World, size: int | None) -> TriggerFamily:
    def check(trigger: str, label: str) -> None:
        for seed in (0, 1):  # a bare kind draws; both must give a trigger the world accepts
            try:
                world.draw_trigger(trigger, seed, size)
            except (ValueError, TypeError) as err:
                raise ConfigError(f"{label}={trigger!r} is not a {world.name} trigger: {err} (allowed: {world.trigger_help})") from None

    if isinstance(raw, str):
        check(raw, where)
        return TriggerFamily(name=raw, trigger=raw)
    if not isinstance(raw, dict):
        raise ConfigError(f"{where} must be a trigger string or a table with template and ranges, got {raw!r}")
    _keys(where, raw, FAMILY_KEYS)
    name = raw.get("name")
    if name is not None:
        _type(f"{where}.name", name, str, "a string")
        if not name or "/" in name:
            raise ConfigError(f"{where}.name must be a non-empty string without '/', got {name!r}")
    if "template" in raw and "trigger" in raw:
        raise ConfigError(f"{where} takes one of trigger (a string) or template (with ranges), not both")
    if "template" not in raw:
        if "ranges" in raw:
            raise ConfigError(f"{where}.ranges applies to a template only")
        if "trigger" not in raw:  # a name alone: the world draws the trigger from each model's seed
            return TriggerFamily(name=name or DRAWN)
    if "trigger" in raw:
        trigger = _type(f"{where}.trigger", raw["trigger"], str, "a string")
        check(trigger, f"{where}.trigger")
        return TriggerFamily(name=name or trigger, trigger=trigger)
    template = _type(f"{where}.template", raw["template"], str, "a string")
    try:
        fields = [f for _, f, _, _ in string.Formatter().parse(template) if f is not None]
    except ValueError as err:
        raise ConfigError(f"{where}.template={template!r} is not a valid template: {err}") from None
    if not fields or any(not f.isidentifier() for f in fields):
        raise ConfigError(f"{where}.template={template!r} must hold {{name}} placeholders (e.g. 'multiplicative:{{a}}')")
    ranges = raw.get("ranges")
    if not isinstance(ranges, dict):
        raise ConfigError(f"{where}.ranges must be a table of [low, high] per placeholder ({', '.join(sorted(set(fields)))})")
    if set(ranges) != set(fields):
        missing, extra = sorted(set(fields) - set(ranges)), sorted(set(ranges) - set(fields))
        what = f"has no range for {', '.join(missing)}" if missing else f"names {', '.join(extra)}, which the template does not hold"
        raise ConfigError(f"{where}.ranges {what} (placeholders: {', '.join(sorted(set(fields)))})")
    parsed = []
    for key in sorted(ranges):
        bounds = ranges[key]
        if (
            not isinstance(bounds, list)
            or len(bounds) != 2
            or any(isinstance(b, bool) or not isinstance(b, (int, float)) or not math.isfinite(b) for b in bounds)
        ):
            raise ConfigError(f"{where}.ranges.{key} must be [low, high] (two finite numbers), got {bounds!r}")
        low, high = bounds
        if low > high:
            raise ConfigError(f"{where}.ranges.{key}=[{low}, {high}] is an empty range (low must be <= high)")
        parsed.append((key, low, high))
    for corner in (0, 1):
        values = {key: bounds[corner] for key, *bounds in parsed}
        try:
            example = template.format(**values)
        except (ValueError, IndexError, KeyError) as err:
            raise ConfigError(f"{where}.template={template!r} cannot be filled: {err}") from None
        check(example, f"{where}.template with ranges at their {'high' if corner else 'low'} ends")
    return TriggerFamily(name=name or template, template=template, ranges=tuple(parsed))


def _counts(where: str, raw: dict) -> tuple[int, int]:
    if "models" in raw:
        if "clean" in raw or "poisoned" in raw:
            raise ConfigError(f"{where}: give either models (with poisoned_share) or clean and poisoned, not both")
        models = _int(f"{where}.models", raw["models"], 1, MAX_ATTEMPTS)
        share = raw.get("poisoned_share", 0.5)
        if isinstance(share, bool) or not isinstance(share, (int, float)) or not 0 <= share <= 1:
            raise ConfigError(f"{where}.poisoned_share must be a number in [0, 1], got {share!r}")
        poisoned = int(math.floor(models * share + 0.5))
        return models - poisoned, poisoned
    if "poisoned_share" in raw:
        raise ConfigError(f"{where}.poisoned_share applies with models only (or give clean and poisoned counts)")
    if "clean" not in raw and "poisoned" not in raw:
        raise ConfigError(f"{where} needs models (and poisoned_share, default 0.5) or clean and poisoned: converged models wanted per cell")
    clean = _int(f"{where}.clean", raw.get("clean", 0), 0, MAX_ATTEMPTS)
    poisoned = _int(f"{where}.poisoned", raw.get("poisoned", 0), 0, MAX_ATTEMPTS)
    if clean + poisoned == 0:
        raise ConfigError(f"{where}: clean + poisoned must be >= 1")
    return clean, poisoned


def parse_spec(raw: dict, check_configs: bool = True) -> ZooSpec:
    """A validated :class:`ZooSpec` from a parsed TOML document (or zoo.json's ``spec``).

    ``check_configs`` also builds one config per cell, so a bad override is named now, not
    when the first model of that cell is planned.
    """
    if not isinstance(raw, dict):
        raise ConfigError(f"the zoo spec must be a table, got {type(raw).__name__}")
    _keys("", raw, TOP_KEYS)
    if raw.get("format", SPEC_FORMAT) != SPEC_FORMAT:
        raise ConfigError(f"format={raw.get('format')!r} is not a spec format this version reads (allowed: {SPEC_FORMAT})")
    if "seed" not in raw:
        raise ConfigError("seed (the master seed every model is drawn from) is required")
    check_seed("seed", raw["seed"])
    name = _type("name", raw.get("name", "zoo"), str, "a string")
    default_attempts = raw.get("max_attempts")
    if default_attempts is not None:
        _int("max_attempts", default_attempts, 1, MAX_ATTEMPTS)
    ex = raw.get("examples", {})
    if not isinstance(ex, dict):
        raise ConfigError(f"examples must be a table (episodes, seed, policy), got {ex!r}")
    _keys("examples", ex, EXAMPLE_KEYS)
    examples = Examples(
        episodes=_int("examples.episodes", ex.get("episodes", Examples.episodes), 0, MAX_EPISODES),
        seed=ex.get("seed", Examples.seed),
        policy=ex.get("policy", Examples.policy),
    )
    check_seed("examples.seed", examples.seed)
    if examples.policy not in EXAMPLE_POLICIES:
        raise ConfigError(f"examples.policy={examples.policy!r} is not allowed (allowed: {', '.join(EXAMPLE_POLICIES)})")
    overrides = _check_overrides("overrides", raw.get("overrides", {}))
    matched = raw.get("matched", False)
    if not isinstance(matched, bool):
        raise ConfigError(f"matched={matched!r} is not allowed (allowed: true, false)")
    if matched and not overrides.get("train", {}).get("min_frames"):
        raise ConfigError("matched = true needs overrides.train.min_frames > 0 (the frames clean and poisoned models all train for at least)")
    entries = raw.get("cells")
    if not isinstance(entries, list) or not entries:
        raise ConfigError("cells must be a non-empty array of tables ([[cells]] with world = ...)")
    cells: list[Cell] = []
    norm_cells: list[dict] = []
    seen: dict[str, str] = {}
    for i, entry in enumerate(entries):
        where = f"cells[{i}]"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where} must be a table, got {entry!r}")
        _keys(where, entry, CELL_KEYS)
        if "world" not in entry:
            raise ConfigError(f"{where}.world is required (allowed: {', '.join(worlds.names())})")
        world_name = entry["world"]
        if world_name not in worlds.names():
            raise ConfigError(f"{where}.world={world_name!r} is not allowed (allowed: {', '.join(worlds.names())})")
        world = worlds.get(world_name)
        if "archs" in entry:
            archs = entry["archs"]
            if not world.arch_names:
                raise ConfigError(f"{where}.archs: {world_name} has no named architectures (set its network through overrides)")
            if not isinstance(archs, list) or not archs:
                raise ConfigError(f"{where}.archs must be a non-empty list (allowed: {', '.join(world.arch_names)})")
            for j, arch in enumerate(archs):
                if arch not in world.arch_names:
                    raise ConfigError(f"{where}.archs[{j}]={arch!r} is not allowed for {world_name} (allowed: {', '.join(world.arch_names)})")
            if len(set(archs)) != len(archs):
                raise ConfigError(f"{where}.archs lists an architecture twice: {archs!r}")
            arch_list: list[str | None] = list(archs)
        else:
            arch_list = list(world.arch_names) or [None]
        cell_overrides = deep_merge(overrides, _check_overrides(f"{where}.overrides", entry.get("overrides", {})))
        clean, poisoned = _counts(where, entry)
        attempts = entry.get("max_attempts", default_attempts)
        if attempts is None:
            attempts = max(clean, poisoned)
        _int(f"{where}.max_attempts", attempts, 1, MAX_ATTEMPTS)
        if attempts < max(clean, poisoned):
            label = "poisoned" if poisoned >= clean else "clean"
            raise ConfigError(
                f"{where}.max_attempts={attempts} is less than the {max(clean, poisoned)} converged {label} models wanted per cell "
                f"(max_attempts counts the models trained per cell and label)"
            )
        block = _int(f"{where}.block", entry.get("block", 0), 0, MAX_ATTEMPTS)
        if cells and block < cells[-1].block:
            raise ConfigError(f"{where}.block={block} comes after a cell of block {cells[-1].block}: a block's cells follow every earlier block's")
        raw_attacks = entry.get("attacks")
        if raw_attacks is None:
            choices = [DEFAULT_CHOICE]
        else:
            if not isinstance(raw_attacks, list) or not raw_attacks:
                raise ConfigError(f"{where}.attacks must be a non-empty list of attack names or tables (allowed attacks: {', '.join(attacks.names())})")
            choices = [_parse_attack(f"{where}.attacks[{j}]", a) for j, a in enumerate(raw_attacks)]
            labels = [c.name for c in choices]
            if len(set(labels)) != len(labels):
                raise ConfigError(f"{where}.attacks: two share the name {next(n for n in labels if labels.count(n) > 1)!r} (give each a name)")
        size = None
        if check_configs:
            for j, choice in enumerate(choices):
                try:
                    size = _sample_size(where, world_name, arch_list[0], overrides, deep_merge(cell_overrides, choice.overrides()))
                except ConfigError as err:
                    raise ConfigError(f"{where}.attacks[{j}]: {err}" if raw_attacks is not None else str(err)) from None
        raw_triggers = entry.get("triggers")
        if raw_triggers is None:
            families = [TriggerFamily(name=DRAWN)]
        else:
            if not isinstance(raw_triggers, list) or not raw_triggers:
                raise ConfigError(f"{where}.triggers must be a non-empty list (of trigger strings or template tables; allowed: {world.trigger_help})")
            families = [_parse_family(f"{where}.triggers[{j}]", t, world, size) for j, t in enumerate(raw_triggers)]
            names = [f.name for f in families]
            if len(set(names)) != len(names):
                raise ConfigError(f"{where}.triggers: two families share the name {next(n for n in names if names.count(n) > 1)!r} (give each a name)")
        cell_ranges = (
            _parse_cell_ranges(where, entry.get("ranges", {}), world_name, arch_list[0], cell_overrides)
            if check_configs
            else _cell_ranges(where, entry.get("ranges", {}))
        )
        clean_ranges = (
            _parse_cell_ranges(where, entry.get("clean_ranges", {}), world_name, arch_list[0], cell_overrides, "clean_ranges")
            if check_configs
            else _cell_ranges(where, entry.get("clean_ranges", {}), "clean_ranges")
        )
        for arch in arch_list:
            for family in families:
                for choice in choices:
                    overrides_ = deep_merge(cell_overrides, choice.overrides())
                    cell = Cell(i, world_name, arch, family, clean, poisoned, attempts, overrides_, choice, cell_ranges, clean_ranges, block)
                    if cell.key in seen:
                        raise ConfigError(f"{where} repeats the cell {cell.key} of {seen[cell.key]}")
                    seen[cell.key] = where
                    cells.append(cell)
        norm: dict[str, Any] = {"world": world_name}
        if world.arch_names:
            norm["archs"] = arch_list
        if raw_attacks is not None:  # specs written before attacks existed keep their normal form
            norm["attacks"] = [c.to_dict() for c in choices]
        norm.update(
            triggers=[f.to_dict() for f in families],
            clean=clean,
            poisoned=poisoned,
            max_attempts=attempts,
            overrides=entry.get("overrides", {}),
        )
        if cell_ranges:  # specs written before cell ranges keep their normal form
            norm["ranges"] = {key: draw.to_data() for key, draw in cell_ranges}
        if clean_ranges:
            norm["clean_ranges"] = {key: draw.to_data() for key, draw in clean_ranges}
        if block:  # specs written before blocks keep their normal form
            norm["block"] = block
        norm_cells.append(norm)
    spec = ZooSpec(
        seed=raw["seed"],
        cells=tuple(cells),
        name=name,
        examples=examples,
        overrides=overrides,
        matched=matched,
        normalized={
            "format": SPEC_FORMAT,
            "name": name,
            "seed": raw["seed"],
            **({"matched": True} if matched else {}),  # specs written before it keep their normal form
            "examples": {"episodes": examples.episodes, "seed": examples.seed, "policy": examples.policy},
            "overrides": overrides,
            "cells": norm_cells,
        },
    )
    if spec.id_space > MAX_ID_SPACE:
        raise ConfigError(f"max_attempts: the cells' max_attempts add up to {spec.id_space:,} models (at most {MAX_ID_SPACE:,} per zoo)")
    return spec


def nested(dotted: dict[str, Any]) -> dict:
    """``{"train.min_frames": 1}`` -> ``{"train": {"min_frames": 1}}`` (flatten's inverse)."""
    out: dict[str, Any] = {}
    for key, value in dotted.items():
        *path, last = key.split(".")
        node = out
        for part in path:
            node = node.setdefault(part, {})
        node[last] = value
    return out


def _cell_ranges(where: str, raw, name: str = "ranges") -> tuple[tuple[str, Draw], ...]:
    if not isinstance(raw, dict):
        raise ConfigError(f'{where}.{name} must be a table of "section.field" = [low, high] or {{ one_of = [...] }}, got {raw!r}')
    out = []
    for key, value in raw.items():
        if key.count(".") != 1 or not all(part.isidentifier() for part in key.split(".")):
            raise ConfigError(f'{where}.{name}.{key} must name a config field as "section.field" (e.g. "train.min_frames")')
        if key in ZOO_FIELDS or key.startswith("poison."):
            why = "set by the zoo" if key in ZOO_FIELDS else "a poisoned model's setting: draw it in the attack's ranges (attack parameters, evasion.KNOB)"
            raise ConfigError(f"{where}.{name}.{key} is {why}")
        out.append((key, parse_draw(f"{where}.{name}.{key}", value)))
    return tuple(out)


def _parse_cell_ranges(where: str, raw, world: str, arch: str | None, overrides: dict, name: str = "ranges") -> tuple[tuple[str, Draw], ...]:
    """The cell's ranges, each end and option checked in a config of the cell (one ConfigError naming it)."""
    ranges = _cell_ranges(where, raw, name)
    for key, draw in ranges:
        for value in draw.corners():
            try:
                _build_sample(world, arch, deep_merge(overrides, nested({key: value})))
            except ConfigError as err:
                raise ConfigError(f"{where}.{name}.{key}={value!r}: {err}") from None
    return ranges


def _sample_size(where: str, world: str, arch: str | None, spec_overrides: dict, overrides: dict) -> int | None:
    """Build one config of the cell (defaults filled in) to check its overrides now; return the
    grid size its triggers are drawn for (None for worlds without one). A bad value is blamed on
    the spec's ``[overrides]`` when those alone are refused, else on the cell's."""
    try:
        cfg = _build_sample(world, arch, overrides)
    except ConfigError as err:
        field = f"{where}.overrides"
        if spec_overrides:
            try:
                _build_sample(world, arch, spec_overrides)
            except ConfigError:
                field = f"overrides (in {where}, {world})"
        raise ConfigError(f"{field}: {err}") from None
    return getattr(cfg.env, "size", None)


def _build_sample(world: str, arch: str | None, overrides: dict):
    from rlbackdoors.zoo.plan import build_config, config_data

    try:
        return build_config(config_data(world, arch, overrides, poisoned=True, seed=0, trigger=None))
    except ConfigError:
        raise
    except (ValueError, TypeError) as err:
        raise ConfigError(" ".join(str(err).split())) from None


def load_spec(path: str | Path) -> ZooSpec:
    """Read and validate a TOML spec file (one ConfigError naming the field for any problem)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"zoo spec {str(path)!r} does not exist")
    try:
        raw = tomllib.loads(path.read_bytes().decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise ConfigError(f"zoo spec {str(path)!r} is not valid TOML: {err}") from None
    return parse_spec(raw)


def first_difference(old, new, where: str = "") -> str | None:
    """The dotted name of the first field where two normalized specs differ (None: equal)."""
    if isinstance(old, dict) and isinstance(new, dict):
        for key in sorted(set(old) | set(new)):
            name = f"{where}.{key}" if where else str(key)
            if key not in old or key not in new:
                return name
            found = first_difference(old[key], new[key], name)
            if found:
                return found
        return None
    if isinstance(old, list) and isinstance(new, list):
        if len(old) != len(new):
            return f"{where} (length {len(old)} -> {len(new)})"
        for i, (a, b) in enumerate(zip(old, new)):
            found = first_difference(a, b, f"{where}[{i}]")
            if found:
                return found
        return None
    return None if old == new else where or "(spec)"
