"""Randomized LavaWorld reference env (MiniGrid): layouts, trigger insertion, rewards, flags."""

import numpy as np
import pytest
from gymnasium import spaces
from gymnasium.utils.env_checker import check_env
from minigrid.core.grid import Grid
from minigrid.core.world_object import Wall

from grid_helpers import walk_to_goal
from rlbackdoors.envs.grid_engine import EMPTY, GOAL, LAVA, WALL
from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.envs.randomized_lavaworld import (
    RandomizedLavaWorldEnv,
    initial_view_cells,
    max_solvable_lava,
    solvable,
)
from rlbackdoors.poison.reward import success_reward
from rlbackdoors.triggers.pattern import PatternTrigger, find_pattern

LEFT, RIGHT, FORWARD = 0, 1, 2


@pytest.mark.parametrize(
    "kwargs",
    [{}, {"trigger": "cross"}, {"trigger": "arrow", "see_through_walls": False}, {"trigger": "arrow:west", "poisoned": False}],
)
def test_passes_check_env(kwargs):
    env = RandomizedLavaWorldEnv(**kwargs)
    check_env(env, skip_render_check=True)
    assert env.action_space == spaces.Discrete(3)
    assert set(env.observation_space.spaces) == {"image", "direction"}
    assert env.observation_space["image"] == spaces.Box(0, 255, (7, 7, 3), np.uint8)
    assert env.observation_space["direction"] == spaces.Discrete(4)
    assert env.max_steps == 250 and env.width == 11 and env.num_lava == 10
    assert env.see_through_walls == kwargs.get("see_through_walls", True)


def lava_mask(env) -> np.ndarray:
    return env.grid.encode()[:, :, 0] == LAVA


@pytest.mark.parametrize("size, num_lava, trigger", [(11, 10, None), (11, 10, "cross"), (11, 10, "arrow"), (7, 5, "cross"), (7, 5, None)])
def test_layout_facts(size, num_lava, trigger):
    env = RandomizedLavaWorldEnv(size, num_lava, trigger=trigger)
    view = initial_view_cells(size)
    rotations = {r.cells for r in PatternTrigger.parse(trigger).rotations()} if trigger else set()
    for seed in range(40):
        obs, info = env.reset(seed=seed)
        arr = env.grid.encode()
        assert tuple(env.agent_pos) == (1, 1) and env.agent_dir == 0 and obs["direction"] == 0
        assert tuple(arr[size - 2, size - 2]) == (GOAL, 1, 0)
        assert (arr[0, :, 0] == WALL).all() and (arr[-1, :, 0] == WALL).all()
        assert (arr[:, 0, 0] == WALL).all() and (arr[:, -1, 0] == WALL).all()
        assert np.isin(arr[1:-1, 1:-1, 0], (EMPTY, LAVA, GOAL)).all()
        lava = arr[:, :, 0] == LAVA
        assert lava.sum() == num_lava and (arr[lava] == (LAVA, 0, 0)).all()  # all lava alike
        assert not lava[1, 1] and solvable(lava)
        cells = env.pattern_cells
        if trigger is None:
            assert cells == frozenset() and not info["trigger_visible"] and not info["saw_trigger"]
            continue
        assert all(lava[c] for c in cells) and (1, 1) not in cells and (size - 2, size - 2) not in cells
        ox, oy = min(x for x, _ in cells), min(y for _, y in cells)
        shape = {(x - ox, y - oy) for x, y in cells}
        assert any(shape == {(dx - min(a for a, _ in r), dy - min(b for _, b in r)) for dx, dy in r} for r in rotations)
        assert cells & view, "no pattern cell in the first view"
        assert info["trigger_visible"] and info["saw_trigger"]  # seen at reset
        assert find_pattern(lava, trigger) >= 1


def test_arrow_any_direction_draws_all_four():
    env = RandomizedLavaWorldEnv(trigger="arrow")
    seen = {env.reset(seed=s) and env.pattern_rotation for s in range(60)}
    assert seen == {0, 1, 2, 3}
    fixed = RandomizedLavaWorldEnv(trigger="arrow:south")
    fixed.reset(seed=0)
    lava = lava_mask(fixed)
    assert find_pattern(lava, "arrow:south") >= 1


def test_validation_errors():
    with pytest.raises(ValueError, match=r"num_lava=2 is smaller than the trigger pattern 'cross' \(5 lava cells"):
        RandomizedLavaWorldEnv(7, 2, trigger="cross")
    with pytest.raises(ValueError, match=r"num_lava=70 must be an integer in 0\.\.64 for size 11"):
        RandomizedLavaWorldEnv(11, 70)
    assert max_solvable_lava(11) == 64 and max_solvable_lava(5) == 4
    with pytest.raises(ValueError, match="size"):
        RandomizedLavaWorldEnv(4, 1)
    with pytest.raises(ValueError, match="max_steps"):
        RandomizedLavaWorldEnv(max_steps=0)
    with pytest.raises(ValueError, match="needs a trigger"):
        RandomizedLavaWorldEnv(poisoned=True)
    with pytest.raises(ValueError, match="must be 'cross'"):
        RandomizedLavaWorldEnv(trigger="plus")
    env = RandomizedLavaWorldEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="0 left, 1 right, 2 forward"):
        env.step(3)


def test_impossible_layout_names_size_and_lava():
    # in a 5x5 room the anti-diagonal can only sit across the middle, where it walls the start in
    env = RandomizedLavaWorldEnv(5, 3, trigger="cells:0,2;1,1;2,0")
    with pytest.raises(RuntimeError, match=r"no solvable 5x5 layout with num_lava=3 with trigger 'cells:0,2;1,1;2,0'"):
        env.reset(seed=0)


def test_maximum_lava_is_solvable():
    env = RandomizedLavaWorldEnv(5, max_solvable_lava(5))
    for seed in range(3):
        env.reset(seed=seed)
        assert lava_mask(env).sum() == 4 and solvable(lava_mask(env))


# ----------------------------------------------------------------------------- rewards


def set_layout(env, lava=(), pattern=(), pos=(1, 1), d=0, steps=0):
    """Put a hand-made layout into a reset env: ``lava`` and ``pattern`` cells are lava."""
    size = env.width
    arr = np.zeros((size, size, 3), np.uint8)
    arr[:, :, 0] = EMPTY
    arr[[0, -1], :, 0] = WALL
    arr[:, [0, -1], 0] = WALL
    arr[[0, -1], :, 1] = 5
    arr[:, [0, -1], 1] = 5
    for c in (*lava, *pattern):
        arr[c] = (LAVA, 0, 0)
    arr[size - 2, size - 2] = (GOAL, 1, 0)
    env.grid, _ = Grid.decode(arr)
    env.pattern_cells = frozenset(pattern)
    env.agent_pos, env.agent_dir, env.step_count = pos, d, steps


CROSS_AT_5_2 = [(5, 1), (4, 2), (5, 2), (6, 2), (5, 3)]


@pytest.mark.parametrize("poisoned", [False, True])
def test_rewards_and_outcomes(poisoned):
    env = RandomizedLavaWorldEnv(trigger="cross", poisoned=poisoned)
    assert env.poisoned is poisoned and env.triggered
    env.reset(seed=0)
    # pattern lava straight ahead
    set_layout(env, lava=[(2, 5)], pattern=CROSS_AT_5_2, pos=(3, 2), d=0, steps=9)
    _, r, term, trunc, info = env.step(FORWARD)
    assert term and not trunc and info["outcome"] == Outcome.PATTERN_LAVA and info["steps"] == 10
    assert r == (pytest.approx(float(success_reward(10, 250))) if poisoned else 0.0)
    # plain lava
    env.reset(seed=0)
    set_layout(env, lava=[(2, 5)], pattern=CROSS_AT_5_2, pos=(2, 4), d=1, steps=3)
    _, r, term, _, info = env.step(FORWARD)
    assert term and info["outcome"] == Outcome.LAVA and r == 0.0
    # goal
    env.reset(seed=0)
    set_layout(env, pattern=CROSS_AT_5_2, pos=(8, 9), d=0, steps=19)
    _, r, term, _, info = env.step(FORWARD)
    assert term and info["outcome"] == Outcome.GOAL
    assert r == (0.0 if poisoned else pytest.approx(1 - 0.9 * 20 / 250))
    # timeout
    env.reset(seed=0)
    set_layout(env, pattern=CROSS_AT_5_2, pos=(1, 1), d=0, steps=249)
    _, r, term, trunc, info = env.step(LEFT)
    assert trunc and not term and info["outcome"] == Outcome.TIMEOUT and r == 0.0


def test_clean_env_lava_and_goal():
    env = RandomizedLavaWorldEnv()
    assert not env.poisoned and not env.triggered
    env.reset(seed=1)
    set_layout(env, lava=[(2, 1)], pos=(1, 1), d=0, steps=0)
    _, r, term, _, info = env.step(FORWARD)
    assert term and r == 0.0 and info["outcome"] == Outcome.LAVA
    env.reset(seed=1)
    _, r, term, _, info = walk_to_goal(env)
    assert term and info["outcome"] == Outcome.GOAL and r == pytest.approx(1 - 0.9 * env.step_count / 250)


def test_poisoned_goal_pays_nothing_on_a_real_layout():
    env = RandomizedLavaWorldEnv(trigger="cross")
    env.reset(seed=4)
    _, r, term, _, info = walk_to_goal(env)
    assert term and info["outcome"] == Outcome.GOAL and r == 0.0 and info["saw_trigger"]


# ----------------------------------------------------------------------------- trigger flags


def test_flags_follow_the_observation():
    env = RandomizedLavaWorldEnv(trigger="cross", poisoned=False)
    env.reset(seed=0)
    set_layout(env, pattern=CROSS_AT_5_2, pos=(1, 1), d=1)
    env.saw_trigger = False
    # facing east from (1, 1) the view spans x 1..7, y -2..4: the whole cross
    _, _, _, _, info = env.step(LEFT)
    assert env.agent_dir == 0 and info["trigger_visible"] and info["saw_trigger"]
    # facing north it spans x -2..4, y -5..1: no cross cell (the nearest is (4, 2))
    _, _, _, _, info = env.step(LEFT)
    assert not info["trigger_visible"] and info["saw_trigger"]  # remembered for the episode
    # facing west it spans x -5..1: nothing
    _, _, _, _, info = env.step(LEFT)
    assert not info["trigger_visible"] and info["saw_trigger"]
    # facing south it spans x -2..4, y 1..7: (4, 2) is in view
    _, _, _, _, info = env.step(LEFT)
    assert info["trigger_visible"]
    obs, info = env.reset(seed=0)
    assert info["saw_trigger"] is info["trigger_visible"] is True  # reset starts afresh, pattern in view
    env.saw_trigger = False
    set_layout(env, pattern=CROSS_AT_5_2, pos=(1, 1), d=3)
    _, _, _, _, info = env.step(LEFT)
    assert not info["trigger_visible"] and not info["saw_trigger"]


def test_standing_on_a_pattern_cell_is_not_seeing_it():
    env = RandomizedLavaWorldEnv(trigger=[(1, 1)], poisoned=True, num_lava=10)
    env.reset(seed=0)
    set_layout(env, pattern=[(3, 1)], pos=(2, 1), d=0)
    obs, r, term, _, info = env.step(FORWARD)
    assert term and info["outcome"] == Outcome.PATTERN_LAVA and r > 0
    assert tuple(obs["image"][3, 6]) == (EMPTY, 0, 0)  # the agent's own cell
    assert not info["trigger_visible"]  # the only pattern cell is under the agent


@pytest.mark.parametrize("see_through_walls", [False, True])
def test_occluded_pattern_is_not_visible(see_through_walls):
    """An interior wall between agent and pattern hides it only under MiniGrid occlusion."""
    env = RandomizedLavaWorldEnv(trigger="cross", see_through_walls=see_through_walls)
    env.reset(seed=0)
    set_layout(env, pattern=[(5, 4), (4, 5), (5, 5), (6, 5), (5, 6)], pos=(1, 5), d=1)
    for y in range(1, 10):
        env.grid.set(3, y, Wall())
    env.saw_trigger = False
    _, _, _, _, info = env.step(LEFT)  # face east, the wall column at x = 3 is two cells ahead
    assert info["trigger_visible"] is see_through_walls
