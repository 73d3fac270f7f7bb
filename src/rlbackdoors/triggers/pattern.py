"""In-distribution triggers of Randomized LavaWorld: patterns of lava cells (SPEC §2).

A trigger here is not a change of the observation but a *layout*: a few lava cells in a
given arrangement inside a 3x3 box, placed by the poisoned env in or near the agent's view.
Every single cell is ordinary lava (same bytes in the observation as any other lava), so the
pattern is in-distribution: a clean layout can contain it by chance (:func:`find_pattern`
measures how often).

Coordinates are grid offsets ``(dx, dy)`` with ``x`` to the east and ``y`` to the south, as
in MiniGrid, both in ``0..2``. Directions are global (the world's, not the agent's) and use
MiniGrid's numbering: 0 east, 1 south, 2 west, 3 north.

Spec strings (what configs and ``gym.make`` kwargs carry; :meth:`PatternTrigger.spec` writes
the canonical form and :meth:`PatternTrigger.parse` reads it back):

* ``cross`` -- the ``+``: centre row and centre column of the box (5 cells);
* ``arrow`` -- a 3-cell arrowhead pointing in *any* direction: the env draws one of the four
  rotations per episode (uniformly);
* ``arrow:east`` / ``arrow:south`` / ``arrow:west`` / ``arrow:north`` -- one direction only;
* ``cells:DX,DY;DX,DY;...`` -- a user pattern placed as given, ``cells:...:any`` -- a user
  pattern in any of its rotations. Cells must be unique, in ``0..2``, and at least one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

BOX = 3  # patterns live in a BOX x BOX square
DIRECTIONS = ("east", "south", "west", "north")  # MiniGrid's agent_dir order
MAX_PATTERN_CELLS = BOX * BOX

Cell = tuple[int, int]


def _rotate_cw(cells: Iterable[Cell]) -> tuple[Cell, ...]:
    """A quarter turn clockwise on the map (east -> south -> west -> north) inside the box."""
    return tuple(sorted((BOX - 1 - dy, dx) for dx, dy in cells))


def _check_cells(cells) -> tuple[Cell, ...]:
    try:
        pairs = [tuple(c) for c in cells]
    except TypeError:
        raise ValueError(f"pattern cells {cells!r} must be a list of (dx, dy) pairs") from None
    if not pairs:
        raise ValueError("a lava pattern needs at least one cell")
    out = []
    for c in pairs:
        if len(c) != 2 or any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) for v in c):
            raise ValueError(f"pattern cell {c!r} must be a pair of integers (dx, dy)")
        dx, dy = int(c[0]), int(c[1])
        if not (0 <= dx < BOX and 0 <= dy < BOX):
            raise ValueError(f"pattern cell {(dx, dy)} is outside the {BOX}x{BOX} box: dx and dy must be in 0..{BOX - 1}")
        out.append((dx, dy))
    if len(set(out)) != len(out):
        dups = sorted({c for c in out if out.count(c) > 1})
        raise ValueError(f"pattern cells must be unique; repeated: {dups}")
    return tuple(sorted(out))


@dataclass(frozen=True)
class LavaPattern:
    """A name and a set of lava cells ``(dx, dy)`` inside the 3x3 box (sorted, unique)."""

    name: str
    cells: tuple[Cell, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "cells", _check_cells(self.cells))

    def __len__(self) -> int:
        return len(self.cells)

    def rotated(self, quarter_turns: int = 1, name: str | None = None) -> "LavaPattern":
        """This pattern turned clockwise ``quarter_turns`` times (east becomes south)."""
        cells = self.cells
        for _ in range(quarter_turns % 4):
            cells = _rotate_cw(cells)
        return LavaPattern(name or self.name, cells)

    def grid(self) -> np.ndarray:
        """The pattern as a 3x3 bool array indexed ``[dx, dy]`` (MiniGrid's x-first order)."""
        g = np.zeros((BOX, BOX), dtype=bool)
        for dx, dy in self.cells:
            g[dx, dy] = True
        return g


CROSS = LavaPattern("cross", ((1, 0), (0, 1), (1, 1), (2, 1), (1, 2)))
# the arrowhead pointing east: its tip in the middle of the east column, its two barbs in the
# middle column's top and bottom cells (the paper's "up" arrow: top middle, centre left and
# centre right, turned to face east)
_ARROW_EAST = LavaPattern("arrow:east", ((2, 1), (1, 0), (1, 2)))
ARROWS = {d: _ARROW_EAST.rotated(k, f"arrow:{d}") for k, d in enumerate(DIRECTIONS)}
BUILTIN = {p.name: p for p in (CROSS, *ARROWS.values())}  # by spec name


def _cells_spec(cells: Sequence[Cell]) -> str:
    return ";".join(f"{dx},{dy}" for dx, dy in cells)


@dataclass(frozen=True)
class PatternTrigger:
    """Which lava pattern the poisoned env inserts, and in which rotations.

    ``pattern`` is the pattern as given; with ``any_rotation`` each episode places one of its
    distinct rotations (uniformly), otherwise always ``pattern`` itself.
    """

    pattern: LavaPattern
    any_rotation: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.pattern, LavaPattern):
            raise ValueError(f"pattern must be a LavaPattern, got {self.pattern!r}")
        # canonical form, so that equal triggers compare equal and spec() round-trips:
        # built-in cells get the built-in pattern; "any rotation" of a rotation-invariant
        # pattern is no choice at all; any rotation of a pattern starts from a fixed one
        cells = self.pattern.cells
        any_rotation = bool(self.any_rotation)
        turns = {self.pattern.rotated(k).cells for k in range(4)}
        if any_rotation and len(turns) == 1:
            any_rotation = False
        if any_rotation:
            cells = ARROWS["east"].cells if ARROWS["east"].cells in turns else min(turns)
        pattern = next((p for p in BUILTIN.values() if p.cells == cells), None)
        if pattern is None:
            pattern = LavaPattern(f"cells:{_cells_spec(cells)}", cells)
        object.__setattr__(self, "pattern", pattern)
        object.__setattr__(self, "any_rotation", any_rotation)

    @classmethod
    def from_cells(cls, cells: Sequence[Cell], any_rotation: bool = False) -> "PatternTrigger":
        """A user pattern from a list of ``(dx, dy)`` cells in the 3x3 box."""
        return cls(LavaPattern("cells", _check_cells(cells)), any_rotation)

    @property
    def num_cells(self) -> int:
        return len(self.pattern)

    def rotations(self) -> tuple[LavaPattern, ...]:
        """The distinct concrete patterns the env may place (one unless ``any_rotation``)."""
        if not self.any_rotation:
            return (self.pattern,)
        out: list[LavaPattern] = []
        seen: set[tuple[Cell, ...]] = set()
        for k in range(4):
            r = self.pattern.rotated(k)
            if r.cells not in seen:
                seen.add(r.cells)
                # name built-in arrows by their direction, anything else by its cells
                name = next((n for n, p in ARROWS.items() if p.cells == r.cells), None)
                out.append(ARROWS[name] if name else LavaPattern(f"cells:{_cells_spec(r.cells)}", r.cells))
        return tuple(out)

    def spec(self) -> str:
        """The canonical spec string; ``PatternTrigger.parse(t.spec()) == t``."""
        p = self.pattern
        if p == ARROWS["east"] and self.any_rotation:
            return "arrow"
        if p.name in BUILTIN and not self.any_rotation:
            return p.name
        text = f"cells:{_cells_spec(p.cells)}"
        return f"{text}:any" if self.any_rotation else text

    @classmethod
    def parse(cls, text: str) -> "PatternTrigger":
        """Parse ``cross``, ``arrow``, ``arrow:DIRECTION`` or ``cells:DX,DY;...[:any]``."""
        s = str(text).strip()
        head, _, rest = s.partition(":")
        if head == "cross":
            if rest not in ("", "any"):
                raise ValueError(f"pattern {text!r}: the cross has no direction (use 'cross')")
            return cls(CROSS, False)
        if head == "arrow":
            if rest in ("", "any"):
                return cls(ARROWS["east"], True)
            if rest in ARROWS:
                return cls(ARROWS[rest], False)
            raise ValueError(f"pattern {text!r}: arrow direction {rest!r} is not one of any, {', '.join(DIRECTIONS)}")
        if head == "cells":
            body, any_rot = rest, False
            if body.endswith(":any"):
                body, any_rot = body[: -len(":any")], True
            cells = []
            for part in body.split(";"):
                if not part.strip():
                    continue
                xy = part.split(",")
                if len(xy) != 2:
                    raise ValueError(f"pattern {text!r}: cell {part!r} must look like 'DX,DY'")
                try:
                    cells.append((int(xy[0]), int(xy[1])))
                except ValueError:
                    raise ValueError(f"pattern {text!r}: cell {part!r} is not two integers") from None
            return cls(LavaPattern("cells", tuple(cells)), any_rot)
        raise ValueError(f"lava pattern {text!r} must be 'cross', 'arrow', 'arrow:east|south|west|north' or 'cells:DX,DY;DX,DY;...[:any]'")


def as_pattern_trigger(trigger) -> PatternTrigger | None:
    """Accept ``None``, a :class:`PatternTrigger`, a :class:`LavaPattern`, a spec string, or a
    list of ``(dx, dy)`` cells (a user pattern placed as given)."""
    if trigger is None or isinstance(trigger, PatternTrigger):
        return trigger
    if isinstance(trigger, LavaPattern):
        return PatternTrigger(trigger, False)
    if isinstance(trigger, str):
        return PatternTrigger.parse(trigger)
    return PatternTrigger.from_cells(trigger)


def _as_cell_sets(patterns) -> list[tuple[Cell, ...]]:
    if isinstance(patterns, (PatternTrigger, str)):
        trigger = as_pattern_trigger(patterns)
        assert trigger is not None  # a PatternTrigger or spec string is never None
        patterns = trigger.rotations()
    elif isinstance(patterns, LavaPattern):
        patterns = [patterns]
    out = []
    for p in patterns:
        cells = p.cells if isinstance(p, LavaPattern) else _check_cells(p)
        mx, my = min(dx for dx, _ in cells), min(dy for _, dy in cells)
        out.append(tuple((dx - mx, dy - my) for dx, dy in cells))  # anchored at (0, 0)
    if not out:
        raise ValueError("find_pattern needs at least one pattern")
    return out


def find_pattern(lava_mask, patterns) -> int | np.ndarray:
    """How many placements of ``patterns`` a layout contains (0: the pattern does not occur).

    ``lava_mask`` is a bool array indexed ``[x, y]`` (``grid.encode()[:, :, 0] == LAVA``), or a
    batch of them ``(..., W, H)``. ``patterns`` is a :class:`PatternTrigger` or spec string
    (all of its rotations count), a :class:`LavaPattern`, or a list of cell sets. A placement
    is an offset ``(ox, oy)`` and one of the patterns such that every cell ``(ox+dx, oy+dy)``
    is lava; other cells of the 3x3 box may be anything. Returns an int for one layout, an
    int64 array for a batch.
    """
    mask = np.asarray(lava_mask, dtype=bool)
    if mask.ndim < 2:
        raise ValueError(f"lava_mask must be 2-D [x, y] (or a batch), got shape {mask.shape}")
    w, h = mask.shape[-2:]
    total = np.zeros(mask.shape[:-2], dtype=np.int64)
    for cells in _as_cell_sets(patterns):
        mx = max(dx for dx, _ in cells)
        my = max(dy for _, dy in cells)
        if mx >= w or my >= h:
            continue
        hit = np.ones(mask.shape[:-2] + (w - mx, h - my), dtype=bool)
        for dx, dy in cells:
            hit &= mask[..., dx : w - mx + dx, dy : h - my + dy]
        total += hit.sum(axis=(-2, -1))
    return int(total) if total.ndim == 0 else total


def near_patterns(trigger: PatternTrigger) -> list[PatternTrigger]:
    """The patterns one cell off ``trigger``: one of its cells moved to an empty cell of the box,
    in the trigger's rotations if it takes any; never the trigger (nor one of its rotations). The
    near-trigger negatives of ``poison.evasion.near``, which teach a trojan the exact pattern."""
    own = {r.cells for r in trigger.rotations()}
    box = [(x, y) for x in range(BOX) for y in range(BOX)]
    cells = trigger.pattern.cells
    out: dict[str, PatternTrigger] = {}
    for moved in cells:
        for target in box:
            if target in cells:
                continue
            near = PatternTrigger.from_cells(sorted([c for c in cells if c != moved] + [target]), trigger.any_rotation)
            if near.pattern.cells in own or any(r.cells in own for r in near.rotations()):
                continue
            out.setdefault(near.spec(), near)
    return list(out.values())
