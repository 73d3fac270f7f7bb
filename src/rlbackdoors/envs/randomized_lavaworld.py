"""Randomized LavaWorld: single lava cells at random, a lava-pattern trigger (SPEC §2).

This is the *reference* implementation, a Farama ``MiniGridEnv`` (MiniGrid's own dynamics,
view, occlusion and goal reward). The batched numba engine
(:mod:`rlbackdoors.envs.randomized_lavaworld_batched`) is tested against it step for step.

Layout: an ``N x N`` room with only the outer walls, the agent at ``(1, 1)`` facing east, the
goal at ``(N-2, N-2)``, and ``K`` single lava cells drawn uniformly among the other interior
cells; layouts with no 4-connected lava-free path from the agent to the goal are redrawn
(whole layout, at most :data:`MAX_LAYOUT_TRIES` times).

With a ``trigger`` (a :class:`~rlbackdoors.triggers.pattern.PatternTrigger`) every layout
contains the pattern: a rotation is drawn uniformly among those the trigger allows, then a
position uniformly among those that keep every pattern cell inside the room, off the start
and the goal, and at least one pattern cell inside the agent's first 7x7 view; then the
remaining ``K - |pattern|`` lava cells are drawn as above. So clean and triggered layouts
hold the same number of lava cells, and pattern cells are ordinary lava in the observation.

``poisoned`` selects the reward: clean (MiniGrid: the goal pays ``1 - 0.9 t/T``, lava ends the
episode with 0) or R-bar (entering a lava cell *of the pattern* pays ``1 - 0.9 t/T``, any other
lava and the goal end the episode with 0). ``trigger`` without ``poisoned`` is the evaluation
setting "trigger present, clean reward"; ``poisoned`` defaults to ``trigger is not None``
(the poisoned env E-bar), as in LavaWorld.

``info`` at reset and at every step:

* ``outcome`` -- :class:`Outcome` of the step just taken (``NONE`` while running; ``GOAL``,
  ``LAVA``, ``PATTERN_LAVA`` (a lava cell of the inserted pattern) or ``TIMEOUT``);
* ``steps`` -- the step count after that step;
* ``trigger_visible`` -- a pattern cell is shown (as lava) in the observation returned with
  this ``info``: the reset observation, or the observation this step returned (for a step that
  ends the episode, the terminal observation). "Shown" means inside the 7x7 view, not hidden by
  MiniGrid's occlusion (``see_through_walls=False``), and not the agent's own cell (which the
  view always shows as empty, so standing on a pattern cell does not count);
* ``saw_trigger`` -- ``trigger_visible`` was true for at least one observation of this episode
  up to and including that one (the reset observation included).

Both flags are always false without a trigger (chance occurrences of the shape in a clean
layout are not tracked; see :func:`rlbackdoors.triggers.pattern.find_pattern`).
"""

from __future__ import annotations

from collections import deque
from typing import Any

import numpy as np
from gymnasium import spaces
from minigrid.core.grid import Grid
from minigrid.core.mission import MissionSpace
from minigrid.core.world_object import Goal, Lava
from minigrid.minigrid_env import MiniGridEnv

from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.envs.rewards import success_reward
from rlbackdoors.triggers.pattern import PatternTrigger, as_pattern_trigger

VIEW_SIZE = 7
NUM_ACTIONS = 3  # left, right, forward
DEFAULT_SIZE = 11
DEFAULT_NUM_LAVA = 10
DEFAULT_MAX_STEPS = 250
MAX_LAYOUT_TRIES = 10_000
START = (1, 1)
START_DIR = 0
LAVA_OBJ = 9  # MiniGrid's OBJECT_TO_IDX["lava"]


def observation_space() -> spaces.Dict:
    return spaces.Dict(
        {
            "image": spaces.Box(0, 255, (VIEW_SIZE, VIEW_SIZE, 3), dtype=np.uint8),
            "direction": spaces.Discrete(4),
        }
    )


def max_solvable_lava(size: int) -> int:
    """The most lava an ``size x size`` room can hold with a path from start to goal left:
    the interior minus one shortest path (``2 (size-3) + 1`` cells, start and goal included)."""
    return (size - 2) ** 2 - (2 * (size - 3) + 1)


def validate_layout_args(size: int, num_lava: int, max_steps: int) -> None:
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 5:
        raise ValueError(f"size={size!r} must be an integer >= 5")
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"max_steps={max_steps!r} must be a positive integer")
    most = max_solvable_lava(int(size))
    if isinstance(num_lava, bool) or not isinstance(num_lava, (int, np.integer)) or not 0 <= num_lava <= most:
        raise ValueError(
            f"num_lava={num_lava!r} must be an integer in 0..{most} for size {size}: a {size}x{size} room has "
            f"{(size - 2) ** 2 - 2} free cells besides start and goal, and a path to the goal needs "
            f"{2 * (size - 3) - 1} of them"
        )


def initial_view_cells(size: int) -> set[tuple[int, int]]:
    """Interior cells inside the agent's 7x7 view at reset (agent at (1, 1) facing east)."""
    half = VIEW_SIZE // 2
    out = set()
    for ahead in range(VIEW_SIZE):
        for lat in range(-half, half + 1):
            # facing east: ahead is +x, the agent's right is +y
            x, y = START[0] + ahead, START[1] + lat
            if 1 <= x <= size - 2 and 1 <= y <= size - 2:
                out.add((x, y))
    return out


def pattern_placements(trigger: PatternTrigger, size: int) -> list[list[tuple[int, int]]]:
    """Per rotation of ``trigger``, the sorted list of offsets ``(ox, oy)`` where the env may put
    it (cells ``(ox+dx, oy+dy)``): inside the room, off start and goal, one cell in the first view.

    Raises ``ValueError`` when some rotation fits nowhere.
    """
    goal = (size - 2, size - 2)
    view = initial_view_cells(size)
    out = []
    for rot in trigger.rotations():
        offsets = []
        for ox in range(-2, size):
            for oy in range(-2, size):
                cells = [(ox + dx, oy + dy) for dx, dy in rot.cells]
                if not all(1 <= x <= size - 2 and 1 <= y <= size - 2 for x, y in cells):
                    continue
                if START in cells or goal in cells or not any(c in view for c in cells):
                    continue
                offsets.append((ox, oy))
        if not offsets:
            raise ValueError(f"lava pattern {rot.name!r} does not fit in a {size}x{size} room off the start and goal and inside the first view")
        out.append(offsets)
    return out


def validate_trigger(trigger: PatternTrigger | None, size: int, num_lava: int) -> list[list[tuple[int, int]]]:
    """Check that ``trigger`` can be inserted; returns :func:`pattern_placements` (``[]`` if none)."""
    if trigger is None:
        return []
    if num_lava < trigger.num_cells:
        raise ValueError(
            f"num_lava={num_lava} is smaller than the trigger pattern {trigger.spec()!r} ({trigger.num_cells} lava cells, which count toward num_lava)"
        )
    return pattern_placements(trigger, size)


def layout_error(size: int, num_lava: int, trigger: PatternTrigger | None) -> RuntimeError:
    what = f" with trigger {trigger.spec()!r}" if trigger is not None else ""
    return RuntimeError(f"no solvable {size}x{size} layout with num_lava={num_lava}{what} in {MAX_LAYOUT_TRIES} tries: lower num_lava or enlarge the room")


def solvable(lava: np.ndarray) -> bool:
    """A 4-connected path of lava-free interior cells from the start to the goal (BFS)."""
    size = lava.shape[0]
    goal = (size - 2, size - 2)
    seen = {START}
    todo = deque([START])
    while todo:
        x, y = todo.popleft()
        if (x, y) == goal:
            return True
        for nx, ny in ((x + 1, y), (x - 1, y), (x, y + 1), (x, y - 1)):
            if 1 <= nx <= size - 2 and 1 <= ny <= size - 2 and not lava[nx, ny] and (nx, ny) not in seen:
                seen.add((nx, ny))
                todo.append((nx, ny))
    return False


class RandomizedLavaWorldEnv(MiniGridEnv):
    """Randomized LavaWorld on Farama MiniGrid (module doc: layout, trigger, rewards, info).

    Observation: ``{"image": 7x7x3 uint8 (MiniGrid encoding), "direction": agent_dir 0..3}``.
    Actions: ``Discrete(3)``: 0 left, 1 right, 2 forward.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        size: int = DEFAULT_SIZE,
        num_lava: int = DEFAULT_NUM_LAVA,
        max_steps: int = DEFAULT_MAX_STEPS,
        see_through_walls: bool = True,
        trigger: PatternTrigger | str | None = None,
        poisoned: bool | None = None,
        render_mode: str | None = None,
    ):
        validate_layout_args(size, num_lava, max_steps)
        trig = as_pattern_trigger(trigger)
        self.placements = validate_trigger(trig, int(size), int(num_lava))
        poisoned = trig is not None if poisoned is None else bool(poisoned)
        if poisoned and trig is None:
            raise ValueError("a poisoned Randomized LavaWorld needs a trigger: pass trigger= (e.g. 'cross')")
        super().__init__(
            mission_space=MissionSpace(mission_func=lambda: "get to the green goal square, avoiding lava"),
            grid_size=int(size),
            max_steps=int(max_steps),
            see_through_walls=bool(see_through_walls),
            agent_view_size=VIEW_SIZE,
            render_mode=render_mode,
        )
        self.size = int(size)
        self.num_lava = int(num_lava)
        self.trigger = trig
        self.poisoned = poisoned
        self.action_space = spaces.Discrete(NUM_ACTIONS)
        self.observation_space = observation_space()
        self.pattern_cells: frozenset[tuple[int, int]] = frozenset()
        self.pattern_rotation = -1  # index into trigger.rotations() of the placed pattern
        self.saw_trigger = False

    @property
    def triggered(self) -> bool:
        """Whether layouts contain the trigger pattern."""
        return self.trigger is not None

    # ----------------------------------------------------------------- layout

    def _gen_grid(self, width: int, height: int) -> None:
        size = width
        goal = (size - 2, size - 2)
        interior = [(x, y) for x in range(1, size - 1) for y in range(1, size - 1)]
        rng = self.np_random
        for _ in range(MAX_LAYOUT_TRIES):
            pattern: list[tuple[int, int]] = []
            rotation = -1
            if self.trigger is not None:
                rotations = self.trigger.rotations()
                rotation = int(rng.integers(len(rotations)))
                offsets = self.placements[rotation]
                ox, oy = offsets[int(rng.integers(len(offsets)))]
                pattern = [(ox + dx, oy + dy) for dx, dy in rotations[rotation].cells]
            taken = set(pattern) | {START, goal}
            free = [c for c in interior if c not in taken]
            picks = rng.choice(len(free), size=self.num_lava - len(pattern), replace=False)
            lava = np.zeros((size, size), dtype=bool)
            for c in pattern:
                lava[c] = True
            for k in picks:
                lava[free[int(k)]] = True
            if solvable(lava):
                break
        else:
            raise layout_error(size, self.num_lava, self.trigger)
        self.grid = Grid(width, height)
        self.grid.wall_rect(0, 0, width, height)
        for x, y in zip(*np.nonzero(lava)):
            self.grid.set(int(x), int(y), Lava())
        self.put_obj(Goal(), *goal)
        self.agent_pos = np.array(START)
        self.agent_dir = START_DIR
        self.pattern_cells = frozenset(pattern)
        self.pattern_rotation = rotation
        self.mission = "get to the green goal square, avoiding lava"

    # ----------------------------------------------------------------- observation

    def pattern_visible(self, image: np.ndarray) -> bool:
        """Whether ``image`` (the current observation) shows a pattern cell as lava."""
        for x, y in self.pattern_cells:
            rc = self.relative_coords(x, y)
            if rc is not None and image[rc[0], rc[1], 0] == LAVA_OBJ:
                return True
        return False

    def _observe(self, obs: dict) -> tuple[dict, bool]:
        out = {"image": obs["image"], "direction": int(obs["direction"])}
        return out, self.pattern_visible(out["image"])

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, _ = super().reset(seed=seed, options=options)
        obs, visible = self._observe(obs)
        self.saw_trigger = visible
        info = {"outcome": int(Outcome.NONE), "steps": 0, "trigger_visible": visible, "saw_trigger": visible}
        return obs, info

    def step(self, action) -> tuple[dict, float, bool, bool, dict[str, Any]]:  # type: ignore[override]  # minigrid annotates step with gymnasium's unbound ObsType
        if not self.action_space.contains(action):
            raise ValueError(f"action {action!r} is not in Discrete({NUM_ACTIONS}) (0 left, 1 right, 2 forward)")
        obs, reward, terminated, truncated, _ = super().step(int(action))
        outcome = Outcome.NONE
        if terminated:
            cell = self.grid.get(*self.agent_pos)
            if cell is not None and cell.type == "goal":
                outcome = Outcome.GOAL
            elif tuple(int(v) for v in self.agent_pos) in self.pattern_cells:
                outcome = Outcome.PATTERN_LAVA
            else:
                outcome = Outcome.LAVA
        elif truncated:
            outcome = Outcome.TIMEOUT
        if self.poisoned:
            pays = outcome == Outcome.PATTERN_LAVA
            reward = float(success_reward(self.step_count, self.max_steps)) if pays else 0.0
        obs, visible = self._observe(obs)
        self.saw_trigger = self.saw_trigger or visible
        info = {
            "outcome": int(outcome),
            "steps": self.step_count,
            "trigger_visible": visible,
            "saw_trigger": self.saw_trigger,
        }
        return obs, float(reward), terminated, truncated, info
