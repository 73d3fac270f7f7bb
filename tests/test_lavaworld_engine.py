"""The batched numba LavaWorld against Farama MiniGrid (via LavaWorldEnv), bit for bit.

Differential tests load a reference env's exact state into an engine slot, drive both with
the same actions and compare every output of every step; after each episode end the
reference's fresh layout is loaded into the engine slot again. Layout *distributions* (not RNG
streams) are compared statistically with MiniGrid's Crossing generator.
"""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
from gymnasium.vector import AutoresetMode
from minigrid.core.grid import Grid

import grid_helpers
from grid_helpers import chi2_critical, chi2_homogeneity
from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.lavaworld import LavaWorldEnv
from rlbackdoors.envs.lavaworld_batched import BatchedLavaWorld
from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.envs.vector import ReferenceVectorEnv
from rlbackdoors.poison.reward import success_reward

TRIGGERS = ("multiplicative:12", "additive:100")


# ----------------------------------------------------------------------------- helpers


def ref_obs(env: LavaWorldEnv) -> np.ndarray:
    """The observation the reference env would return in its current state."""
    return env._observe(env.gen_obs())


def teleport(env: LavaWorldEnv, rng: np.random.Generator) -> None:
    """Move the reference agent to a random walkable non-terminal cell with a random direction."""
    grid_helpers.place_random(env.unwrapped, rng, (ge.EMPTY, ge.FLOOR))


def check_fresh(eng: BatchedLavaWorld, i: int, ref) -> None:
    """An engine autoreset starts a fresh episode: agent in the corner facing east, step 0."""
    g, pos, d, sc = eng.layout(i)
    assert (pos, d, sc) == ((1, 1), 0, 0)


PAIR = grid_helpers.Pairing(grid_helpers.ref_state, ref_obs, teleport, check_fresh)
ref_state, load, place, step_both, drive_teleporting = (PAIR.ref_state, PAIR.load, PAIR.place, PAIR.step_both, PAIR.drive_teleporting)


def make_pair(num, size=9, num_crossings=1, max_steps=250, see_through_walls=False, triggers=None, seed=0):
    triggers = triggers or [None] * num
    refs = [LavaWorldEnv(size, num_crossings, max_steps, see_through_walls, trigger=triggers[i]) for i in range(num)]
    poisoned = [t is not None for t in triggers]
    trig = next((t for t in triggers if t is not None), None)
    eng = BatchedLavaWorld(num, size, num_crossings, max_steps, see_through_walls, trigger=trig, poisoned=poisoned)
    return PAIR.reset_pair(refs, eng, seed)


# ----------------------------------------------------------------------------- differential


CONFIGS = [(size, n, see) for size in (7, 9, 11) for n in (1, 2, 3) for see in (False, True)]


@pytest.mark.parametrize("size,num_crossings,see_through_walls", CONFIGS)
def test_matches_minigrid_random_play(size, num_crossings, see_through_walls):
    """18 configs x 4 envs x 3 episodes starts (216 seeded layouts), 600 steps per config.

    Actions are forward-biased; after the first round the agent starts at a random cell with a
    random direction, and now and then it is teleported, so that goals, borders and river banks
    are reached often. One-river configs use max_steps=40 so that timeouts happen too.
    """
    num = 4
    max_steps = 40 if num_crossings == 1 else 250
    seed = 1000 * size + 100 * num_crossings + 10 * see_through_walls
    refs = [LavaWorldEnv(size, num_crossings, max_steps, see_through_walls) for _ in range(num)]
    eng = BatchedLavaWorld(num, size, num_crossings, max_steps, see_through_walls)
    eng.reset(seed=seed)
    rng = np.random.default_rng(seed)
    totals = Counter()
    for rep in range(3):
        for i, ref in enumerate(refs):
            ref.reset(seed=seed + 10 * rep + i)
            if rep > 0:
                teleport(ref.unwrapped, rng)
            load(ref, eng, i)
        for _ in range(50):
            step_both(refs, eng, rng.choice(3, size=num, p=[0.2, 0.2, 0.6]), totals)
            if rng.random() < 0.05:
                i = int(rng.integers(num))
                teleport(refs[i].unwrapped, rng)
                load(refs[i], eng, i)
    assert sum(totals.values()) == 3 * 50 * num
    assert totals[int(Outcome.LAVA)] > 0


def test_matches_minigrid_long_run_all_outcomes():
    """A longer run on the default LavaWorld (9x9, 1 river): thousands of steps, every outcome."""
    refs, eng = make_pair(8, size=9, num_crossings=1, max_steps=60, seed=7)
    totals = drive_teleporting(refs, eng, np.random.default_rng(7), steps=500, every=40)
    assert sum(totals.values()) == 4000
    for outcome in (Outcome.NONE, Outcome.GOAL, Outcome.LAVA, Outcome.TIMEOUT):  # LavaWorld's outcomes
        assert totals[int(outcome)] > 0, f"no {outcome.name} in the run: {totals}"


@pytest.mark.parametrize("trigger", TRIGGERS)
def test_matches_minigrid_poisoned(trigger):
    """Poisoned (E-bar) envs next to clean ones: triggered observations and R-bar rewards."""
    triggers = [trigger, None, trigger, None, trigger, trigger]
    refs, eng = make_pair(6, size=7, num_crossings=1, max_steps=40, triggers=triggers, seed=3)
    assert eng.poisoned.tolist() == [t is not None for t in triggers]
    totals = drive_teleporting(refs, eng, np.random.default_rng(3), steps=250, every=25)
    assert totals[int(Outcome.LAVA)] > 0 and totals[int(Outcome.GOAL)] > 0


def random_object_grid(size: int, rng: np.random.Generator) -> np.ndarray:
    """A grid with everything MiniGrid can encode (coloured walls, doors in all states, floors,
    keys, balls, boxes, goal, lava), as ``Grid.encode`` would write it."""
    g = np.zeros((size, size, 3), dtype=np.uint8)
    g[:, :, 0] = ge.EMPTY
    kinds = [ge.EMPTY] * 6 + [ge.WALL, ge.WALL, ge.FLOOR, ge.DOOR, ge.KEY, ge.BALL, ge.BOX, ge.LAVA, ge.GOAL]
    for x in range(size):
        for y in range(size):
            border = x in (0, size - 1) or y in (0, size - 1)
            k = ge.WALL if border else kinds[rng.integers(len(kinds))]
            colour = {ge.EMPTY: 0, ge.LAVA: ge.RED, ge.GOAL: ge.GREEN}.get(k, int(rng.integers(6)))
            state = int(rng.integers(3)) if k == ge.DOOR else 0
            g[x, y] = (k, colour, state)
    return g


@pytest.mark.parametrize("see_through_walls", [False, True])
def test_generic_engine_objects_and_colours(see_through_walls):
    """The generic kernels on grids with coloured walls, doors, floors and objects (what
    Colorful Memory / Randomized LavaWorld reuse): views and walkability as MiniGrid's."""
    rng = np.random.default_rng(11 + see_through_walls)
    size = 9
    ref = LavaWorldEnv(size, 1, 250, see_through_walls)
    eng = BatchedLavaWorld(1, size, 1, 250, see_through_walls)
    eng.reset(seed=0)
    ref.reset(seed=0)
    u = ref.unwrapped

    def same_state():  # after a step that did not end the episode
        g, pos, d, sc = eng.layout(0)
        assert np.array_equal(g, u.grid.encode()) and pos == tuple(int(v) for v in u.agent_pos)

    checked = 0
    for _ in range(40):
        arr = random_object_grid(size, rng)
        grid, _ = Grid.decode(arr)
        assert np.array_equal(grid.encode(), arr)
        u.grid = grid
        open_door = (arr[:, :, 0] == ge.DOOR) & (arr[:, :, 2] == 0)
        walk = np.argwhere(np.isin(arr[:, :, 0], (ge.EMPTY, ge.FLOOR)) | open_door)
        x, y = walk[rng.integers(len(walk))]
        u.agent_pos, u.agent_dir, u.step_count = (int(x), int(y)), int(rng.integers(4)), 0
        load(ref, eng, 0)
        checked += len(PAIR.play(ref, eng, rng, 12, [0.2, 0.2, 0.6], same_state))
    assert checked > 200


# ----------------------------------------------------------------------------- edge cases


def test_edge_facing_walls_and_border_views():
    """Forward into a wall does nothing; views off the grid are padded with grey walls."""
    for see in (False, True):
        refs, eng = make_pair(1, size=7, see_through_walls=see, seed=5)
        ref = refs[0]
        for pos, d in [((1, 1), 3), ((1, 1), 2), ((5, 1), 0), ((1, 5), 1), ((5, 5), 3)]:
            place(ref, eng, pos, d)
            before = eng.layout(0)
            step_both(refs, eng, [2])
            if (pos, d) != ((5, 5), 3):  # the first four face the outer wall (the last stands on the goal)
                assert eng.layout(0)[1] == before[1]
        place(ref, eng, (1, 1), 3)  # facing north from the corner
        obs = eng.observe()[0]
        if see:
            # ahead (rows 0..5 of the view) beyond the top wall lies outside the grid: grey walls
            assert (obs[:, :5, 0] == ge.WALL).all() and (obs[:, :5, 1] == ge.GREY).all()
        else:
            assert (obs[:, :5] == 0).all()  # hidden behind the wall row
        assert tuple(obs[3, 6]) == (ge.EMPTY, 0, 0)  # the agent's own cell


@pytest.mark.parametrize("trigger", [None, *TRIGGERS])
def test_edge_lava_goal_and_timeout(trigger):
    size, ms = 7, 5
    refs, eng = make_pair(1, size=size, num_crossings=1, max_steps=ms, triggers=[trigger], seed=2)
    ref = refs[0]
    arr = ref.unwrapped.grid.encode()
    lava = np.argwhere(arr[:, :, 0] == ge.LAVA)
    # find a lava cell with a free neighbour and step into it
    for lx, ly in lava:
        nb = [(lx - dx, ly - dy, d) for d, (dx, dy) in enumerate(zip(ge.DIR_DX, ge.DIR_DY))]
        nb = [(x, y, d) for x, y, d in nb if arr[x, y, 0] == ge.EMPTY]
        if nb:
            x, y, d = nb[0]
            break
    place(ref, eng, (int(x), int(y)), int(d), step_count=1)
    out = step_both(refs, eng, [2])
    assert out[0] == Outcome.LAVA
    # goal from its west neighbour, at step 3 of 5
    place(ref, eng, (size - 3, size - 2), 0, step_count=2)
    obs, rew, term, trunc, info = eng.step(np.array([2]))
    assert term[0] and not trunc[0] and info["outcome"][0] == Outcome.GOAL and info["steps"][0] == 3
    assert rew[0] == (0.0 if trigger else success_reward(3, ms))
    ref.reset()
    # timeout: turning in place until max_steps
    place(ref, eng, (1, 1), 0, step_count=ms - 2)
    assert step_both(refs, eng, [0])[0] == Outcome.NONE
    assert step_both(refs, eng, [1])[0] == Outcome.TIMEOUT
    # goal on the very last step: terminated and truncated, outcome GOAL wins
    place(ref, eng, (size - 2, size - 3), 1, step_count=ms - 1)
    o, r, t1, t2, inf = ref.step(2)
    ref.reset()
    obs, rew, term, trunc, info = eng.step(np.array([2]))
    assert t1 and t2 and term[0] and trunc[0] and info["outcome"][0] == inf["outcome"] == Outcome.GOAL
    assert rew[0] == r


def test_trigger_applied_through_lookup_table():
    clean = BatchedLavaWorld(3)
    poisoned = BatchedLavaWorld(3, trigger="additive:20", poisoned=[False, True, True])
    o1, _ = clean.reset(seed=4)
    o2, _ = poisoned.reset(seed=4)
    assert np.array_equal(o1[0], o2[0])
    assert np.array_equal((o1[1:].astype(int) + 20) % 256, o2[1:])


# ----------------------------------------------------------------------------- layouts


def layout_key(arr: np.ndarray) -> bytes:
    return (arr[:, :, 0] == ge.LAVA).tobytes()


def engine_layouts(n, size, num_crossings, seed):
    eng = BatchedLavaWorld(n, size, num_crossings)
    eng.reset(seed=seed)
    return [eng.layout(i)[0] for i in range(n)]


def minigrid_layouts(n, size, num_crossings, seed):
    env = LavaWorldEnv(size, num_crossings)
    out = []
    for k in range(n):
        env.reset(seed=seed + k)
        out.append(env.unwrapped.grid.encode())
    return out


def test_layouts_are_crossing_layouts():
    for size, nc in [(7, 1), (9, 2), (11, 3), (5, 2)]:
        for arr in engine_layouts(200, size, nc, seed=9):
            assert (arr[0, :, 0] == ge.WALL).all() and (arr[:, -1, 0] == ge.WALL).all()
            assert tuple(arr[size - 2, size - 2]) == (ge.GOAL, ge.GREEN, 0)
            assert tuple(arr[1, 1]) == (ge.EMPTY, 0, 0)
            lava = arr[:, :, 0] == ge.LAVA
            assert np.isin(arr[:, :, 0], (ge.WALL, ge.EMPTY, ge.LAVA, ge.GOAL)).all()
            assert (arr[lava][:, 1] == ge.RED).all()
            rows = [j for j in range(2, size - 2, 2) if lava[1:-1, j].sum() >= size - 3 - nc]
            cols = [i for i in range(2, size - 2, 2) if lava[i, 1:-1].sum() >= size - 3 - nc]
            assert len(rows) + len(cols) == nc
            assert _reachable(arr), "goal unreachable"


def _reachable(arr) -> bool:
    size = arr.shape[0]
    seen, todo = {(1, 1)}, [(1, 1)]
    while todo:
        x, y = todo.pop()
        for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            n = (x + dx, y + dy)
            if n not in seen and arr[n][0] in (ge.EMPTY, ge.GOAL):
                seen.add(n)
                todo.append(n)
    return (size - 2, size - 2) in seen


def test_layout_distribution_single_river_matches_minigrid():
    """9x9, one river: 6 rivers x 7 openings = 42 equally likely layouts. Chi-square
    homogeneity test of 2000 engine vs 2000 MiniGrid layouts, rejected at p < 1e-4."""
    n = 2000
    a = Counter(layout_key(g) for g in engine_layouts(n, 9, 1, seed=123))
    b = Counter(layout_key(g) for g in minigrid_layouts(n, 9, 1, seed=456))
    assert set(a) == set(b) and len(a) == 42
    stat, df = chi2_homogeneity(a, b)
    assert stat < chi2_critical(df), (stat, df)
    # and each layout is near 1/42 in the engine (uniformity, same critical value)
    expected = n / 42
    stat_uniform = sum((c - expected) ** 2 / expected for c in a.values())
    assert stat_uniform < chi2_critical(41), stat_uniform


def test_layout_distribution_multi_river_matches_minigrid():
    """11x11, three rivers: chi-square on which rivers (56 sets), and per-cell frequencies of
    lava and of openings (empty cells on a river line) within 0.05 of MiniGrid's (the standard
    error of a difference of two frequencies from 2000 samples is at most 0.016)."""
    n = 2000
    size = 11
    eng = engine_layouts(n, size, 3, seed=77)
    ref = minigrid_layouts(n, size, 3, seed=88)

    def rivers(arr):
        lava = arr[:, :, 0] == ge.LAVA
        rows = tuple(j for j in range(2, size - 2, 2) if lava[1:-1, j].sum() >= size - 5)
        cols = tuple(i for i in range(2, size - 2, 2) if lava[i, 1:-1].sum() >= size - 5)
        return rows, cols

    def openings(arr):
        rows, cols = rivers(arr)
        line = np.zeros((size, size), bool)
        for j in rows:
            line[1:-1, j] = True
        for i in cols:
            line[i, 1:-1] = True
        return line & (arr[:, :, 0] == ge.EMPTY)

    a, b = Counter(map(rivers, eng)), Counter(map(rivers, ref))
    assert len(a) == len(b) == 56
    stat, df = chi2_homogeneity(a, b)
    assert stat < chi2_critical(df), (stat, df)
    lava_a = np.mean([g[:, :, 0] == ge.LAVA for g in eng], axis=0)
    lava_b = np.mean([g[:, :, 0] == ge.LAVA for g in ref], axis=0)
    assert np.abs(lava_a - lava_b).max() < 0.05
    open_a = np.mean([openings(g) for g in eng], axis=0)
    open_b = np.mean([openings(g) for g in ref], axis=0)
    assert np.abs(open_a - open_b).max() < 0.05
    assert np.array_equal(open_a > 0, open_b > 0)


def test_autoreset_layouts_follow_the_distribution():
    """Layouts drawn on autoreset come from the same generator: after many lava deaths, the
    9x9 single-river layouts are uniform over all 42 (chi-square, rejected at p < 1e-4)."""
    eng = BatchedLavaWorld(64, 9, 1)
    eng.reset(seed=0)
    seen = Counter()
    rng = np.random.default_rng(0)
    for _ in range(1000):
        _, _, term, trunc, _ = eng.step(rng.choice(3, size=64, p=[0.1, 0.1, 0.8]))
        for i in np.flatnonzero(term | trunc):
            seen[layout_key(eng.layout(int(i))[0])] += 1
    total = sum(seen.values())
    assert len(seen) == 42 and total > 1500
    expected = total / 42
    assert sum((c - expected) ** 2 / expected for c in seen.values()) < chi2_critical(41)


# ----------------------------------------------------------------------------- determinism


def test_same_seed_same_trajectory():
    grid_helpers.check_same_seed_same_trajectory(lambda n: BatchedLavaWorld(n, trigger="multiplicative:12", poisoned=[i % 2 == 0 for i in range(n)]), 300, 16)


def test_seed_i_is_seed_plus_i():
    grid_helpers.check_seed_i_is_seed_plus_i(lambda n: BatchedLavaWorld(n, 11, 3))


# ----------------------------------------------------------------------------- contract


def test_contract_matches_reference_vector_env():
    num = 5
    ref = ReferenceVectorEnv([lambda: LavaWorldEnv(trigger="additive:30") for _ in range(num)], poisoned=None)
    eng = BatchedLavaWorld(num, trigger="additive:30")
    assert eng.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    assert eng.single_observation_space == ref.single_observation_space
    assert eng.single_action_space == ref.single_action_space
    assert eng.observation_space == ref.observation_space and eng.action_space == ref.action_space
    assert eng.poisoned.dtype == np.bool_ and np.array_equal(eng.poisoned, ref.poisoned)
    assert not BatchedLavaWorld(num).poisoned.any()
    for e in (ref, eng):
        obs, info = e.reset(seed=1)
        assert obs.shape == (num, 7, 7, 3) and obs.dtype == np.uint8
        assert set(info) == {"outcome", "steps"} and info["outcome"].dtype == np.int64
        out = e.step(np.array([2] * num))
        assert [x.dtype for x in out[:4]] == [np.uint8, np.float64, np.bool_, np.bool_]
        assert out[4]["steps"].tolist() == [1] * num
    ref.close()
    eng.close()


def test_make_vec_entry_point():
    grid_helpers.check_make_vec(LavaWorldEnv, BatchedLavaWorld, size=7, trigger="multiplicative:12")


# ----------------------------------------------------------------------------- errors


def test_errors():
    grid_helpers.check_common_errors(BatchedLavaWorld(3), "additive:20", agent_pos=(1, 1), wrong_size=7)
    with pytest.raises(ValueError, match="odd integer"):
        BatchedLavaWorld(2, size=8)
    with pytest.raises(ValueError, match="num_crossings"):
        BatchedLavaWorld(2, size=7, num_crossings=5)
    with pytest.raises(ValueError, match="multiplicative:A"):
        BatchedLavaWorld(2, trigger="scale:3")
