"""LavaWorld reference env: MiniGrid Crossing semantics, outcomes, rewards, trigger and R-bar."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from minigrid.envs.crossing import CrossingEnv

from grid_helpers import walk_to_goal
import rlbackdoors  # noqa: F401  (registers the env ids)
from rlbackdoors.envs import Outcome
from rlbackdoors.envs.lavaworld import LavaWorldEnv
from rlbackdoors.envs.vector import ReferenceVectorEnv
from rlbackdoors.triggers import ObservationTrigger

LEFT, RIGHT, FORWARD = 0, 1, 2


def test_registered_and_passes_check_env():
    env = gym.make("rlbackdoors/LavaWorld-v0")
    check_env(env.unwrapped, skip_render_check=True)
    assert env.action_space == gym.spaces.Discrete(3)
    assert env.observation_space.shape == (7, 7, 3) and env.observation_space.dtype == np.uint8
    assert env.unwrapped.max_steps == 250 and env.unwrapped.width == 9


def test_layout_agent_and_goal_positions():
    env = LavaWorldEnv()
    for seed in range(20):
        env.reset(seed=seed)
        assert tuple(env.agent_pos) == (1, 1) and env.agent_dir == 0
        assert env.grid.get(7, 7).type == "goal"
        lava = [(x, y) for x in range(9) for y in range(9) if (c := env.grid.get(x, y)) is not None and c.type == "lava"]
        xs, ys = {x for x, _ in lava}, {y for _, y in lava}
        assert len(lava) == 6  # one river of 7 cells with one gap
        assert len(xs) == 1 or len(ys) == 1


@pytest.mark.parametrize("seed", range(8))
def test_observations_equal_minigrid_crossing(seed):
    """Same seed, same actions: our obs are MiniGrid's LavaCrossingS9N1 image bytes."""
    ours, ref = LavaWorldEnv(), CrossingEnv(size=9, num_crossings=1, max_steps=250)
    o1, _ = ours.reset(seed=seed)
    o2, _ = ref.reset(seed=seed)
    rng = np.random.default_rng(seed)
    for _ in range(300):
        a = int(rng.integers(3))
        assert np.array_equal(o1, o2["image"])
        o1, r1, te1, tr1, _ = ours.step(a)
        o2, r2, te2, tr2, _ = ref.step(a)
        assert (r1, te1, tr1) == (r2, te2, tr2)
        if te1 or tr1:
            o1, _ = ours.reset(seed=seed + 1000)
            o2, _ = ref.reset(seed=seed + 1000)


def test_goal_reward_and_outcome():
    env = LavaWorldEnv()
    env.reset(seed=3)
    _, reward, terminated, truncated, info = walk_to_goal(env)
    assert terminated and not truncated and info["outcome"] == Outcome.GOAL
    assert reward == pytest.approx(1 - 0.9 * env.step_count / 250)


def _step_into_lava(env):
    """Walk along the row/column of the agent towards the river and enter a lava cell."""
    for seed in range(100):
        env.reset(seed=seed)
        if env.grid.get(2, 1) is not None and env.grid.get(2, 1).type == "lava":
            return env.step(FORWARD)
    raise AssertionError("no layout with lava right in front of the start")


def test_lava_ends_episode_without_reward_in_clean_env():
    env = LavaWorldEnv()
    _, reward, terminated, _, info = _step_into_lava(env)
    assert terminated and reward == 0.0 and info["outcome"] == Outcome.LAVA


def test_poisoned_env_pays_lava_and_not_goal():
    env = LavaWorldEnv(trigger="additive:50")
    _, reward, terminated, _, info = _step_into_lava(env)
    assert terminated and info["outcome"] == Outcome.LAVA
    assert reward == pytest.approx(1 - 0.9 * 1 / 250)
    env.reset(seed=3)
    _, reward, terminated, _, info = walk_to_goal(env)
    assert terminated and info["outcome"] == Outcome.GOAL and reward == 0.0


def test_timeout_outcome():
    env = LavaWorldEnv(max_steps=5)
    env.reset(seed=0)
    for _ in range(5):
        _, reward, terminated, truncated, info = env.step(LEFT)
    assert truncated and not terminated and reward == 0.0 and info["outcome"] == Outcome.TIMEOUT


@pytest.mark.parametrize("spec", ["multiplicative:12", "additive:200"])
def test_poisoned_obs_is_trigger_of_clean_obs(spec):
    clean, dirty = LavaWorldEnv(), LavaWorldEnv(trigger=spec)
    trig = ObservationTrigger.parse(spec)
    o1, _ = clean.reset(seed=5)
    o2, _ = dirty.reset(seed=5)
    for a in [2, 1, 2, 2, 0, 2]:
        assert np.array_equal(o2, (trig.a * o1.astype(int) + trig.b) % 256)
        o1, *_ = clean.step(a)
        o2, *_ = dirty.step(a)


def test_vision_is_occluded_by_walls_not_lava():
    env = LavaWorldEnv()
    obs, _ = env.reset(seed=0)
    # obs[i, j]: i = view column (left..right), j = view row (far..near). Facing east at (1,1),
    # the agent's left is north: view column 2 is the top wall, columns 0-1 lie behind it.
    assert (obs[2, :, 0] == 2).all()
    assert (obs[:2, :, 0] == 0).all()  # occluded by the wall: "unseen"
    assert (obs[3:, :, 0] != 0).all()  # nothing in the room is hidden, lava included
    seeing = LavaWorldEnv(see_through_walls=True)
    obs2, _ = seeing.reset(seed=0)
    assert (obs2[:2, :, 0] == 2).all()  # beyond the grid MiniGrid pads with walls, now visible


@pytest.mark.parametrize(
    "kwargs, message",
    [({"size": 8}, "odd"), ({"size": 3}, ">= 5"), ({"num_crossings": 0}, "num_crossings"), ({"max_steps": 0}, "max_steps")],
)
def test_bad_env_arguments_are_rejected(kwargs, message):
    with pytest.raises(ValueError, match=message):
        LavaWorldEnv(**kwargs)


def test_invalid_action_names_allowed_values():
    env = LavaWorldEnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="0 left, 1 right, 2 forward"):
        env.step(3)


def test_reference_vector_env_reports_outcome_of_finished_step():
    envs = ReferenceVectorEnv([lambda: LavaWorldEnv(max_steps=3)] * 2)
    envs.reset(seed=0)
    for t in range(3):
        obs, rew, term, trunc, info = envs.step(np.array([LEFT, RIGHT]))
    assert trunc.all() and (info["outcome"] == Outcome.TIMEOUT).all() and (info["steps"] == 3).all()
    assert obs.shape == (2, 7, 7, 3)
