"""In-distribution triggers of Colorful Memory: colour sequences over wall squares (SPEC §3).

Every wall square of a Colorful Memory grid gets one of MiniGrid's six colours at random per
episode. A trigger is a fixed colour sequence over a fixed set of wall squares; the poisoned
env paints it, so the trigger is in-distribution: a clean episode shows it by chance with
probability ``6 ** -n`` for ``n`` squares (:func:`chance_probability`; :func:`matches` and
:func:`distance` check grids).

Squares (MiniGrid coordinates: ``x`` to the east, ``y`` to the south; ``mid = size // 2``,
``hallway_end = size - 3`` as in MiniGrid's ``MemoryEnv``):

* **End Trigger** -- ``size + 2`` squares (9 for the default size 7), listed as a path around
  the far end of the vertical corridor: the top end square of the corridor
  ``(hallway_end + 1, 0)``, then the far wall ``(hallway_end + 2, y)`` for ``y = 0 .. size-1``
  (north to south), then the bottom end square ``(hallway_end + 1, size - 1)``;
* **Room Trigger** -- the 3 wall squares above the start room ``(1, mid-2), (2, mid-2),
  (3, mid-2)``, west to east (on the agent's left at the start: it faces east);
* **both** -- the End Trigger's squares, then the Room Trigger's.

Colours are MiniGrid's indices: red 0, green 1, blue 2, purple 3, yellow 4, grey 5.

Spec strings (what configs and ``gym.make`` kwargs carry; :meth:`WallColorTrigger.spec` writes
the canonical form and :meth:`WallColorTrigger.parse` reads it back):

* ``end:C,C,...`` -- the End Trigger's ``size + 2`` colours in the order above;
* ``room:C,C,C`` -- the Room Trigger's 3 colours;
* ``end+room:E,...;R,R,R`` -- both (``room+end`` and a single list whose last 3 colours are the
  room's are accepted too);
* a bare kind (``end``, ``room``, ``end+room``) names no colours: :func:`sample` draws them
  uniformly (all ``6 ** n`` patterns equally likely) from a seed, and :func:`parse` does that
  when given ``rng=``. Envs take only concrete triggers, so that a model's config records the
  very pattern it was poisoned with.

Colour names are case-insensitive; ``gray`` is read as ``grey``.

Close-to-trigger (:func:`close_to_trigger`): the trigger with ``k`` distinct squares (uniform
among its squares) each recoloured to one of the 5 *other* colours (uniformly), so it differs
from the trigger in exactly ``k`` squares.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

COLORS = ("red", "green", "blue", "purple", "yellow", "grey")  # MiniGrid's COLOR_TO_IDX order
NUM_COLORS = len(COLORS)
KINDS = ("end", "room", "end+room")
ROOM_SQUARES = 3
WALL = 2  # MiniGrid's OBJECT_TO_IDX["wall"]
MIN_SIZE = 7

Square = tuple[int, int]


# ----------------------------------------------------------------------------- geometry


def check_size(size) -> int:
    """MiniGrid Memory's constraint: an odd grid size, at least 7 (the start room, a corridor
    and the T-junction need it). Returns ``size`` as an int."""
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < MIN_SIZE or size % 2 == 0:
        raise ValueError(f"size={size!r} must be an odd integer >= {MIN_SIZE} (MiniGrid Memory's geometry)")
    return int(size)


def hallway_end(size: int) -> int:
    """The x of the vertical corridor's west wall (MiniGrid ``MemoryEnv`` without random length)."""
    return check_size(size) - 3


def end_squares(size: int = 7) -> tuple[Square, ...]:
    """The End Trigger's ``size + 2`` squares, in spec order (module doc)."""
    he = hallway_end(size)
    return ((he + 1, 0), *((he + 2, y) for y in range(size)), (he + 1, size - 1))


def room_squares(size: int = 7) -> tuple[Square, ...]:
    """The Room Trigger's 3 squares, west to east (module doc)."""
    mid = check_size(size) // 2
    return tuple((x, mid - 2) for x in range(1, 1 + ROOM_SQUARES))


def kind_squares(kind: str, size: int = 7) -> tuple[Square, ...]:
    """The squares of a trigger kind, in spec order."""
    kind = _check_kind(kind)
    out: tuple[Square, ...] = ()
    if "end" in kind:
        out += end_squares(size)
    if "room" in kind:
        out += room_squares(size)
    return out


def _check_kind(kind) -> str:
    k = str(kind).strip().lower()
    if k == "room+end":
        k = "end+room"
    if k not in KINDS:
        raise ValueError(f"wall-colour trigger kind {kind!r} is not one of {', '.join(KINDS)}")
    return k


# ----------------------------------------------------------------------------- colours


def color_index(color, where: str = "colour") -> int:
    """A colour name (case-insensitive, ``gray`` = ``grey``) or index 0..5 as its index."""
    if isinstance(color, (int, np.integer)) and not isinstance(color, bool):
        if 0 <= int(color) < NUM_COLORS:
            return int(color)
        raise ValueError(f"{where} {color!r} is not a colour index in 0..{NUM_COLORS - 1} ({', '.join(COLORS)})")
    name = str(color).strip().lower()
    if name == "gray":
        name = "grey"
    if name not in COLORS:
        raise ValueError(f"{where} {color!r} is not one of {', '.join(COLORS)}")
    return COLORS.index(name)


def _colors(values, part: str) -> tuple[int, ...]:
    if isinstance(values, str):
        values = [v for v in values.split(",")]
    try:
        seq = list(values)
    except TypeError:
        raise ValueError(f"{part} trigger colours {values!r} must be a list of colours") from None
    return tuple(color_index(c, f"{part} trigger colour {i + 1}") for i, c in enumerate(seq))


# ----------------------------------------------------------------------------- the trigger


@dataclass(frozen=True)
class WallColorTrigger:
    """Colours (MiniGrid indices) for the End Trigger's squares, the Room Trigger's, or both.

    ``end`` has ``size + 2`` colours (9 for size 7) or is ``None``; ``room`` has 3 or is
    ``None``; at least one is given. Colour names are accepted and stored as indices.
    """

    end: tuple[int, ...] | None = None
    room: tuple[int, ...] | None = None

    def __post_init__(self) -> None:
        end = None if self.end is None else _colors(self.end, "end")
        room = None if self.room is None else _colors(self.room, "room")
        if end is None and room is None:
            raise ValueError("a wall-colour trigger needs end colours, room colours or both")
        if end is not None and (len(end) < MIN_SIZE + 2 or len(end) % 2 == 0):
            raise ValueError(
                f"end trigger has {len(end)} colours; it needs size + 2 of them for an odd grid size >= {MIN_SIZE} "
                f"(9 for the default size 7: the far wall's 7 squares and the corridor's 2 end squares)"
            )
        if room is not None and len(room) != ROOM_SQUARES:
            raise ValueError(f"room trigger has {len(room)} colours; it needs exactly {ROOM_SQUARES}")
        object.__setattr__(self, "end", end)
        object.__setattr__(self, "room", room)

    # ------------------------------------------------------------------ facts

    @property
    def kind(self) -> str:
        if self.end is not None and self.room is not None:
            return "end+room"
        return "end" if self.end is not None else "room"

    @property
    def size(self) -> int | None:
        """The grid size the End Trigger fits (``len(end) - 2``), ``None`` for a room trigger."""
        return None if self.end is None else len(self.end) - 2

    @property
    def colors(self) -> tuple[int, ...]:
        """All colours in square order: end, then room."""
        return (self.end or ()) + (self.room or ())

    @property
    def num_squares(self) -> int:
        return len(self.colors)

    @property
    def num_patterns(self) -> int:
        """How many patterns of this kind and size exist (``6 ** num_squares``)."""
        return NUM_COLORS**self.num_squares

    def check_size(self, size: int) -> None:
        """Raise ``ValueError`` unless the trigger fits a ``size x size`` Colorful Memory."""
        size = check_size(size)
        if self.end is not None and len(self.end) != size + 2:
            raise ValueError(
                f"end trigger has {len(self.end)} colours but a {size}x{size} Colorful Memory's End Trigger has "
                f"{size + 2} squares (the far wall's {size} and the corridor's 2 end squares)"
            )

    def squares(self, size: int | None = None) -> tuple[Square, ...]:
        """The trigger's squares in colour order (``size`` defaults to :attr:`size`, else 7)."""
        size = self.size if size is None else size
        size = MIN_SIZE if size is None else size
        self.check_size(size)
        return kind_squares(self.kind, size)

    def cells(self, size: int | None = None) -> tuple[tuple[int, int, int], ...]:
        """``(x, y, colour)`` for every square, in order."""
        return tuple((x, y, c) for (x, y), c in zip(self.squares(size), self.colors))

    def with_colors(self, colors: Sequence[int]) -> "WallColorTrigger":
        """The same kind and size with ``colors`` (in square order)."""
        colors = tuple(int(c) for c in colors)
        if len(colors) != self.num_squares:
            raise ValueError(f"{len(colors)} colours given for a trigger of {self.num_squares} squares")
        n_end = 0 if self.end is None else len(self.end)
        return WallColorTrigger(
            end=colors[:n_end] if self.end is not None else None,
            room=colors[n_end:] if self.room is not None else None,
        )

    # ------------------------------------------------------------------ text

    def spec(self) -> str:
        """The canonical spec string; ``WallColorTrigger.parse(t.spec()) == t``."""
        names = lambda cs: ",".join(COLORS[c] for c in cs)  # noqa: E731
        if self.kind == "end+room":
            return f"end+room:{names(self.end)};{names(self.room)}"
        return f"{self.kind}:{names(self.colors)}"

    def __str__(self) -> str:
        return self.spec()

    @classmethod
    def parse(cls, text: str, rng=None, size: int = MIN_SIZE) -> "WallColorTrigger":
        """Parse a spec string (module doc). A bare kind needs ``rng`` (a seed or numpy
        ``Generator``) and is then sampled uniformly for a ``size x size`` grid."""
        s = str(text).strip()
        head, sep, rest = s.partition(":")
        try:
            kind = _check_kind(head)
        except ValueError:
            raise ValueError(
                f"wall-colour trigger {text!r} must look like 'end:C,...', 'room:C,C,C' or 'end+room:E,...;R,R,R' "
                f"(or a bare kind {', '.join(KINDS)} with a seed); colours: {', '.join(COLORS)}"
            ) from None
        if not sep or not rest.strip():
            if rng is None:
                raise ValueError(
                    f"wall-colour trigger {text!r} names a kind but no colours: give the colours "
                    f"('{kind}:C,...') or sample them with a seed (sample({kind!r}, seed))"
                )
            return sample(kind, rng, size)
        if kind == "end":
            return cls(end=_colors(rest, "end"))
        if kind == "room":
            return cls(room=_colors(rest, "room"))
        if ";" in rest:
            parts = rest.split(";")
            if len(parts) != 2:
                raise ValueError(f"wall-colour trigger {text!r}: 'end+room:' takes end colours ';' room colours")
            first, second = parts
            if head.strip().lower() == "room+end":
                first, second = second, first
            return cls(end=_colors(first, "end"), room=_colors(second, "room"))
        colors = rest.split(",")
        if len(colors) <= ROOM_SQUARES:
            raise ValueError(f"wall-colour trigger {text!r}: 'end+room:' needs the end colours, then the {ROOM_SQUARES} room colours")
        if head.strip().lower() == "room+end":
            return cls(end=_colors(colors[ROOM_SQUARES:], "end"), room=_colors(colors[:ROOM_SQUARES], "room"))
        return cls(end=_colors(colors[:-ROOM_SQUARES], "end"), room=_colors(colors[-ROOM_SQUARES:], "room"))


def as_wall_color_trigger(trigger, rng=None, size: int = MIN_SIZE) -> WallColorTrigger | None:
    """Accept ``None``, a :class:`WallColorTrigger` or a spec string (a bare kind only with ``rng``)."""
    if trigger is None or isinstance(trigger, WallColorTrigger):
        return trigger
    if isinstance(trigger, str):
        return WallColorTrigger.parse(trigger, rng=rng, size=size)
    raise ValueError(f"trigger {trigger!r} must be a WallColorTrigger or a spec string like 'end:red,...'")


# ----------------------------------------------------------------------------- sampling


def _generator(rng) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool) and int(rng) >= 0:
        return np.random.default_rng(int(rng))
    raise ValueError(f"rng={rng!r} must be a non-negative integer seed or a numpy Generator")


def sample(kind: str, rng, size: int = MIN_SIZE) -> WallColorTrigger:
    """A trigger of ``kind`` (``end``, ``room``, ``end+room``) drawn uniformly among its
    ``6 ** n`` patterns, for a ``size x size`` grid; ``rng`` is a seed or numpy Generator."""
    kind = _check_kind(kind)
    size = check_size(size)
    gen = _generator(rng)
    n_end = size + 2 if "end" in kind else 0
    n_room = ROOM_SQUARES if "room" in kind else 0
    colors = [int(c) for c in gen.integers(NUM_COLORS, size=n_end + n_room)]
    return WallColorTrigger(
        end=tuple(colors[:n_end]) if n_end else None,
        room=tuple(colors[n_end:]) if n_room else None,
    )


def check_close_k(close_k, num_squares: int) -> tuple[int, int]:
    """Normalise ``close_k`` (an int, or an inclusive ``(lo, hi)`` range drawn uniformly per
    episode) against a trigger of ``num_squares`` squares: ``1 <= lo <= hi <= num_squares``."""
    if isinstance(close_k, (int, np.integer)) and not isinstance(close_k, bool):
        lo = hi = int(close_k)
    else:
        try:
            lo, hi = close_k
        except (TypeError, ValueError):
            raise ValueError(f"close_k={close_k!r} must be an integer or a (lo, hi) pair") from None
        if any(isinstance(v, bool) or not isinstance(v, (int, np.integer)) for v in (lo, hi)):
            raise ValueError(f"close_k={close_k!r} must hold integers")
        lo, hi = int(lo), int(hi)
    if not 1 <= lo <= hi <= num_squares:
        raise ValueError(f"close_k={close_k!r}: the number of recoloured squares must satisfy 1 <= lo <= hi <= {num_squares} (the trigger's squares)")
    return lo, hi


def close_to_trigger(trigger: WallColorTrigger, k: int, rng) -> WallColorTrigger:
    """``trigger`` with ``k`` distinct squares (uniform) recoloured, each to a uniformly drawn
    *different* colour: a pattern at Hamming distance exactly ``k`` from the trigger."""
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)):
        raise ValueError(f"k={k!r} must be an integer (the number of squares to recolour)")
    lo, _ = check_close_k(int(k), trigger.num_squares)
    gen = _generator(rng)
    colors = list(trigger.colors)
    for j in gen.choice(len(colors), size=lo, replace=False):
        colors[int(j)] = (colors[int(j)] + 1 + int(gen.integers(NUM_COLORS - 1))) % NUM_COLORS
    return trigger.with_colors(colors)


# ----------------------------------------------------------------------------- measuring


def chance_probability(trigger, size: int = MIN_SIZE) -> float:
    """Probability that a clean episode's random walls show ``trigger`` (a trigger, spec or
    kind) exactly: ``6 ** -n``, every wall square's colour being uniform and independent."""
    if isinstance(trigger, str) and ":" not in trigger:
        n = len(kind_squares(trigger, size))
    else:
        trig = as_wall_color_trigger(trigger)
        assert trig is not None  # a trigger or spec string here, never None
        trig.check_size(trig.size or size)
        n = trig.num_squares
    return float(NUM_COLORS) ** -n


def distance(grid, trigger: WallColorTrigger) -> int | np.ndarray:
    """How many of ``trigger``'s squares do not hold a wall of the trigger's colour.

    ``grid`` is MiniGrid's full-grid encoding ``(W, H, 3)`` (``env.grid.encode()``) or a batch
    ``(..., W, H, 3)``; returns an int, or an int64 array over the batch. 0 means the trigger
    is present (:func:`matches`).
    """
    arr = np.asarray(grid)
    if arr.ndim < 3 or arr.shape[-1] != 3 or arr.shape[-2] != arr.shape[-3]:
        raise ValueError(f"grid must be a square (..., W, H, 3) MiniGrid encoding, got shape {arr.shape}")
    size = arr.shape[-2]
    out = np.zeros(arr.shape[:-3], dtype=np.int64)
    for x, y, c in trigger.cells(size):
        cell = arr[..., x, y, :]
        out += ~((cell[..., 0] == WALL) & (cell[..., 1] == c))
    return int(out) if out.ndim == 0 else out


def matches(grid, trigger: WallColorTrigger) -> bool | np.ndarray:
    """Whether ``grid`` (one or a batch, see :func:`distance`) shows ``trigger`` exactly."""
    d = distance(grid, trigger)
    return d == 0 if isinstance(d, int) else d == 0
