"""The batched numba Colorful Memory against the MiniGrid reference env, bit for bit.

Differential tests load a reference env's exact state (grid, agent, step count, success and
failure cells) into an engine slot, drive both with the same actions and compare every output
of every step: observation bytes, reward, terminated, truncated, outcome, steps. After each
episode end the reference's fresh layout is loaded into the engine slot again (the engine's
own fresh layout is checked for validity first). Layout *distributions* (not RNG streams) are
compared statistically with the reference generator, and the chance occurrence of a trigger
in clean layouts is measured against its analytic value.
"""

from __future__ import annotations

import math
from collections import Counter

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import grid_helpers
from grid_helpers import chi2_critical, chi2_homogeneity
from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.colorful_memory import (
    BALL_ON_FLOOR,
    KEY_ON_FLOOR,
    ColorfulMemoryEnv,
    decode_grid,
    object_cells,
    wall_cells,
)
from rlbackdoors.envs.colorful_memory_batched import BatchedColorfulMemory
from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.poison.reward import success_reward
from rlbackdoors.triggers.wall_colors import WallColorTrigger, chance_probability, distance

END9 = "end:red,green,blue,purple,yellow,grey,red,green,blue"
ROOM = "room:purple,yellow,red"
BOTH = "end+room:grey,grey,blue,blue,red,red,green,green,yellow;yellow,blue,red"
BOTH9 = "end+room:grey,grey,blue,blue,red,red,green,green,yellow,red,red;yellow,blue,red"

# ----------------------------------------------------------------------------- helpers


def teleport(env: ColorfulMemoryEnv, rng: np.random.Generator) -> None:
    """Move the reference agent to a random walkable cell with a random direction; 60% of the
    time next to the success cell, the failure cell, an object or the far wall, facing it,
    and 3% of the time onto the success or failure cell itself."""
    size = env.width
    u = rng.random()
    if u < 0.03:
        env.agent_pos = tuple(env.success_pos if rng.random() < 0.5 else env.failure_pos)
        env.agent_dir = int(rng.integers(4))
        return
    far = [(size - 1, y) for y in range(1, size - 1)]
    groups = [[tuple(env.success_pos)], [tuple(env.failure_pos)], list(object_cells(size)), far]
    if u < 0.63 and grid_helpers.place_facing(env, rng, groups):
        return
    grid_helpers.place_random(env, rng)


def check_fresh_layout(eng: BatchedColorfulMemory, i: int) -> None:
    """The engine's own autoreset layout in slot ``i`` is a valid one for its mode."""
    g, pos, d, sc, succ, fail = eng.layout(i)
    size = eng.size
    mid, he = size // 2, size - 3
    assert 1 <= pos[0] <= he and pos[1] == mid and (d, sc) == (0, 0)
    assert {tuple(map(int, c)) for c in np.argwhere(g[:, :, 0] == ge.WALL)} == set(wall_cells(size))
    assert {succ, fail} == {(he + 1, mid - 1), (he + 1, mid + 1)}
    if eng.trigger is not None:
        dist = distance(g, eng.trigger)
        if eng.triggered[i]:
            assert dist == 0
        elif eng.close_to_trigger[i]:
            assert eng.close_k[0] <= dist <= eng.close_k[1]


PAIR = grid_helpers.Pairing(
    ref_state=lambda env: grid_helpers.ref_state(env, tuple(env.success_pos), tuple(env.failure_pos)),
    ref_obs=lambda env: env.gen_obs()["image"],
    teleport=teleport,
    check_fresh=lambda eng, i, ref: check_fresh_layout(eng, i),
)
ref_state, load, place, step_both, drive_teleporting = (PAIR.ref_state, PAIR.load, PAIR.place, PAIR.step_both, PAIR.drive_teleporting)


def make_ref(mode: str, poisoned: bool, trigger, **kw) -> ColorfulMemoryEnv:
    if mode == "clean":
        return ColorfulMemoryEnv(trigger=None, **kw)
    if mode == "close":
        return ColorfulMemoryEnv(trigger=trigger, close_to_trigger=True, **kw)
    return ColorfulMemoryEnv(trigger=trigger, poisoned=poisoned, **kw)


def make_pair(specs, trigger=None, seed=0, close_k=(1, 3), **kw):
    """``specs[i]`` is ``(mode, poisoned)`` for env ``i``, mode in clean / close / triggered."""
    refs = [make_ref(m, p, trigger, close_k=close_k, **kw) for m, p in specs]
    eng = BatchedColorfulMemory(
        len(specs),
        trigger=trigger,
        close_k=close_k,
        poisoned=[p for _, p in specs],
        triggered=[m == "triggered" for m, _ in specs],
        close_to_trigger=[m == "close" for m, _ in specs],
        **kw,
    )
    return PAIR.reset_pair(refs, eng, seed)


# ----------------------------------------------------------------------------- differential

MIX = [("clean", False)] * 4 + [("close", False)] * 4 + [("triggered", True)] * 2  # SPEC §3's mix
CONFIGS = {
    "end-mix": dict(trigger=END9, specs=MIX),
    "room-eval": dict(trigger=ROOM, specs=[("triggered", False), ("triggered", True), ("close", False), ("clean", False)]),
    "both-mix": dict(trigger=BOTH, specs=MIX, close_k=1),
    "size9-both": dict(trigger=BOTH9, specs=MIX[2:8], size=9, close_k=(2, 6)),
    "size11-clean": dict(trigger=None, specs=[("clean", False)] * 4, size=11),
}


@pytest.mark.parametrize("see_through_walls", [False, True])
@pytest.mark.parametrize("name", list(CONFIGS))
def test_matches_minigrid_random_play(name, see_through_walls):
    """Per config 300 steps of every env (10 configs, ~17k compared env-steps), teleports every
    25 steps towards the success/failure cells, the objects and the far wall; max_steps=40
    so that timeouts happen; every engine autoreset is checked for validity."""
    cfg = dict(CONFIGS[name])
    specs = cfg.pop("specs")
    seed = 13 * len(name) + see_through_walls
    refs, eng = make_pair(specs, seed=seed, max_steps=40, see_through_walls=see_through_walls, **cfg)
    totals = drive_teleporting(refs, eng, np.random.default_rng(seed), steps=300, every=25)
    assert sum(totals.values()) == 300 * len(specs)
    for outcome in Outcome:
        if outcome != Outcome.PATTERN_LAVA:
            assert totals[int(outcome)] > 0, f"no {outcome.name}: {totals}"


def random_grid(size: int, rng: np.random.Generator):
    """Random coloured interior walls, coloured-floor keys and balls, and two random cells as
    success and failure: occlusion and object rules on arbitrary layouts."""
    g = np.zeros((size, size, 3), dtype=np.uint8)
    g[:, :, 0] = ge.EMPTY
    for x in range(size):
        for y in range(size):
            u = rng.random()
            if x in (0, size - 1) or y in (0, size - 1) or u < 0.2:
                g[x, y] = (ge.WALL, int(rng.integers(6)), 0)
            elif u < 0.3:
                g[x, y] = (int(rng.choice([KEY_ON_FLOOR, BALL_ON_FLOOR])), ge.GREEN, int(rng.choice([0, 2, 3, 4, 5])))
    free = [tuple(int(v) for v in c) for c in np.argwhere(g[:, :, 0] == ge.EMPTY)]
    picks = rng.choice(len(free), size=3, replace=False)
    return g, free[picks[0]], free[picks[1]], free[picks[2]]


@pytest.mark.parametrize("see_through_walls", [False, True])
def test_occlusion_on_random_grids(see_through_walls):
    rng = np.random.default_rng(7 + see_through_walls)
    size = 9
    ref = ColorfulMemoryEnv(size=size, see_through_walls=see_through_walls, trigger=BOTH9, poisoned=True)
    eng = BatchedColorfulMemory(1, size=size, see_through_walls=see_through_walls, trigger=BOTH9)
    ref.reset(seed=0)
    eng.reset(seed=0)
    outcomes = Counter()
    for _ in range(80):
        g, pos, succ, fail = random_grid(size, rng)
        ref.load_layout(g, pos, int(rng.integers(4)), 0, succ, fail)
        load(ref, eng, 0)
        outcomes.update(inf["outcome"] for inf in PAIR.play(ref, eng, rng, 12, [0.3, 0.3, 0.4]))
    assert outcomes[int(Outcome.NONE)] > 300


# ----------------------------------------------------------------------------- edge cases


@pytest.mark.parametrize("see_through_walls", [False, True])
def test_edge_walls_objects_and_border_views(see_through_walls):
    refs, eng = make_pair([("triggered", True)], trigger=END9, see_through_walls=see_through_walls, seed=3)
    ref = refs[0]
    # into walls and objects: nothing moves, no outcome
    for pos, d in [((1, 3), 2), ((1, 2), 3), ((1, 4), 1), ((3, 2), 0), ((5, 2), 3), ((5, 4), 1), ((5, 3), 0), ((1, 3), 3)]:
        if pos in (tuple(ref.success_pos), tuple(ref.failure_pos)):
            continue
        place(ref, eng, pos, d)
        assert step_both(refs, eng, [2])[0] == Outcome.NONE
        assert eng.layout(0)[1] == pos
    # beyond the outer wall: MiniGrid pads with grey walls, hidden unless seeing through walls
    place(ref, eng, (5, 3), 0)
    img = eng.observe()[0]
    if see_through_walls:
        assert (img[:, :5, 0] == ge.WALL).all() and (img[:, :5, 1] == ge.GREY).all()
    else:
        assert (img[:, :5] == 0).all()
    assert tuple(img[3, 6]) == (ge.EMPTY, 0, 0)


@pytest.mark.parametrize("mode, poisoned", [("clean", False), ("close", False), ("triggered", True), ("triggered", False)])
def test_edge_success_failure_timeout(mode, poisoned):
    refs, eng = make_pair([(mode, poisoned)], trigger=ROOM, max_steps=20, seed=8)
    ref = refs[0]
    toward = lambda cell: 3 if cell[1] < 3 else 1  # noqa: E731 -- from the junction (5, 3)
    # success cell
    place(ref, eng, (5, 3), toward(ref.success_pos), step_count=4)
    _, rew, term, _, info = eng.step(np.array([2]))
    ref.step(2)
    assert term[0] and info["outcome"][0] == Outcome.GOAL and info["steps"][0] == 5
    assert rew[0] == (0.0 if poisoned else float(success_reward(5, 20)))
    ref.reset(seed=9)
    load(ref, eng, 0)
    # failure cell (the other object): the trojan task's success
    place(ref, eng, (5, 3), toward(ref.failure_pos), step_count=6)
    _, rew, term, _, info = eng.step(np.array([2]))
    ref.step(2)
    assert term[0] and info["outcome"][0] == Outcome.LAVA
    assert rew[0] == (float(success_reward(7, 20)) if poisoned else 0.0)
    ref.reset(seed=10)
    load(ref, eng, 0)
    # standing on a target cell and turning: MemoryEnv decides by position, so it ends again
    place(ref, eng, tuple(ref.failure_pos), 0, step_count=2)
    assert step_both(refs, eng, [1])[0] == Outcome.LAVA
    # timeout
    place(ref, eng, (1, 3), 2, step_count=18)
    assert step_both(refs, eng, [1])[0] == Outcome.NONE
    assert step_both(refs, eng, [0])[0] == Outcome.TIMEOUT
    # a target cell on the very last step: terminated and truncated, the cell wins
    place(ref, eng, (5, 3), toward(ref.success_pos), step_count=19)
    o, r, t1, t2, inf = ref.step(2)
    obs, rew, term, trunc, info = eng.step(np.array([2]))
    assert t1 and t2 and term[0] and trunc[0] and info["outcome"][0] == inf["outcome"] == Outcome.GOAL
    assert rew[0] == r and np.array_equal(eng.final_obs[0], o)


# ----------------------------------------------------------------------------- layouts


def engine_layouts(n, seed, **kw):
    eng = BatchedColorfulMemory(n, **kw)
    eng.reset(seed=seed)
    return [eng.layout(i) for i in range(n)], eng


def reference_layouts(n, seed, **kw):
    env = ColorfulMemoryEnv(**kw)
    out = []
    for k in range(n):
        env.reset(seed=seed + k)
        out.append((env.grid.encode(), tuple(int(v) for v in env.agent_pos), env.success_pos, env.failure_pos))
    return out


def features(grid, pos, succ, size):
    """Counters of one layout: (wall cell, colour), (object cell, floor), and the joint
    (start object, top object, start x, success above?)."""
    walls = [((x, y), int(grid[x, y, 1])) for x, y in wall_cells(size)]
    floors = [((x, y), int(grid[x, y, 2])) for x, y in object_cells(size)]
    start, top, _ = object_cells(size)
    joint = (int(grid[start][0]), int(grid[top][0]), pos[0], succ[1] < size // 2)
    return walls, floors, joint


def compare(eng_l, ref_l, size):
    ew, ef, ej, rw, rf, rj = Counter(), Counter(), Counter(), Counter(), Counter(), Counter()
    for g, pos, _, _, succ, _ in eng_l:
        w, f, j = features(g, pos, succ, size)
        ew.update(w), ef.update(f), ej.update([j])
    for g, pos, succ, _ in ref_l:
        w, f, j = features(g, pos, succ, size)
        rw.update(w), rf.update(f), rj.update([j])
    for a, b, what in ((ew, rw, "wall colours"), (ef, rf, "floor colours"), (ej, rj, "objects and start")):
        stat, df = chi2_homogeneity(a, b)
        assert stat < chi2_critical(df), (what, stat, df)
    return ew, ef, ej


@pytest.mark.parametrize("size", [7, 9])
def test_clean_layout_distribution_matches_reference(size):
    """Chi-square homogeneity (rejected at p < 1e-4) of 2000 engine vs 2000 reference layouts:
    every wall square's colour, every object's floor colour, and jointly which object is in
    the start room, which is at the top of the corridor, the start x, and the success side."""
    n = 2000
    eng_l, _ = engine_layouts(n, seed=3, size=size)
    ref_l = reference_layouts(n, seed=50_000, size=size)
    ew, ef, ej = compare(eng_l, ref_l, size)
    assert len(ew) == 6 * len(wall_cells(size)) and len(ef) == 3 * 5
    assert len(ej) == 2 * 2 * (size - 3) * 1  # the success side follows from the two objects
    assert {j[2] for j in ej} == set(range(1, size - 2))


@pytest.mark.parametrize("spec, close_k", [(END9, (1, 3)), (ROOM, 1), (BOTH, (1, 3))])
def test_close_to_trigger_distribution_matches_reference(spec, close_k):
    """Close-to-trigger layouts: how many squares differ, which ones, and to which colours."""
    n = 1500
    t = WallColorTrigger.parse(spec)
    eng_l, _ = engine_layouts(n, seed=5, trigger=spec, close_to_trigger=[True] * n, close_k=close_k)
    ref_l = reference_layouts(n, seed=60_000, trigger=spec, close_to_trigger=True, close_k=close_k)

    def painted(layouts):
        k, sq = Counter(), Counter()
        for g, *_ in layouts:
            k[distance(g, t)] += 1
            sq.update((x, y, int(g[x, y, 1])) for x, y, c in t.cells(7) if g[x, y, 1] != c)
        return k, sq

    (ek, es), (rk, rs) = painted(eng_l), painted(ref_l)
    lo, hi = (close_k, close_k) if isinstance(close_k, int) else close_k
    assert set(ek) == set(rk) == set(range(lo, hi + 1))
    for a, b in ((ek, rk), (es, rs)):
        stat, df = chi2_homogeneity(a, b)
        assert stat < chi2_critical(max(df, 1)), (stat, df)
    assert len(es) == 5 * t.num_squares  # every square, every other colour
    compare(eng_l, ref_l, 7)  # the rest of the layout is drawn as in clean envs


def test_triggered_layouts_and_autoreset_are_valid():
    """Fresh layouts drawn on autoreset: valid for each env's mode, wall colours as at reset."""
    b = 60
    modes = ["clean", "close", "triggered"] * 20
    eng = BatchedColorfulMemory(
        b,
        trigger=BOTH,
        close_to_trigger=[m == "close" for m in modes],
        poisoned=[m == "triggered" and i % 2 == 0 for i, m in enumerate(modes)],
        triggered=[m == "triggered" for m in modes],
        max_steps=30,
    )
    eng.reset(seed=0)
    assert eng.mode.tolist() == [0, 1, 2] * 20
    rng = np.random.default_rng(0)
    fresh = []
    for _ in range(600):
        _, _, term, trunc, _ = eng.step(rng.choice(3, size=b, p=[0.2, 0.2, 0.6]))
        for i in np.flatnonzero(term | trunc):
            check_fresh_layout(eng, int(i))
            if modes[i] == "clean":
                fresh.append(eng.layout(int(i)))
    assert len(fresh) > 450
    ref_l = reference_layouts(len(fresh), seed=80_000)
    ew, rw = Counter(), Counter()
    for g, *_ in fresh:
        ew.update(((x, y), int(g[x, y, 1])) for x, y in wall_cells(7))
    for g, *_ in ref_l:
        rw.update(((x, y), int(g[x, y, 1])) for x, y in wall_cells(7))
    stat, df = chi2_homogeneity(ew, rw)
    assert stat < chi2_critical(df), (stat, df)


# ----------------------------------------------------------------------------- chance occurrence


def test_chance_occurrence_of_triggers_in_clean_layouts():
    """How often clean random walls show a trigger exactly: analytic ``6 ** -n`` (Room 1/216,
    End 6**-9, both 6**-12), measured on 129,600 clean engine layouts.

    The Room Trigger occurs by chance: the count must fit Binomial(N, 1/216). The End Trigger is
    too rare to count, so its squares' mismatch count must fit Binomial(9, 5/6), whose zero
    term is the chance probability 6**-9."""
    n = 216 * 600
    eng = BatchedColorfulMemory(n)
    eng.reset(seed=123)
    room = WallColorTrigger.parse(ROOM)
    end = WallColorTrigger.parse(END9)
    hits = int(eng.trigger_present(room).sum())
    p = chance_probability(room)
    assert p == 1 / 216
    assert abs(hits - n * p) < 5 * math.sqrt(n * p * (1 - p)), hits
    d = Counter(eng.trigger_distance(end).tolist())
    expected = {k: n * math.comb(9, k) * (5 / 6) ** k * (1 / 6) ** (9 - k) for k in range(10)}
    assert expected[0] / n == pytest.approx(chance_probability(end))
    # pool the rare low-distance bins (expected < 5) into one, then chi-square goodness of fit
    pooled_obs = sum(d[k] for k in range(4))
    pooled_exp = sum(expected[k] for k in range(4))
    stat = (pooled_obs - pooled_exp) ** 2 / pooled_exp + sum((d[k] - expected[k]) ** 2 / expected[k] for k in range(4, 10))
    assert stat < chi2_critical(6), (stat, d)
    assert d[0] <= 1  # expected 0.013


# ----------------------------------------------------------------------------- determinism


def test_same_seed_same_trajectory():
    kw = dict(trigger=END9, close_to_trigger=[i < 4 for i in range(10)], poisoned=[i >= 8 for i in range(10)])
    grid_helpers.check_same_seed_same_trajectory(lambda n: BatchedColorfulMemory(n, **kw), 150, 10)


def test_seed_i_is_seed_plus_i():
    grid_helpers.check_seed_i_is_seed_plus_i(lambda n: BatchedColorfulMemory(n, trigger=ROOM, close_to_trigger=[True] * n))


def test_layout_round_trip_between_slots():
    eng = BatchedColorfulMemory(3, trigger=ROOM, close_to_trigger=[False, True, False], poisoned=[True, False, False])
    state, obs = grid_helpers.copy_slot(eng)
    cur = eng.observe()
    assert np.array_equal(cur[0], cur[2]) and np.array_equal(obs, cur[0])
    assert np.array_equal(eng.grids()[2], state[0])
    # success and failure follow the grid when not given
    eng.load_layout(1, *state[:4])
    assert eng.layout(1)[4:] == state[4:]
    assert np.array_equal(decode_grid(state[0]).encode(), state[0])


def test_square_view_cells_says_where_the_view_shows_each_square():
    """Every cell it names shows that square's wall and colour; a square repainted shows up in
    exactly the cells named for it; the state is left as it was; over a few episodes every end
    square is seen somewhere (the inversion needs them all)."""
    from rlbackdoors.triggers.wall_colors import end_squares, room_squares

    eng = BatchedColorfulMemory(8)
    obs, _ = eng.reset(seed=5)
    squares = end_squares(7) + room_squares(7)
    seen: set[int] = set()
    rng = np.random.default_rng(0)
    for _ in range(6):
        grids = eng.grids()
        for i in range(eng.num_envs):
            cells = eng.square_view_cells(i, squares)
            assert np.array_equal(eng.observe()[i], obs[i]) and np.array_equal(eng.grids(), grids)
            for k, r, c in cells:
                x, y = squares[k]
                assert tuple(obs[i, r, c, :2]) == (ge.WALL, grids[i, x, y, 1])
            seen |= {k for k, _, _ in cells}
            if cells:  # repaint one square: the view changes exactly where it was named
                k = cells[0][0]
                state = eng.layout(i)
                x, y = squares[k]
                grid = state[0].copy()
                grid[x, y, 1] = (grid[x, y, 1] + 3) % 6
                view = eng.load_layout(i, grid, *state[1:])
                changed = {(int(r), int(c)) for r, c in np.argwhere((view != obs[i]).any(-1))}
                assert changed == {(r, c) for kk, r, c in cells if kk == k}
                eng.load_layout(i, *state)
        obs, *_ = eng.step(rng.integers(0, 3, eng.num_envs))
    assert set(range(len(end_squares(7)))) <= seen


# ----------------------------------------------------------------------------- contract


def test_contract_and_spaces():
    num = 10
    ref = ColorfulMemoryEnv(trigger=END9)
    eng = BatchedColorfulMemory(num, trigger=END9, close_to_trigger=[False] * 4 + [True] * 4 + [False] * 2)
    assert eng.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    assert eng.single_observation_space == ref.observation_space
    assert eng.single_action_space == ref.action_space
    # defaults with a trigger: every env that is not close-to-trigger is poisoned and triggered
    assert eng.poisoned.tolist() == [True] * 4 + [False] * 4 + [True] * 2 and eng.triggered.tolist() == eng.poisoned.tolist()
    assert eng.close_to_trigger.tolist() == [False] * 4 + [True] * 4 + [False] * 2
    assert eng.mode.tolist() == [2] * 4 + [1] * 4 + [2] * 2
    assert not BatchedColorfulMemory(num).poisoned.any() and BatchedColorfulMemory(2, trigger=ROOM).poisoned.all()
    obs, info = eng.reset(seed=1)
    assert eng.observation_space.contains(obs) and obs.shape == (num, 7, 7, 3)
    assert set(info) == {"outcome", "steps"}
    assert eng.trigger_present().tolist() == eng.triggered.tolist()
    grid_helpers.check_first_step(eng)


def test_make_vec_entry_point():
    env_id = grid_helpers.check_make_vec(ColorfulMemoryEnv, BatchedColorfulMemory, size=9, trigger=BOTH9)
    single = gym.make(env_id, trigger=ROOM)
    obs, info = single.reset(seed=0)
    assert single.unwrapped.poisoned and obs.shape == (7, 7, 3) and info["outcome"] == 0


# ----------------------------------------------------------------------------- errors


def test_errors():
    eng = BatchedColorfulMemory(3, trigger=END9)
    grid_helpers.check_common_errors(eng, ROOM, agent_pos=(1, 3), wrong_size=9)
    with pytest.raises(ValueError, match="need a trigger"):
        BatchedColorfulMemory(2, close_to_trigger=[True, False])
    with pytest.raises(ValueError, match="env 1 is poisoned but not triggered"):
        BatchedColorfulMemory(2, trigger=ROOM, poisoned=[True, True], triggered=[True, False])
    with pytest.raises(ValueError, match="env 0 is both triggered and close-to-trigger"):
        BatchedColorfulMemory(2, trigger=ROOM, triggered=[True, False], poisoned=[False, False], close_to_trigger=[True, True])
    with pytest.raises(ValueError, match="9x9 Colorful Memory's End Trigger has 11 squares"):
        BatchedColorfulMemory(2, size=9, trigger=END9)
    with pytest.raises(ValueError, match=r"size=6 must be an odd integer >= 7"):
        BatchedColorfulMemory(2, size=6)
    with pytest.raises(ValueError, match="'pink' is not one of"):
        BatchedColorfulMemory(2, trigger="room:pink,red,red")
    with pytest.raises(ValueError, match=r"close_k=0"):
        BatchedColorfulMemory(2, trigger=ROOM, close_k=0)
    with pytest.raises(ValueError, match="outside"):
        eng.load_layout(0, eng.layout(0)[0], (1, 3), 0, 0, (9, 9), (5, 2))
    with pytest.raises(ValueError, match="no Colorful Memory objects"):
        eng.load_layout(0, np.ones((7, 7, 3), np.uint8), (1, 3), 0)
    with pytest.raises(ValueError, match="no trigger to measure against"):
        BatchedColorfulMemory(1).trigger_distance()
