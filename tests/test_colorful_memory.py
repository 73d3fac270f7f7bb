"""The Colorful Memory reference env (MiniGrid's MemoryEnv with coloured walls and wall-colour triggers)."""

from collections import Counter

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from minigrid.envs.memory import MemoryEnv

from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.colorful_memory import (
    BALL_ON_FLOOR,
    KEY_ON_FLOOR,
    ColorfulMemoryEnv,
    decode_grid,
    object_cells,
    target_cells,
    wall_cells,
)
from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.poison.reward import success_reward
from rlbackdoors.triggers.wall_colors import WallColorTrigger, distance, end_squares, room_squares

END9 = "end:red,green,blue,purple,yellow,grey,red,green,blue"
ROOM = "room:purple,yellow,red"
BOTH = "end+room:grey,grey,blue,blue,red,red,green,green,yellow;yellow,blue,red"


@pytest.mark.parametrize("size", [7, 9, 11, 13])
def test_geometry_is_minigrid_memory(size):
    """Walls, objects (types and places), start cell and direction, success and failure cells
    are those of MiniGrid's own MemoryEnv for the same seed; only colours differ."""
    for seed in range(6):
        mg = MemoryEnv(size=size, max_steps=250)
        mg.reset(seed=seed)
        cm = ColorfulMemoryEnv(size=size)
        cm.reset(seed=seed)
        a, b = mg.grid.encode(), cm.grid.encode()
        assert {tuple(map(int, c)) for c in np.argwhere(a[:, :, 0] == ge.WALL)} == set(wall_cells(size))
        assert np.array_equal(a[:, :, 0] == ge.WALL, b[:, :, 0] == ge.WALL)
        for x, y in object_cells(size):
            assert b[x, y, 0] == {ge.KEY: KEY_ON_FLOOR, ge.BALL: BALL_ON_FLOOR}[a[x, y, 0]]
            assert a[x, y, 1] == b[x, y, 1] == ge.GREEN
        assert ((a[:, :, 0] == ge.EMPTY) == (b[:, :, 0] == ge.EMPTY)).all()
        assert tuple(mg.agent_pos) == tuple(cm.agent_pos) and mg.agent_dir == cm.agent_dir == 0
        assert (mg.success_pos, mg.failure_pos) == (cm.success_pos, cm.failure_pos) == target_cells(b)


def test_check_env_and_spaces():
    for kw in ({}, {"trigger": END9}, {"trigger": ROOM, "close_to_trigger": True}, {"size": 9, "max_steps": 40}):
        env = ColorfulMemoryEnv(**kw)
        check_env(env, skip_render_check=True)
        assert env.observation_space.shape == (7, 7, 3) and env.observation_space.dtype == np.uint8
        assert env.action_space.n == 3
    env = ColorfulMemoryEnv()
    assert (env.width, env.max_steps, env.see_through_walls, env.poisoned, env.trigger) == (7, 250, False, False, None)


def test_colours_and_encoding():
    env = ColorfulMemoryEnv()
    walls = Counter()
    floors = Counter()
    for seed in range(300):
        obs, info = env.reset(seed=seed)
        assert info == {"outcome": 0, "steps": 0} and obs.shape == (7, 7, 3) and obs.dtype == np.uint8
        g = env.grid.encode()
        w = g[g[:, :, 0] == ge.WALL]
        assert (w[:, 2] == 0).all()
        walls.update(w[:, 1].tolist())
        for x, y in object_cells(7):
            t, c, floor = g[x, y]
            assert t in (KEY_ON_FLOOR, BALL_ON_FLOOR) and c == ge.GREEN and floor != ge.GREEN and floor < 6
            floors[int(floor)] += 1
        assert {g[c][0] for c in object_cells(7)[1:]} == {KEY_ON_FLOOR, BALL_ON_FLOOR}
    assert set(walls) == set(range(6)) and min(walls.values()) > 0.8 * sum(walls.values()) / 6
    assert set(floors) == {0, 2, 3, 4, 5}


def test_objects_are_in_the_observation_with_their_floor():
    env = ColorfulMemoryEnv()
    for seed in range(50):
        env.reset(seed=seed)
        if tuple(env.agent_pos) == (1, 3):
            break
    else:
        raise AssertionError("no start at x = 1 in 50 seeds")
    obs = env.gen_obs()["image"]
    g = env.grid.encode()
    vx, vy = env.relative_coords(1, 2)
    assert tuple(obs[vx, vy]) == tuple(g[1, 2]) and obs[vx, vy, 0] in (KEY_ON_FLOOR, BALL_ON_FLOOR)
    # the Room Trigger's squares are all in the first view when the agent starts at x = 1
    for x, y in room_squares(7):
        vx, vy = env.relative_coords(x, y)
        assert tuple(obs[vx, vy]) == (ge.WALL, g[x, y, 1], 0)


def test_decode_grid_round_trip():
    env = ColorfulMemoryEnv(trigger=BOTH)
    env.reset(seed=4)
    g = env.grid.encode()
    assert np.array_equal(decode_grid(g).encode(), g)
    env.render_mode = "rgb_array"
    img = env.render()
    assert img.ndim == 3 and img.shape[2] == 3


@pytest.mark.parametrize("spec", [END9, ROOM, BOTH])
def test_triggered_and_poisoned_envs_paint_the_trigger(spec):
    t = WallColorTrigger.parse(spec)
    for poisoned in (True, False):
        env = ColorfulMemoryEnv(trigger=spec, poisoned=poisoned)
        assert env.poisoned == poisoned and env.triggered and not env.close_to_trigger
        for seed in range(30):
            env.reset(seed=seed)
            g = env.grid.encode()
            assert distance(g, t) == 0 and env.painted == t
            for x, y, c in t.cells(7):
                assert tuple(g[x, y]) == (ge.WALL, c, 0)
    assert ColorfulMemoryEnv(trigger=spec).poisoned  # poisoned by default


@pytest.mark.parametrize("spec, close_k", [(END9, (1, 3)), (ROOM, 1), (BOTH, (2, 5)), (ROOM, (3, 3))])
def test_close_to_trigger_envs(spec, close_k):
    t = WallColorTrigger.parse(spec)
    env = ColorfulMemoryEnv(trigger=spec, close_to_trigger=True, close_k=close_k)
    assert not env.poisoned and not env.triggered and env.close_to_trigger
    lo, hi = (close_k, close_k) if isinstance(close_k, int) else close_k
    ks = Counter()
    patterns = set()
    for seed in range(120):
        env.reset(seed=seed)
        d = distance(env.grid.encode(), t)
        assert lo <= d <= hi and d == sum(a != b for a, b in zip(env.painted.colors, t.colors))
        ks[d] += 1
        patterns.add(env.painted)
    assert set(ks) == set(range(lo, hi + 1)) and len(patterns) > 10


def test_clean_env_shows_the_trigger_only_by_chance():
    t = WallColorTrigger.parse(END9)
    env = ColorfulMemoryEnv()
    d = Counter()
    for seed in range(300):
        env.reset(seed=seed)
        d[distance(env.grid.encode(), t)] += 1
    assert d[0] == 0 and sum(d.values()) == 300 and max(d, key=d.get) in (7, 8)  # Binomial(9, 5/6) mode: 8


def step_to(env, pos, d, step_count=0):
    env.agent_pos, env.agent_dir, env.step_count = pos, d, step_count


@pytest.mark.parametrize("poisoned", [False, True])
def test_rewards_and_outcomes(poisoned):
    env = ColorfulMemoryEnv(trigger=END9, poisoned=poisoned, max_steps=20)
    env.reset(seed=2)
    he, mid = 4, 3
    # from the junction, walk to the success cell
    sx, sy = env.success_pos
    d = 3 if sy < mid else 1
    step_to(env, (he + 1, mid), d, step_count=6)
    obs, r, term, trunc, info = env.step(2)
    assert term and not trunc and info == {"outcome": int(Outcome.GOAL), "steps": 7}
    assert r == (0.0 if poisoned else float(success_reward(7, 20)))
    # and to the failure cell (the other object)
    env.reset(seed=2)
    fx, fy = env.failure_pos
    step_to(env, (he + 1, mid), 3 if fy < mid else 1, step_count=3)
    obs, r, term, trunc, info = env.step(2)
    assert term and info["outcome"] == Outcome.LAVA
    assert r == (float(success_reward(4, 20)) if poisoned else 0.0)
    # the objects themselves block the way: from the success cell, forward into the object
    env.reset(seed=2)
    step_to(env, (sx, sy), d, step_count=0)
    obs, r, term, trunc, info = env.step(2)  # standing on the success cell already: it counts again
    assert tuple(env.agent_pos) == (sx, sy) and term and info["outcome"] == Outcome.GOAL
    # timeout
    env.reset(seed=2)
    step_to(env, (1, mid), 0, step_count=18)
    assert env.step(0)[4]["outcome"] == Outcome.NONE
    obs, r, term, trunc, info = env.step(0)
    assert trunc and not term and r == 0.0 and info == {"outcome": int(Outcome.TIMEOUT), "steps": 20}
    # success on the very last step: terminated and truncated, the cell wins
    env.reset(seed=2)
    step_to(env, (he + 1, mid), d, step_count=19)
    obs, r, term, trunc, info = env.step(2)
    assert term and trunc and info["outcome"] == Outcome.GOAL
    assert r == (0.0 if poisoned else float(success_reward(20, 20)))


def test_random_play_outcomes_and_determinism():
    def run(seed):
        env = ColorfulMemoryEnv(trigger=ROOM, max_steps=30)
        env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        out, outcomes = [], Counter()
        for _ in range(600):
            obs, r, term, trunc, info = env.step(int(rng.choice(3, p=[0.2, 0.2, 0.6])))
            out.append((obs.tobytes(), r, term, trunc, info["outcome"]))
            outcomes[info["outcome"]] += 1
            if term or trunc:
                env.reset()
        return out, outcomes

    a, outcomes = run(1)
    assert run(1)[0] == a and run(2)[0] != a
    assert outcomes[int(Outcome.GOAL)] > 0 and outcomes[int(Outcome.LAVA)] > 0 and outcomes[int(Outcome.TIMEOUT)] > 0


def test_trigger_visibility_from_each_start():
    """Size 7: the End Trigger is in every first view; the Room Trigger fully only from x = 1."""
    env = ColorfulMemoryEnv(trigger=BOTH)
    env.reset(seed=0)
    for x, room_seen in ((1, 3), (2, 2), (3, 1), (4, 0)):
        step_to(env, (x, 3), 0)
        obs = env.gen_obs()["image"]

        def shown(cells):
            rcs = [env.relative_coords(cx, cy) for cx, cy in cells]
            return sum(rc is not None and obs[rc[0], rc[1], 0] == ge.WALL for rc in rcs)

        assert (shown(end_squares(7)), shown(room_squares(7))) == (9, room_seen)


def test_end_trigger_is_in_view_from_the_corridor():
    env = ColorfulMemoryEnv(trigger=END9)
    env.reset(seed=0)
    g = env.grid.encode()
    seen = set()
    for pos, d in (((5, 3), 0), ((5, 2), 3), ((5, 4), 1), ((5, 3), 3), ((5, 3), 1)):
        step_to(env, pos, d)
        obs = env.gen_obs()["image"]
        for x, y in end_squares(7):
            rc = env.relative_coords(x, y)
            if rc is not None and obs[rc[0], rc[1], 0] == ge.WALL:
                assert obs[rc[0], rc[1], 1] == g[x, y, 1]
                seen.add((x, y))
    assert seen == set(end_squares(7))


def test_errors():
    with pytest.raises(ValueError, match=r"size=8 must be an odd integer >= 7"):
        ColorfulMemoryEnv(size=8)
    with pytest.raises(ValueError, match=r"size=5 must be an odd integer >= 7"):
        ColorfulMemoryEnv(size=5)
    with pytest.raises(ValueError, match=r"size=True"):
        ColorfulMemoryEnv(size=True)
    with pytest.raises(ValueError, match="max_steps"):
        ColorfulMemoryEnv(max_steps=0)
    with pytest.raises(ValueError, match="poisoned Colorful Memory needs a trigger"):
        ColorfulMemoryEnv(poisoned=True)
    with pytest.raises(ValueError, match="close-to-trigger Colorful Memory needs the trigger"):
        ColorfulMemoryEnv(close_to_trigger=True)
    with pytest.raises(ValueError, match="cannot be poisoned"):
        ColorfulMemoryEnv(trigger=ROOM, close_to_trigger=True, poisoned=True)
    with pytest.raises(ValueError, match="9x9 Colorful Memory's End Trigger has 11 squares"):
        ColorfulMemoryEnv(size=9, trigger=END9)
    with pytest.raises(ValueError, match="names a kind but no colours"):
        ColorfulMemoryEnv(trigger="end")
    with pytest.raises(ValueError, match="'pink' is not one of red, green"):
        ColorfulMemoryEnv(trigger="room:pink,red,red")
    with pytest.raises(ValueError, match=r"close_k=\(1, 4\).*<= 3"):
        ColorfulMemoryEnv(trigger=ROOM, close_to_trigger=True, close_k=(1, 4))
    env = ColorfulMemoryEnv()
    env.reset(seed=0)
    for bad in (3, -1, 1.5):
        with pytest.raises(ValueError, match=r"Discrete\(3\) \(0 left, 1 right, 2 forward\)"):
            env.step(bad)
    with pytest.raises(ValueError, match="no Colorful Memory objects"):
        target_cells(np.ones((7, 7, 3), dtype=np.uint8))


def test_gymnasium_ids_and_parse_trigger():
    import gymnasium as gym

    import rlbackdoors.envs  # noqa: F401  (registers the ids)
    from rlbackdoors.envs.colorful_memory import ColorfulMemoryEnv
    from rlbackdoors.envs.colorful_memory_batched import BatchedColorfulMemory
    from rlbackdoors.worlds import parse_trigger

    assert isinstance(gym.make("rlbackdoors/ColorfulMemory-v0").unwrapped, ColorfulMemoryEnv)
    vec = gym.make_vec("rlbackdoors/ColorfulMemory-v0", num_envs=3)
    assert isinstance(vec, BatchedColorfulMemory) and vec.reset(seed=0)[0].shape == (3, 7, 7, 3)
    spec = "room:red,green,blue"
    assert parse_trigger("colorful-memory", spec).spec() == spec
