"""Randomized LavaWorld stepped by JAX (envs/randomized_lavaworld_jax.py) against the numba engine,
bit for bit.

The numba engine is itself checked against its MiniGrid reference (test_randomized_lavaworld_engine.py),
so equal bytes here mean the reference's dynamics. Two engines are reset alike; one is handed to
the JAX side, which steps it in compiled blocks (``lax.scan`` of the step, as the compiled
trainer's rollout does), the other is stepped by numba with the same random actions; every output
of every step is compared (image, direction, reward as float32, termination, truncation, outcome,
episode step), and at each block's end the whole state (grid, position, direction, step count,
terminal view and direction, the pattern's mask, cells and count, ``saw_trigger``). Layouts are
handed over shallow (2 a slot) so that blocks starve and run again deeper, and after the last
block the slots are handed back and the numba engine goes on from there. The slots are poisoned,
triggered with the clean reward, near-trigger or clean; each case steps 40 slots x 300 steps
(12,000 slot-steps; 60,000 over the cases, across some 3,000 autoresets).
"""

from __future__ import annotations

import numpy as np
import pytest

import jax  # a core dependency: the compiled trainer's

from grid_helpers import assert_step_matches, run_block  # noqa: E402
from rlbackdoors.envs.batched_base import EngineGroup  # noqa: E402
from rlbackdoors.envs.grid_device import pad_grid  # noqa: E402
from rlbackdoors.envs.outcome import Outcome  # noqa: E402
from rlbackdoors.envs.randomized_lavaworld_batched import BatchedRandomizedLavaWorld  # noqa: E402
from rlbackdoors.envs.randomized_lavaworld_jax import randomized_lavaworld_jax  # noqa: E402
from rlbackdoors.triggers.pattern import PatternTrigger, near_patterns  # noqa: E402

N = 40


def engine(trigger="cross", size=11, num_lava=10, max_steps=250, see=True, near=True, seed=7, turned=False) -> BatchedRandomizedLavaWorld:
    """Slots by fours: poisoned, triggered with the clean reward, near-trigger, clean. ``turned``:
    each first layout with the agent facing north, the pattern out of sight (a drawn layout shows
    one of its cells in the first view), so ``saw_trigger`` turns on mid-episode."""
    kind = np.arange(N) % 4
    patterns = [p.spec() for p in near_patterns(PatternTrigger.parse(trigger))] if trigger and near else []
    e = BatchedRandomizedLavaWorld(
        N,
        size,
        num_lava,
        max_steps,
        see,
        trigger=trigger,
        poisoned=kind == 0 if trigger else None,
        triggered=kind <= 1 if trigger else None,
        near_patterns=patterns,
    )
    if patterns:
        e.near_next(kind == 2)
    e.reset(seed=seed)
    if turned:
        for i in range(N):
            grid, pos, _, _, cells, _ = e.layout(i)
            e.load_layout(i, grid, pos, 3, 0, cells)
    return e


def state_of(e) -> dict[str, np.ndarray]:
    return {
        "grid": e._grid,
        "pos": e._pos,
        "dirs": e._dir,
        "steps": e._steps,
        "final_image": e.final_obs["image"],
        "final_direction": e.final_obs["direction"],
        "pat": e._pat,
        "pcells": e._pcells,
        "pcount": e._pcount,
        "saw": e._saw,
    }


def step_both(numba_side, jax_side, blocks: int, block: int, depth: int, seed: int = 0) -> tuple[np.ndarray, int, int, int]:
    """Step both sides ``blocks`` x ``block`` steps with the same random actions, comparing every
    output (and whether each view shows the whole trigger, ``trigger_in_sight``); the outcomes of
    the episodes that ended, how many blocks ran again deeper, how often ``saw_trigger`` turned on
    mid-episode and how many views showed the whole trigger."""
    world, params, host = jax_side
    rollout = jax.jit(world.rollout)
    rng = np.random.default_rng(seed)
    ends, reruns, flips, sights = [], 0, 0, 0
    slots = host.slots
    for k in range(blocks):
        acts = rng.integers(0, 3, (block, host.num_envs))
        before = slots
        slots, out, again = run_block(host, rollout, slots, params, acts, depth)
        reruns += again
        for t in range(block):
            saw = numba_side._saw.copy()
            step = numba_side.step(acts[t])
            obs, _, terminated, truncated, info = step
            flips += int((~saw & numba_side._saw & ~(terminated | truncated)).sum())
            assert_step_matches(step, out, t, f"block {k} step {t}", image=obs["image"])
            direction = np.asarray(out.dirs[t])
            assert direction.dtype == np.int32 and np.array_equal(direction, obs["direction"]), f"block {k} step {t}: direction differs"
            if hasattr(numba_side, "trigger_in_sight"):  # (an engine group has none of its own)
                want_sight = numba_side.trigger_in_sight()
                assert np.array_equal(np.asarray(out.sight[t]), want_sight), f"block {k} step {t}: trigger in sight differs"
                sights += int(want_sight.sum())
            ends.append(info["outcome"][terminated | truncated])
        assert before is not slots
        got = {
            "grid": slots.grid,
            "pos": slots.pos,
            "dirs": slots.dirs,
            "steps": slots.steps,
            "final_image": slots.final_obs,
            **dict(zip(("pat", "pcells", "pcount", "saw", "final_direction"), slots.world)),
        }
        want = state_of(numba_side)
        want["grid"] = pad_grid(want["grid"], host.view_size)
        for name, value in want.items():
            assert np.array_equal(np.asarray(got[name]), value), f"after block {k}: {name} differs"
    host.hand_back(jax.tree_util.tree_map(np.asarray, slots))
    return np.concatenate(ends), reruns, flips, sights


@pytest.mark.parametrize(
    "trigger,size,num_lava,max_steps,see,turned",
    [
        ("cross", 11, 10, 250, True, True),
        ("arrow:east", 11, 10, 60, False, False),
        ("arrow:any", 9, 6, 40, True, False),
        ("cells:0,0;1,1", 7, 3, 30, False, True),
        (None, 11, 10, 50, True, False),
    ],
)
def test_jax_steps_as_the_numba_engine_and_hands_the_slots_back(trigger, size, num_lava, max_steps, see, turned):
    """40 slots (poisoned, triggered, near, clean), 6 compiled blocks of 50 random steps; then
    both engines, the handed-back one and numba's own, step on alike, and their states are equal."""
    sides = [engine(trigger, size, num_lava, max_steps, see, turned=turned) for _ in range(2)]
    numba_side, handed = sides
    ends, reruns, flips, sights = step_both(numba_side, randomized_lavaworld_jax(handed), 6, 50, depth=2)
    assert (sights > 0) == (trigger is not None)  # whole patterns were in view, and were told so
    assert (flips > 0) == turned  # the flag's own path was stepped where a pattern began out of sight
    assert len(ends) > N * 300 / max_steps  # every slot ended episodes and took drawn layouts
    assert {int(Outcome.LAVA), int(Outcome.TIMEOUT)} <= set(ends.tolist())
    if trigger is not None and max_steps < 100:
        assert int(Outcome.PATTERN_LAVA) in set(ends.tolist())  # the pattern's lava, told apart
    assert reruns > 0  # some block ended more than 2 episodes in a slot: run again, deeper
    for name, value in state_of(numba_side).items():  # handed back: the numba engine's own state
        assert np.array_equal(state_of(handed)[name], value), name
    rng = np.random.default_rng(99)
    for _ in range(30):  # the numba engine goes on from the handed-back state as from its own
        acts = rng.integers(0, 3, N)
        a, b = numba_side.step(acts), handed.step(acts)
        assert all(np.array_equal(a[0][key], b[0][key]) for key in ("image", "direction"))
        assert all(np.array_equal(x, y) for x, y in zip(a[1:4], b[1:4]))
        assert all(np.array_equal(a[4][key], b[4][key]) for key in ("outcome", "trigger_visible", "saw_trigger"))


def test_jax_steps_an_engine_group_of_several_triggers():
    """Three agents' engines in one group (a clean one, two triggers): each slot reads its own pattern."""
    sides = [EngineGroup.of([engine(None, seed=1), engine("cross", seed=2), engine("arrow:east", seed=3)]) for _ in range(2)]
    group, other = sides
    jax_side = randomized_lavaworld_jax(other)
    assert jax_side[2].num_envs == 3 * N and jax_side[1].poisoned.any() and not jax_side[1].poisoned.all()
    ends, _, _, _ = step_both(group, jax_side, 4, 50, depth=4, seed=5)
    assert len(ends) > 3 * N


def test_errors():
    with pytest.raises(ValueError, match="reset the engines"):
        randomized_lavaworld_jax(BatchedRandomizedLavaWorld(2))
    from rlbackdoors.envs.lavaworld_batched import BatchedLavaWorld

    with pytest.raises(TypeError, match="not a BatchedRandomizedLavaWorld"):
        randomized_lavaworld_jax(BatchedLavaWorld(2))


def clean_engine(seed: int = 11) -> BatchedRandomizedLavaWorld:
    """20 clean slots of an engine with a trigger and near-trigger patterns, none switched on (an
    attack's budget switches them per episode: the layouts' kinds)."""
    e = BatchedRandomizedLavaWorld(
        20,
        11,
        10,
        40,
        True,
        trigger="cross",
        poisoned=[False] * 20,
        triggered=[False] * 20,
        near_patterns=[p.spec() for p in near_patterns(PatternTrigger.parse("cross"))],
    )
    e.reset(seed=seed)
    return e


def test_a_kinds_queue_draws_its_own_stream_and_leaves_the_engines_as_they_were():
    """KindLayouts: the trigger's queue holds the cross in every layout, the near queue a
    near-trigger pattern (not the trigger: no count), drawn from streams of their own; the main
    queue draws the same layouts as an engine that has no other queue, and a rewound queue draws
    its untaken layouts again."""
    from rlbackdoors.envs.grid_jax import HostLayouts, KindLayouts

    plain_host = randomized_lavaworld_jax(clean_engine())[2]
    main = randomized_lavaworld_jax(clean_engine())[2]
    trigger, near = KindLayouts(main, "trigger", 0x1234567), KindLayouts(main, "near", 0x7654321)
    t, n = trigger.layouts(6), near.layouts(6)
    got, want = main.layouts(6), plain_host.layouts(6)
    for name in ("grid", "pos", "dirs", "view"):
        assert np.array_equal(getattr(got, name), getattr(want, name)), name
    cells = np.arange(got.world[1].shape[2])[None, None, :] < got.world[2][..., None]  # a layout's pattern cells (the rest is scratch, never read)
    assert np.array_equal(got.world[1][cells], want.world[1][cells])
    assert all(np.array_equal(got.world[i], want.world[i]) for i in (0, 2, 3))
    count = lambda q: q.world[2]  # noqa: E731  # each layout's pattern cells
    assert (count(t) > 0).all() and (count(got) == 0).all() and (count(n) == 0).all()
    unswitched = randomized_lavaworld_jax(clean_engine())[2]  # the near queue's streams, drawn with no pattern
    unswitched.host._rng[:] = np.asarray(clean_engine()._rng) ^ np.uint64(0x7654321)
    differ = (unswitched.layouts(6).grid != n.grid).any((2, 3, 4))
    assert differ[:, 0].all()  # every first near layout holds a near pattern where the same stream draws none
    assert not np.array_equal(t.grid, n.grid) and not np.array_equal(t.grid, got.grid)
    assert not main.host.triggered.any() and not main.host.near.any()  # the switches are put back
    trigger.took(np.full(20, 2))
    rest = trigger.layouts(4).grid
    streams = trigger.rewind()
    assert np.array_equal(streams, trigger.streams) and not np.array_equal(streams, np.asarray(main.host._rng) ^ np.uint64(0x1234567))
    assert np.array_equal(trigger.layouts(4).grid, rest)  # drawn again from where they were
    assert isinstance(main, HostLayouts) and main.num_envs == trigger.num_envs == 20
    with pytest.raises(TypeError, match="rewind"):
        trigger.hand_back(main.slots)


def test_a_step_with_kinds_takes_each_slots_layout_from_the_queue_it_names():
    """A rollout of 200 random steps, each slot taking from the queue its kind names (fixed per
    slot here), gives the same bytes as the plain rollout of one queue holding each slot's chosen
    layouts; each queue counts only the layouts taken from it."""
    world, params, main = randomized_lavaworld_jax(clean_engine(3))
    from rlbackdoors.envs.grid_jax import KindLayouts, Layouts

    queues = (main.layouts(32), KindLayouts(main, "trigger", 99).layouts(32), KindLayouts(main, "near", 98).layouts(32))
    kind = np.arange(20) % 3
    pick = lambda *fields: np.choose(kind.reshape((20,) + (1,) * (fields[0].ndim - 1)), fields)  # noqa: E731
    chosen = Layouts(*(pick(*f) if name not in ("world", "taken", "starved") else None for name, f in zip(Layouts._fields, zip(*queues))))
    chosen = chosen._replace(world=tuple(pick(*w) for w in zip(*(q.world for q in queues))), taken=queues[0].taken, starved=queues[0].starved)
    acts = np.random.default_rng(0).integers(0, 3, (200, 20)).astype(np.int32)

    def rollout(slots, layouts, kind):
        def body(carry, a):
            s, q = carry
            s, q, out = world.step(s, q, params, a, kind)
            return (s, q), out

        return jax.lax.scan(body, (slots, layouts), acts)

    (s1, q1), out1 = jax.jit(rollout, static_argnums=())(main.slots, queues, jax.numpy.asarray(kind, dtype=jax.numpy.int32))
    (s2, q2), out2 = jax.jit(lambda s, q: rollout(s, q, None))(main.slots, chosen)
    for a, b in zip(jax.tree_util.tree_leaves((s1, out1)), jax.tree_util.tree_leaves((s2, out2))):
        assert np.array_equal(np.asarray(a), np.asarray(b))
    ended = np.asarray(q2.taken)
    assert ended.min() >= 2 and not bool(q2.starved) and not any(bool(q.starved) for q in q1)
    for k, q in enumerate(q1):
        assert np.array_equal(np.asarray(q.taken), np.where(kind == k, ended, 0))
    assert (np.asarray(s1.world[2])[kind == 1] > 0).all() and (np.asarray(s1.world[2])[kind != 1] == 0).all()
