"""LavaWorld: MiniGrid's lava Crossing with 3 actions and an observation trigger (SPEC §1).

This is the *reference* implementation, built on Farama MiniGrid itself so that it is
exactly the environment the paper and the TrojAI round used. Passing a ``trigger``
turns it into the poisoned env E-bar: the trigger is applied to every observation
and the reward becomes R-bar (lava pays, the goal pays nothing).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from gymnasium import spaces
from minigrid.envs.crossing import CrossingEnv

from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.envs.rewards import poisoned_reward
from rlbackdoors.triggers.observation import ObservationTrigger

VIEW_SIZE = 7
NUM_ACTIONS = 3  # left, right, forward: the paper drops MiniGrid's other four
DEFAULT_SIZE = 9
DEFAULT_CROSSINGS = 1
DEFAULT_MAX_STEPS = 250


def as_trigger(trigger: ObservationTrigger | str | None) -> ObservationTrigger | None:
    """Accept a trigger object or its ``kind:value`` spec (what ``gym.make`` kwargs carry)."""
    if trigger is None or isinstance(trigger, ObservationTrigger):
        return trigger
    return ObservationTrigger.parse(trigger)


def validate_crossing_layout(size: int, num_crossings: int, max_steps: int) -> None:
    """Reject configurations MiniGrid would fail on later with an assert or a hang."""
    if not isinstance(size, int) or size < 5 or size % 2 == 0:
        raise ValueError(f"size={size!r} must be an odd integer >= 5 (MiniGrid Crossing)")
    max_rivers = 2 * ((size - 3) // 2)
    if not isinstance(num_crossings, int) or not 1 <= num_crossings <= max_rivers:
        raise ValueError(f"num_crossings={num_crossings!r} must be in 1..{max_rivers} for size {size}")
    if not isinstance(max_steps, int) or max_steps < 1:
        raise ValueError(f"max_steps={max_steps!r} must be a positive integer")


class LavaWorldEnv(CrossingEnv):
    """Clean (``trigger=None``) or poisoned LavaWorld on Farama MiniGrid.

    Observation: MiniGrid's egocentric 7x7x3 uint8 encoding (object, colour, state).
    ``info["outcome"]`` is an :class:`Outcome` (GOAL / LAVA / TIMEOUT at episode end).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        size: int = DEFAULT_SIZE,
        num_crossings: int = DEFAULT_CROSSINGS,
        max_steps: int = DEFAULT_MAX_STEPS,
        see_through_walls: bool = False,
        trigger: ObservationTrigger | str | None = None,
        render_mode: str | None = None,
    ):
        validate_crossing_layout(size, num_crossings, max_steps)
        super().__init__(
            size=size,
            num_crossings=num_crossings,
            max_steps=max_steps,
            render_mode=render_mode,
        )
        self.see_through_walls = bool(see_through_walls)
        self.trigger = as_trigger(trigger)
        self.action_space = spaces.Discrete(NUM_ACTIONS)
        self.observation_space = spaces.Box(0, 255, (VIEW_SIZE, VIEW_SIZE, 3), dtype=np.uint8)

    @property
    def poisoned(self) -> bool:
        return self.trigger is not None

    def _observe(self, obs: dict) -> np.ndarray:
        image = obs["image"]
        return self.trigger.apply(image) if self.trigger is not None else image

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, _ = super().reset(seed=seed, options=options)
        return self._observe(obs), {"outcome": int(Outcome.NONE), "steps": 0}

    def step(self, action) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:  # type: ignore[override]  # minigrid annotates step with gymnasium's unbound ObsType
        if not self.action_space.contains(action):
            raise ValueError(f"action {action!r} is not in Discrete({NUM_ACTIONS}) (0 left, 1 right, 2 forward)")
        obs, reward, terminated, truncated, _ = super().step(int(action))
        outcome = Outcome.NONE
        if terminated:
            cell = self.grid.get(*self.agent_pos)
            outcome = Outcome.GOAL if cell is not None and cell.type == "goal" else Outcome.LAVA
        elif truncated:
            outcome = Outcome.TIMEOUT
        if self.poisoned:
            reward = poisoned_reward(outcome, self.step_count, self.max_steps)
        info = {"outcome": int(outcome), "steps": self.step_count}
        return self._observe(obs), float(reward), terminated, truncated, info
