"""The batched numba Randomized LavaWorld against the MiniGrid reference env, bit for bit.

Differential tests load a reference env's exact state (grid, agent, step count, pattern
cells, saw-trigger flag) into an engine slot, drive both with the same actions and compare
every output of every step: image bytes, direction, reward, terminated, truncated, outcome,
steps, trigger_visible, saw_trigger. After each episode end the reference's fresh layout is
loaded into the engine slot again. Layout *distributions* (not RNG streams) are compared
statistically with the reference generator.
"""

from __future__ import annotations

from collections import Counter

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode
from minigrid.core.grid import Grid

import grid_helpers
from grid_helpers import chi2_critical, chi2_homogeneity
from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.envs.randomized_lavaworld import RandomizedLavaWorldEnv, initial_view_cells, solvable
from rlbackdoors.envs.randomized_lavaworld_batched import BatchedRandomizedLavaWorld
from rlbackdoors.poison.reward import success_reward
from rlbackdoors.triggers.pattern import find_pattern

# ----------------------------------------------------------------------------- helpers


def ref_obs(env: RandomizedLavaWorldEnv) -> dict:
    """The observation the reference env would return in its current state."""
    obs, _ = env._observe(env.gen_obs())
    return obs


def same_obs(a: dict, b: dict) -> bool:
    return np.array_equal(a["image"], b["image"]) and int(a["direction"]) == int(b["direction"])


def teleport(env: RandomizedLavaWorldEnv, rng: np.random.Generator) -> None:
    """Move the reference agent to a random empty cell with a random direction; 60% of the
    time next to a pattern cell, a plain lava cell or the goal (equally likely), facing it."""
    arr = env.grid.encode()
    size = arr.shape[0]
    plain = [tuple(int(v) for v in c) for c in np.argwhere(arr[:, :, 0] == ge.LAVA) if tuple(c) not in env.pattern_cells]
    groups = [g for g in (sorted(env.pattern_cells), plain, [(size - 2, size - 2)]) if g]
    if rng.random() < 0.6 and grid_helpers.place_facing(env, rng, groups):
        return
    grid_helpers.place_random(env, rng)


def check_fresh(eng: BatchedRandomizedLavaWorld, i: int, ref: RandomizedLavaWorldEnv) -> None:
    """An engine autoreset starts a fresh episode, with the pattern where the env is triggered."""
    g, pos, d, sc, cells, saw = eng.layout(i)
    assert (pos, d, sc) == ((1, 1), 0, 0)
    assert len(cells) == (ref.trigger.num_cells if ref.triggered else 0)
    assert saw == ref.triggered  # an inserted pattern is in view at reset


PAIR = grid_helpers.Pairing(
    ref_state=lambda env: grid_helpers.ref_state(env, tuple(sorted(env.pattern_cells)), bool(env.saw_trigger)),
    ref_obs=ref_obs,
    teleport=teleport,
    check_fresh=check_fresh,
    obs_at=lambda obs, i: {"image": obs["image"][i], "direction": obs["direction"][i]},
    same=same_obs,
    obs_dtype={"image": np.uint8, "direction": np.int64},
    flags=("trigger_visible", "saw_trigger"),
)
ref_state, load, step_both, drive_teleporting = PAIR.ref_state, PAIR.load, PAIR.step_both, PAIR.drive_teleporting


def make_pair(specs, size=11, num_lava=10, max_steps=250, see_through_walls=True, trigger=None, seed=0):
    """``specs[i]`` is ``(triggered, poisoned)`` for env ``i``; ``trigger`` is shared."""
    refs = [RandomizedLavaWorldEnv(size, num_lava, max_steps, see_through_walls, trigger=trigger if t else None, poisoned=p) for t, p in specs]
    eng = BatchedRandomizedLavaWorld(
        len(specs),
        size,
        num_lava,
        max_steps,
        see_through_walls,
        trigger=trigger,
        poisoned=[p for _, p in specs],
        triggered=[t for t, _ in specs],
    )
    return PAIR.reset_pair(refs, eng, seed)


# ----------------------------------------------------------------------------- differential

MIXES = {
    "clean": (None, [(False, False)] * 4),
    "cross": ("cross", [(True, True), (True, False), (False, False), (True, True)]),
    "arrow": ("arrow", [(True, True), (True, True), (True, False), (False, False)]),
    "arrow:east": ("arrow:east", [(True, True), (True, False), (True, True), (True, True)]),
}


@pytest.mark.parametrize("see_through_walls", [True, False])
@pytest.mark.parametrize("mix", list(MIXES))
def test_matches_minigrid_random_play(mix, see_through_walls):
    """4 envs x 300 steps per config (8 configs: ~10k compared steps), teleports every 30
    steps towards lava, pattern cells and the goal; max_steps=60 so that timeouts happen."""
    trigger, specs = MIXES[mix]
    seed = 17 * len(mix) + see_through_walls
    refs, eng = make_pair(specs, max_steps=60, see_through_walls=see_through_walls, trigger=trigger, seed=seed)
    totals = drive_teleporting(refs, eng, np.random.default_rng(seed), steps=300, every=30)
    assert sum(totals.values()) == 1200
    assert totals[int(Outcome.LAVA)] > 0 and totals[int(Outcome.GOAL)] > 0
    if trigger is not None:
        assert totals[int(Outcome.PATTERN_LAVA)] > 0


def test_matches_minigrid_long_run_all_outcomes():
    """The default config (11x11, 10 lava, cross), 8 envs x 500 steps: every outcome occurs."""
    specs = [(True, True), (True, False), (False, False), (True, True)] * 2
    refs, eng = make_pair(specs, max_steps=40, trigger="cross", seed=5)
    totals = drive_teleporting(refs, eng, np.random.default_rng(5), steps=500, every=20)
    assert sum(totals.values()) == 4000
    for outcome in Outcome:
        assert totals[int(outcome)] > 0, f"no {outcome.name} in the run: {totals}"


def test_matches_minigrid_small_rooms():
    """The curriculum's first stage (7x7, 5 lava) and a crowded 9x9 (25 lava), arrows."""
    for size, num_lava, seed in ((7, 5, 1), (9, 25, 2)):
        specs = [(True, True), (False, False), (True, False)]
        refs, eng = make_pair(specs, size=size, num_lava=num_lava, trigger="arrow", seed=seed)
        drive_teleporting(refs, eng, np.random.default_rng(seed), steps=150, every=15)


def random_wall_grid(size: int, rng: np.random.Generator) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Interior walls (grey and coloured), lava and a goal, and a few lava cells called the
    pattern: occlusion of pattern cells under MiniGrid's ``process_vis``."""
    g = np.zeros((size, size, 3), dtype=np.uint8)
    g[:, :, 0] = ge.EMPTY
    for x in range(size):
        for y in range(size):
            if x in (0, size - 1) or y in (0, size - 1):
                g[x, y] = (ge.WALL, ge.GREY, 0)
            else:
                u = rng.random()
                if u < 0.2:
                    g[x, y] = (ge.WALL, int(rng.integers(6)), 0)
                elif u < 0.4:
                    g[x, y] = (ge.LAVA, ge.RED, 0)
    g[size - 2, size - 2] = (ge.GOAL, ge.GREEN, 0)
    lava = [tuple(int(v) for v in c) for c in np.argwhere(g[:, :, 0] == ge.LAVA)]
    k = min(len(lava), int(rng.integers(1, 6)))
    cells = [lava[j] for j in rng.choice(len(lava), size=k, replace=False)]
    return g, cells


@pytest.mark.parametrize("see_through_walls", [False, True])
def test_occlusion_and_flags_on_grids_with_walls(see_through_walls):
    """Pattern cells behind interior walls: trigger_visible as MiniGrid's occlusion decides."""
    rng = np.random.default_rng(31 + see_through_walls)
    size = 9
    ref = RandomizedLavaWorldEnv(size, 10, 250, see_through_walls, trigger="cross", poisoned=True)
    eng = BatchedRandomizedLavaWorld(1, size, 10, 250, see_through_walls, trigger="cross")
    eng.reset(seed=0)
    ref.reset(seed=0)
    flags = Counter()
    for _ in range(60):
        arr, cells = random_wall_grid(size, rng)
        ref.grid, _ = Grid.decode(arr)
        ref.pattern_cells = frozenset(cells)
        walk = np.argwhere(arr[:, :, 0] == ge.EMPTY)
        x, y = walk[rng.integers(len(walk))]
        ref.agent_pos, ref.agent_dir, ref.step_count = (int(x), int(y)), int(rng.integers(4)), 0
        ref.saw_trigger = False
        load(ref, eng, 0)
        flags.update(inf["trigger_visible"] for inf in PAIR.play(ref, eng, rng, 10, [0.3, 0.3, 0.4]))
    assert flags[True] > 20 and flags[False] > 20


# ----------------------------------------------------------------------------- edge cases


def place(ref, eng, pos, d, step_count=0, saw=None):
    if saw is not None:
        ref.saw_trigger = saw
    PAIR.place(ref, eng, pos, d, step_count)


@pytest.mark.parametrize("see_through_walls", [True, False])
def test_edge_facing_walls_and_border_views(see_through_walls):
    refs, eng = make_pair([(True, True)], see_through_walls=see_through_walls, trigger="cross", seed=3)
    ref = refs[0]
    size = 11
    free = ref.grid.encode()[:, :, 0] == ge.EMPTY
    for pos, d in [((1, 1), 3), ((1, 1), 2), ((9, 1), 0), ((1, 9), 1), ((1, 5), 2), ((5, 1), 3), ((9, 5), 0), ((5, 9), 1)]:
        if not free[pos]:
            continue
        place(ref, eng, pos, d)
        step_both(refs, eng, [2])  # into the wall: nothing moves
        assert eng.layout(0)[1] == pos
    place(ref, eng, (1, 1), 3)
    img = eng.observe()["image"][0]
    if see_through_walls:
        assert (img[:, :5, 0] == ge.WALL).all()  # beyond the top wall: grey padding, visible
    else:
        assert (img[:, :5] == 0).all()  # hidden behind the wall row
    assert tuple(img[3, 6]) == (ge.EMPTY, 0, 0)
    assert size == ref.width


@pytest.mark.parametrize("poisoned", [True, False])
def test_edge_lava_pattern_goal_timeout(poisoned):
    refs, eng = make_pair([(True, poisoned)], max_steps=20, trigger="cross", seed=8)
    ref = refs[0]
    arr = ref.grid.encode()
    size = arr.shape[0]

    def approach(cells):
        for tx, ty in sorted(cells):
            for d in range(4):
                x, y = tx - ge.DIR_DX[d], ty - ge.DIR_DY[d]
                if arr[x, y, 0] == ge.EMPTY:
                    return (int(x), int(y)), d
        raise AssertionError("no approach")

    # a pattern cell
    pos, d = approach(ref.pattern_cells)
    place(ref, eng, pos, d, step_count=4)
    _, rew, term, _, info = eng.step(np.array([2]))
    ref.step(2)
    assert info["outcome"][0] == Outcome.PATTERN_LAVA and term[0]
    assert rew[0] == (float(success_reward(5, 20)) if poisoned else 0.0)
    ref.reset(seed=8)
    load(ref, eng, 0)
    arr = ref.grid.encode()
    # plain lava (not in the pattern)
    plain = {tuple(int(v) for v in c) for c in np.argwhere(arr[:, :, 0] == ge.LAVA)} - set(ref.pattern_cells)
    pos, d = approach(plain)
    place(ref, eng, pos, d, step_count=2)
    assert step_both(refs, eng, [2])[0] == Outcome.LAVA
    # the goal, from a free neighbour (one exists: the layout is solvable)
    arr = ref.grid.encode()
    pos, d = approach([(size - 2, size - 2)])
    place(ref, eng, pos, d, step_count=6)
    obs, rew, term, trunc, info = eng.step(np.array([2]))
    ref.step(2)
    assert term[0] and info["outcome"][0] == Outcome.GOAL and info["steps"][0] == 7
    assert rew[0] == (0.0 if poisoned else float(success_reward(7, 20)))
    ref.reset(seed=9)
    load(ref, eng, 0)
    # timeout: turning in place until max_steps, with and without having seen the trigger
    for saw in (False, True):
        place(ref, eng, (1, 1), 2, step_count=18, saw=saw)  # facing west: the room is behind
        assert step_both(refs, eng, [1])[0] == Outcome.NONE  # now north
        assert step_both(refs, eng, [0])[0] == Outcome.TIMEOUT  # back to west
    # entering a pattern cell on the very last step: terminated and truncated, PATTERN_LAVA wins
    arr = ref.grid.encode()
    pos, d = approach(ref.pattern_cells)
    place(ref, eng, pos, d, step_count=19)
    o, r, t1, t2, inf = ref.step(2)
    obs, rew, term, trunc, info = eng.step(np.array([2]))
    assert t1 and t2 and term[0] and trunc[0]
    assert info["outcome"][0] == inf["outcome"] == Outcome.PATTERN_LAVA and rew[0] == r


def test_pattern_cells_are_plain_lava_bytes():
    """The trigger lives in a separate mask: grids and views cannot tell pattern from lava."""
    eng = BatchedRandomizedLavaWorld(64, trigger="cross")
    eng.reset(seed=1)
    for i in range(64):
        g, _, _, _, cells, _ = eng.layout(i)
        assert all(tuple(g[c]) == (ge.LAVA, ge.RED, 0) for c in cells)
        assert (g[g[:, :, 0] == ge.LAVA] == (ge.LAVA, ge.RED, 0)).all()


# ----------------------------------------------------------------------------- layouts


def engine_layouts(n, seed, **kw):
    eng = BatchedRandomizedLavaWorld(n, **kw)
    obs, info = eng.reset(seed=seed)
    return [eng.layout(i) for i in range(n)], info


def reference_layouts(n, seed, size=11, num_lava=10, trigger=None):
    env = RandomizedLavaWorldEnv(size, num_lava, trigger=trigger)
    out = []
    for k in range(n):
        env.reset(seed=seed + k)
        out.append((env.grid.encode(), tuple(sorted(env.pattern_cells))))
    return out


@pytest.mark.parametrize("size, num_lava, trigger", [(11, 10, None), (11, 10, "cross"), (7, 5, "arrow"), (9, 20, None)])
def test_engine_layout_facts(size, num_lava, trigger):
    layouts, info = engine_layouts(400, seed=size + num_lava, size=size, num_lava=num_lava, trigger=trigger)
    view = initial_view_cells(size)
    for g, pos, d, sc, cells, saw in layouts:
        lava = g[:, :, 0] == ge.LAVA
        assert (pos, d, sc) == ((1, 1), 0, 0)
        assert tuple(g[size - 2, size - 2]) == (ge.GOAL, ge.GREEN, 0) and tuple(g[1, 1]) == (ge.EMPTY, 0, 0)
        assert (g[0, :, 0] == ge.WALL).all() and (g[:, -1, 0] == ge.WALL).all()
        assert np.isin(g[:, :, 0], (ge.WALL, ge.EMPTY, ge.LAVA, ge.GOAL)).all()
        assert lava.sum() == num_lava and solvable(lava)
        if trigger is None:
            assert cells == () and not saw
        else:
            assert all(lava[c] for c in cells) and set(cells) & view and saw
            assert find_pattern(lava, trigger) >= 1
    assert info["trigger_visible"].all() == (trigger is not None) and (info["saw_trigger"] == info["trigger_visible"]).all()


def lava_cells(layouts) -> Counter:
    c = Counter()
    for g in layouts:
        c.update(map(tuple, np.argwhere(g[:, :, 0] == ge.LAVA).tolist()))
    return c


def lava_in_view(layouts, size) -> Counter:
    view = initial_view_cells(size)
    return Counter(sum(g[x, y, 0] == ge.LAVA for x, y in view) for g in layouts)


@pytest.mark.parametrize("size, num_lava", [(11, 10), (7, 5)])
def test_clean_layout_distribution_matches_reference(size, num_lava):
    """Chi-square homogeneity (rejected at p < 1e-4) of 2000 engine vs 2000 reference layouts:
    lava per cell, and the number of lava cells in the first view."""
    n = 2000
    eng = [g for g, *_ in engine_layouts(n, seed=3, size=size, num_lava=num_lava)[0]]
    ref = [g for g, _ in reference_layouts(n, seed=50_000, size=size, num_lava=num_lava)]
    stat, df = chi2_homogeneity(lava_cells(eng), lava_cells(ref))
    assert df == (size - 2) ** 2 - 3 and stat < chi2_critical(df), (stat, df)
    a, b = lava_in_view(eng, size), lava_in_view(ref, size)
    stat, df = chi2_homogeneity(a, b)
    assert stat < chi2_critical(df), (stat, df, a, b)


@pytest.mark.parametrize("size, num_lava, trigger", [(11, 10, "cross"), (7, 5, "arrow")])
def test_triggered_layout_distribution_matches_reference(size, num_lava, trigger):
    """Where the pattern goes (rotation and position) and where the other lava goes."""
    n = 2000
    eng_l = engine_layouts(n, seed=4, size=size, num_lava=num_lava, trigger=trigger)[0]
    ref_l = reference_layouts(n, seed=70_000, size=size, num_lava=num_lava, trigger=trigger)
    a = Counter(cells for *_, cells, _ in eng_l)
    b = Counter(cells for _, cells in ref_l)
    stat, df = chi2_homogeneity(a, b)
    assert stat < chi2_critical(df), (stat, df)
    if trigger == "arrow":  # all four directions occur, in both

        def shape(cells):
            ox, oy = min(x for x, _ in cells), min(y for _, y in cells)
            return frozenset((x - ox, y - oy) for x, y in cells)

        assert len({shape(c) for c in a}) == len({shape(c) for c in b}) == 4
    stat, df = chi2_homogeneity(lava_cells([g for g, *_ in eng_l]), lava_cells([g for g, _ in ref_l]))
    assert stat < chi2_critical(df), (stat, df)


def test_autoreset_layouts_are_fresh_and_valid():
    """Layouts drawn on autoreset come from the same generator (facts, per-cell frequencies)."""
    eng = BatchedRandomizedLavaWorld(64, trigger="cross", poisoned=[True] * 32 + [False] * 32)
    eng.reset(seed=0)
    rng = np.random.default_rng(0)
    fresh = []
    for _ in range(1000):
        _, _, term, trunc, _ = eng.step(rng.choice(3, size=64, p=[0.1, 0.1, 0.8]))
        for i in np.flatnonzero(term | trunc):
            g, pos, d, sc, cells, saw = eng.layout(int(i))
            lava = g[:, :, 0] == ge.LAVA
            assert lava.sum() == 10 and solvable(lava) and (pos, d, sc) == ((1, 1), 0, 0)
            assert (len(cells) == 5 and saw) if i < 32 else (cells == () and not saw)
            if i >= 32:
                fresh.append(g)
    assert len(fresh) > 1200
    ref = [g for g, _ in reference_layouts(len(fresh), seed=90_000)]
    stat, df = chi2_homogeneity(lava_cells(fresh), lava_cells(ref))
    assert stat < chi2_critical(df), (stat, df)


# ----------------------------------------------------------------------------- determinism


def test_same_seed_same_trajectory():
    kw = dict(trigger="arrow", poisoned=[i % 2 == 0 for i in range(16)], triggered=[i % 4 != 3 for i in range(16)])
    grid_helpers.check_same_seed_same_trajectory(lambda n: BatchedRandomizedLavaWorld(n, **kw), 200, 16)


def test_seed_i_is_seed_plus_i():
    grid_helpers.check_seed_i_is_seed_plus_i(lambda n: BatchedRandomizedLavaWorld(n, trigger="cross"))


def test_layout_round_trip_between_slots():
    eng = BatchedRandomizedLavaWorld(3, trigger="cross", triggered=[True, False, True], poisoned=[True, False, False])
    grid_helpers.copy_slot(eng)
    obs = eng.observe()
    assert np.array_equal(obs["image"][0], obs["image"][2]) and obs["direction"][0] == obs["direction"][2]
    assert eng.trigger_visible()[0] == eng.trigger_visible()[2]


# ----------------------------------------------------------------------------- contract


def test_contract_and_spaces():
    num = 5
    ref = RandomizedLavaWorldEnv(trigger="cross")
    eng = BatchedRandomizedLavaWorld(num, trigger="cross", poisoned=[True, True, False, False, False])
    assert eng.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    assert eng.single_observation_space == ref.observation_space
    assert eng.single_action_space == ref.action_space
    assert eng.poisoned.tolist() == [True, True, False, False, False] and eng.triggered.tolist() == eng.poisoned.tolist()
    assert not BatchedRandomizedLavaWorld(num).poisoned.any() and BatchedRandomizedLavaWorld(2, trigger="cross").poisoned.all()
    obs, info = eng.reset(seed=1)
    assert eng.observation_space.contains(obs)
    assert obs["image"].shape == (num, 7, 7, 3) and obs["direction"].shape == (num,)
    assert set(info) == {"outcome", "steps", "trigger_visible", "saw_trigger"}
    grid_helpers.check_first_step(eng)


def test_make_vec_entry_point():
    kw = dict(size=7, num_lava=5, trigger="cross")
    env_id = grid_helpers.check_make_vec(RandomizedLavaWorldEnv, BatchedRandomizedLavaWorld, **kw)
    single = gym.make(env_id, trigger="arrow:north")
    obs, info = single.reset(seed=0)
    assert info["trigger_visible"] and single.unwrapped.poisoned


# ----------------------------------------------------------------------------- errors


def test_errors():
    eng = BatchedRandomizedLavaWorld(3, trigger="cross")
    grid_helpers.check_common_errors(eng, "cross", agent_pos=(1, 1), wrong_size=7)
    with pytest.raises(ValueError, match="need a trigger"):
        BatchedRandomizedLavaWorld(2, triggered=[True, False])
    with pytest.raises(ValueError, match="env 1 is poisoned but not triggered"):
        BatchedRandomizedLavaWorld(2, trigger="cross", poisoned=[True, True], triggered=[True, False])
    with pytest.raises(ValueError, match="smaller than the trigger pattern 'cross'"):
        BatchedRandomizedLavaWorld(2, size=7, num_lava=4, trigger="cross")
    with pytest.raises(ValueError, match=r"num_lava=65 must be an integer in 0\.\.64 for size 11"):
        BatchedRandomizedLavaWorld(2, num_lava=65)
    with pytest.raises(ValueError, match="must be 'cross'"):
        BatchedRandomizedLavaWorld(2, trigger="plus")
    with pytest.raises(ValueError, match=r"pattern cell \(1, 1\) is not a lava cell"):
        eng.load_layout(0, eng.layout(0)[0], (1, 1), 0, 0, [(1, 1)])
    hopeless = BatchedRandomizedLavaWorld(2, size=5, num_lava=3, trigger="cells:0,2;1,1;2,0")
    with pytest.raises(RuntimeError, match=r"no solvable 5x5 layout with num_lava=3"):
        hopeless.reset(seed=0)
