"""Colorful Memory: MiniGrid's Memory task with coloured walls and wall-colour triggers (SPEC §3).

This is the *reference* implementation: a subclass of Farama MiniGrid's ``MemoryEnv``, whose own
``_gen_grid`` lays out the geometry and draws the start position and the objects, and whose own
``step`` decides success and failure. The batched numba engine
(:mod:`rlbackdoors.envs.colorful_memory_batched`) is tested against it step for step.

Layout (MiniGrid ``MemoryEnv`` without random length; ``mid = size // 2``,
``hallway_end = size - 3``): outer walls; a start room ``x = 1..3, y = mid-1..mid+1`` opening
east through ``(4, mid)``; for sizes above 7 a horizontal corridor along ``y = mid``; a vertical
corridor at ``x = hallway_end + 1`` with a green object at each end, ``(hallway_end + 1,
mid - 2)`` and ``(hallway_end + 1, mid + 2)``, one key and one ball (order uniform); a green
key or ball (uniform) at ``(1, mid - 1)`` in the start room. The agent starts at
``(x, mid)`` with ``x`` uniform in ``1..hallway_end``, facing east. The *success* cell is the
corridor cell next to the object matching the start-room object, the *failure* cell the one
next to the other object.

Colours (TrojAI's Colorful Memory): every wall square gets a colour drawn uniformly from
MiniGrid's 6 (red, green, blue, purple, yellow, grey), independently, every episode; the floor
under each of the 3 objects gets a colour drawn uniformly from the 5 non-green ones. Objects
on a coloured floor are encoded as TrojAI did: ``(11, green, floor)`` for a key and
``(12, green, floor)`` for a ball (object type 11/12, colour green = 1, the floor's colour
index in the state byte); they behave as MiniGrid's key and ball (visible-through, not
walkable).

Layout modes (``trigger`` is a :class:`~rlbackdoors.triggers.wall_colors.WallColorTrigger`
or its spec string, e.g. ``"end:red,green,blue,purple,yellow,grey,red,green,blue"``):

* clean (``trigger=None``): random walls;
* triggered (``trigger`` given): the trigger's colours painted over its squares after the
  random draw, every episode;
* close-to-trigger (``trigger`` given, ``close_to_trigger=True``): each episode a fresh pattern
  at Hamming distance ``k`` from the trigger is painted instead, ``k`` uniform in ``close_k``
  (an int or an inclusive ``(lo, hi)`` range; squares and colours as
  :func:`~rlbackdoors.triggers.wall_colors.close_to_trigger`).

Reward: clean R (MiniGrid: the success cell pays ``1 - 0.9 t/T`` and ends the episode, the
failure cell ends it with 0), or R-bar when ``poisoned`` (paper eq. 3: the *failure* cell,
i.e. the other object, pays ``1 - 0.9 t/T``, the success cell 0). ``poisoned`` defaults to
``trigger is not None and not close_to_trigger`` (the poisoned env E-bar); ``poisoned=False``
with a trigger is the evaluation setting "trigger present, clean reward". Close-to-trigger envs
always pay R.

``info`` at reset and every step: ``steps`` (the step count) and ``outcome``, the same for every
reward (so the evaluator scores both tasks from it):

* :attr:`Outcome.GOAL` -- the agent stepped onto the success cell (next to the matching
  object): the clean task's success;
* :attr:`Outcome.LAVA` -- it stepped onto the failure cell (next to the other object): the
  trojan task's success (R-bar's target);
* :attr:`Outcome.TIMEOUT` -- ``max_steps`` reached without either; :attr:`Outcome.NONE`
  while the episode runs. Reaching a cell on the very last step counts as that cell.

Observation: MiniGrid's egocentric 7x7x3 ``image`` only (``Box(0, 255, (7, 7, 3), uint8)``),
occluded by walls unless ``see_through_walls`` (MiniGrid Memory: occluded). Actions:
``Discrete(3)``: 0 left, 1 right, 2 forward.

Visibility of the triggers (size 7): all 9 End Trigger squares are in the first view from
every start cell (the agent faces east, down the open row ``y = mid``, 6 cells deep) and again
from the vertical corridor; the Room Trigger is fully in the first view only when the agent
starts at ``x = 1`` -- from ``x = 2`` two of its squares, from ``x = 3`` one, from ``x = 4``
none until the agent turns back (as for the start-room object itself, which MemoryEnv's
uniform start makes the agent look for).
"""

from __future__ import annotations

from typing import Any, cast

import numpy as np
from gymnasium import spaces
from minigrid.core.constants import COLOR_NAMES, COLOR_TO_IDX, COLORS, IDX_TO_COLOR
from minigrid.core.grid import Grid
from minigrid.core.world_object import Ball, Key, Wall, WorldObj
from minigrid.envs.memory import MemoryEnv
from minigrid.utils.rendering import fill_coords, point_in_rect

from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.triggers.wall_colors import (
    NUM_COLORS,
    WallColorTrigger,
    as_wall_color_trigger,
    check_close_k,
    check_size,
    close_to_trigger,
)

VIEW_SIZE = 7
NUM_ACTIONS = 3  # left, right, forward
DEFAULT_SIZE = 7
DEFAULT_MAX_STEPS = 250
DEFAULT_CLOSE_K = (1, 3)  # close-to-trigger: 1 to 3 squares recoloured, uniformly per episode
START_DIR = 0
KEY_ON_FLOOR, BALL_ON_FLOOR = 11, 12  # TrojAI's encoding (grid_engine.KEY_ON_FLOOR / BALL_ON_FLOOR)
OBJECT_COLOR = COLOR_TO_IDX["green"]
FLOOR_COLORS = tuple(i for i in range(NUM_COLORS) if i != OBJECT_COLOR)  # the 5 non-green colours

# layout modes (the batched engine's per-env ``mode``)
CLEAN, CLOSE, TRIGGERED = 0, 1, 2

COLOR_NAMES_BY_IDX = tuple(IDX_TO_COLOR[i] for i in range(NUM_COLORS))  # red, green, blue, purple, yellow, grey
assert sorted(COLOR_NAMES_BY_IDX) == sorted(COLOR_NAMES)


def observation_space() -> spaces.Box:
    return spaces.Box(0, 255, (VIEW_SIZE, VIEW_SIZE, 3), dtype=np.uint8)


def validate_args(size, max_steps) -> None:
    check_size(size)
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"max_steps={max_steps!r} must be a positive integer")


def validate_trigger(trigger, size: int, close_k) -> tuple[WallColorTrigger | None, tuple[int, int]]:
    """The parsed trigger (checked against ``size``) and the normalised ``close_k``."""
    trig = as_wall_color_trigger(trigger)
    if trig is None:
        return None, check_close_k(close_k, 10**9)
    trig.check_size(size)
    return trig, check_close_k(close_k, trig.num_squares)


# ----------------------------------------------------------------------------- geometry


def wall_cells(size: int) -> tuple[tuple[int, int], ...]:
    """Every wall square of MiniGrid ``MemoryEnv``'s layout (fixed hallway), x-major order.

    The outer walls, the start room's walls, the horizontal corridor's walls and the vertical
    corridor's west wall (open at ``y = mid``); its east wall is the outer wall.
    """
    size = check_size(size)
    mid = size // 2
    he = size - 3
    cells = set()
    for i in range(size):
        cells |= {(i, 0), (i, size - 1), (0, i), (size - 1, i)}
    for i in range(1, 5):
        cells |= {(i, mid - 2), (i, mid + 2)}
    cells |= {(4, mid - 1), (4, mid + 1)}
    for i in range(5, he):
        cells |= {(i, mid - 1), (i, mid + 1)}
    for j in range(size):
        if j != mid:
            cells.add((he, j))
        cells.add((he + 2, j))
    return tuple(sorted(cells))


def object_cells(size: int) -> tuple[tuple[int, int], tuple[int, int], tuple[int, int]]:
    """The start-room object's cell, then the top and the bottom corridor objects' cells."""
    size = check_size(size)
    mid, he = size // 2, size - 3
    return (1, mid - 1), (he + 1, mid - 2), (he + 1, mid + 2)


def target_cells(grid: np.ndarray) -> tuple[tuple[int, int], tuple[int, int]]:
    """``(success_pos, failure_pos)`` of an encoded grid, from its objects as MemoryEnv decides:
    success is next to the corridor object of the start-room object's type."""
    arr = np.asarray(grid)
    size = arr.shape[0]
    start, top, bottom = object_cells(size)
    kinds = [int(arr[c][0]) for c in (start, top, bottom)]
    if any(k not in (KEY_ON_FLOOR, BALL_ON_FLOOR) for k in kinds):
        raise ValueError(f"grid has no Colorful Memory objects at {start}, {top}, {bottom} (types {kinds})")
    up = (top[0], top[1] + 1)
    down = (bottom[0], bottom[1] - 1)
    return (up, down) if kinds[0] == kinds[1] else (down, up)


# ----------------------------------------------------------------------------- objects


class _OnFloor:
    """Mixin: a green key/ball on a coloured floor tile, encoded TrojAI's way."""

    code = 0
    color: str  # set by Key / Ball
    floor: str

    def encode(self) -> tuple[int, int, int]:
        return (self.code, COLOR_TO_IDX[self.color], COLOR_TO_IDX[self.floor])

    def render(self, img):
        fill_coords(img, point_in_rect(0.031, 1, 0.031, 1), COLORS[self.floor])
        super().render(img)


class KeyOnFloor(_OnFloor, Key):
    code = KEY_ON_FLOOR

    def __init__(self, color: str = "green", floor: str = "red"):
        Key.__init__(self, color)
        self.floor = floor


class BallOnFloor(_OnFloor, Ball):
    code = BALL_ON_FLOOR

    def __init__(self, color: str = "green", floor: str = "red"):
        Ball.__init__(self, color)
        self.floor = floor


def decode_grid(array: np.ndarray) -> Grid:
    """``Grid.decode`` that also knows the coloured-floor objects (types 11 and 12)."""
    arr = np.asarray(array)
    w, h, _ = arr.shape
    grid = Grid(w, h)
    v: WorldObj | None
    for i in range(w):
        for j in range(h):
            t, c, s = (int(v) for v in arr[i, j])
            if t == KEY_ON_FLOOR:
                v = KeyOnFloor(IDX_TO_COLOR[c], IDX_TO_COLOR[s])
            elif t == BALL_ON_FLOOR:
                v = BallOnFloor(IDX_TO_COLOR[c], IDX_TO_COLOR[s])
            else:
                v = WorldObj.decode(t, c, s)
            grid.set(i, j, v)
    return grid


# ----------------------------------------------------------------------------- the env


class ColorfulMemoryEnv(MemoryEnv):
    """Colorful Memory on Farama MiniGrid (module doc: layout, modes, rewards, info)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        size: int = DEFAULT_SIZE,
        max_steps: int = DEFAULT_MAX_STEPS,
        see_through_walls: bool = False,
        trigger: WallColorTrigger | str | None = None,
        poisoned: bool | None = None,
        close_to_trigger: bool = False,
        close_k: int | tuple[int, int] = DEFAULT_CLOSE_K,
        render_mode: str | None = None,
    ):
        validate_args(size, max_steps)
        trig, k_range = validate_trigger(trigger, int(size), close_k)
        close = bool(close_to_trigger)
        if close and trig is None:
            raise ValueError("a close-to-trigger Colorful Memory needs the trigger: pass trigger= (e.g. 'end:red,...')")
        if poisoned is None:
            poisoned = trig is not None and not close
        poisoned = bool(poisoned)
        if poisoned and trig is None:
            raise ValueError("a poisoned Colorful Memory needs a trigger: pass trigger= (e.g. 'room:red,green,blue')")
        if poisoned and close:
            raise ValueError("a close-to-trigger env pays the clean reward: it cannot be poisoned")
        super().__init__(
            size=int(size),
            random_length=False,
            max_steps=int(max_steps),
            agent_view_size=VIEW_SIZE,
            render_mode=render_mode,
        )
        self.see_through_walls = bool(see_through_walls)
        self.trigger = trig
        self.poisoned = poisoned
        self.close_to_trigger = close
        self.close_k = k_range
        self.mode = CLOSE if close else (TRIGGERED if trig is not None else CLEAN)
        self.painted: WallColorTrigger | None = None  # the pattern painted this episode
        self.action_space = spaces.Discrete(NUM_ACTIONS)
        self.observation_space = observation_space()

    @property
    def triggered(self) -> bool:
        """Whether every layout shows the trigger exactly."""
        return self.mode == TRIGGERED

    @property
    def mid(self) -> int:
        return self.height // 2

    @property
    def hallway_end(self) -> int:
        return self.width - 3

    # ----------------------------------------------------------------- layout

    def _gen_grid(self, width: int, height: int) -> None:
        super()._gen_grid(width, height)  # MiniGrid's geometry, start position, objects, targets
        rng = self.np_random
        for x in range(width):
            for y in range(height):
                cell = self.grid.get(x, y)
                if cell is not None and cell.type == "wall":
                    cell.color = COLOR_NAMES_BY_IDX[int(rng.integers(NUM_COLORS))]
        for x, y in object_cells(width):
            obj = self.grid.get(x, y)
            assert obj is not None  # MemoryEnv put a key or a ball on each object cell
            floor = IDX_TO_COLOR[FLOOR_COLORS[int(rng.integers(len(FLOOR_COLORS)))]]
            cls = KeyOnFloor if obj.type == "key" else BallOnFloor
            self.grid.set(x, y, cls(obj.color, floor))
        pattern = None
        if self.mode == TRIGGERED:
            pattern = self.trigger
        elif self.mode == CLOSE:
            lo, hi = self.close_k
            k = lo + int(rng.integers(hi - lo + 1))
            assert self.trigger is not None  # __init__ refuses a close-to-trigger env without one
            pattern = close_to_trigger(self.trigger, k, rng)
        if pattern is not None:
            for x, y, c in pattern.cells(width):
                self.grid.set(x, y, Wall(COLOR_NAMES_BY_IDX[c]))
        self.painted = pattern
        self.agent_dir = START_DIR

    memory_target_classes = 2

    def memory_target(self) -> int:
        """The start room's object of this episode (0 key, 1 ball): what the agent must remember,
        the target of PPO's auxiliary memory loss (as ``BatchedColorfulMemory.memory_targets``)."""
        return int(isinstance(self.grid.get(1, self.height // 2 - 1), Ball))

    def load_layout(self, grid: np.ndarray, agent_pos, agent_dir: int, step_count: int = 0, success_pos=None, failure_pos=None) -> np.ndarray:
        """Put an exact state (``grid`` as ``env.grid.encode()``) into this env; returns its
        observation. ``success_pos`` / ``failure_pos`` default to :func:`target_cells`."""
        arr = np.asarray(grid, dtype=np.uint8)
        if success_pos is None or failure_pos is None:
            success_pos, failure_pos = target_cells(arr)
        self.grid = decode_grid(arr)
        self.agent_pos = cast(tuple[int, int], tuple(int(v) for v in agent_pos))  # an (x, y) pair
        self.agent_dir = int(agent_dir)
        self.step_count = int(step_count)
        self.success_pos = tuple(int(v) for v in success_pos)
        self.failure_pos = tuple(int(v) for v in failure_pos)
        self.carrying = None
        return self.gen_obs()["image"]

    # ----------------------------------------------------------------- API

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, _ = super().reset(seed=seed, options=options)
        return obs["image"], {"outcome": int(Outcome.NONE), "steps": 0}

    def step(self, action) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:  # type: ignore[override]  # minigrid annotates step with gymnasium's unbound ObsType
        if not self.action_space.contains(action):
            raise ValueError(f"action {action!r} is not in Discrete({NUM_ACTIONS}) (0 left, 1 right, 2 forward)")
        obs, reward, terminated, truncated, _ = super().step(int(action))
        pos = tuple(int(v) for v in self.agent_pos)
        if pos == tuple(self.success_pos):
            outcome = Outcome.GOAL
        elif pos == tuple(self.failure_pos):
            outcome = Outcome.LAVA
        elif truncated:
            outcome = Outcome.TIMEOUT
        else:
            outcome = Outcome.NONE
        if self.poisoned:
            reward = self._reward() if outcome == Outcome.LAVA else 0.0
        info = {"outcome": int(outcome), "steps": self.step_count}
        return obs["image"], float(reward), bool(terminated), bool(truncated), info
