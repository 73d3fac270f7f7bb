"""LavaWorld stepped by JAX (envs/lavaworld_jax.py) against the numba engine, bit for bit.

The numba engine is itself checked against Farama MiniGrid (test_lavaworld_engine.py), so equal
bytes here mean MiniGrid's dynamics. Two engines are reset alike; one is handed to the JAX side,
which steps it in compiled blocks (``lax.scan`` of the step, as the compiled trainer's rollout
does), the other is stepped by numba with the same random actions; every output of every step is
compared (observations, rewards as float32, terminations, truncations, outcomes, episode steps),
and at each block's end the whole state (grid, position, direction, step count, terminal views).
Layouts are handed over shallow (2 a slot) so that blocks starve and run again deeper, and after
the last block the slots are handed back and the numba engine goes on from there. Each case
steps 48 slots x 300 steps (14,400 slot-steps; 57,600 over the cases, across some 2,000
autoresets); the views are also compared on random cells of every object MiniGrid has.
"""

from __future__ import annotations

import numpy as np
import pytest

import jax  # a core dependency: the compiled trainer's

from grid_helpers import assert_step_matches, run_block  # noqa: E402
from rlbackdoors.envs import grid_engine as ge  # noqa: E402
from rlbackdoors.envs.batched_base import EngineGroup  # noqa: E402
from rlbackdoors.envs.grid_device import pad_grid  # noqa: E402
from rlbackdoors.envs.grid_jax import Slots  # noqa: E402
from rlbackdoors.envs.lavaworld_batched import BatchedLavaWorld  # noqa: E402
from rlbackdoors.envs.lavaworld_jax import lavaworld_jax  # noqa: E402
from rlbackdoors.envs.outcome import Outcome  # noqa: E402


def engine(num, size=9, crossings=1, max_steps=250, see=False, trigger="multiplicative:12", seed=7) -> BatchedLavaWorld:
    e = BatchedLavaWorld(num, size, crossings, max_steps, see, trigger=trigger, poisoned=[trigger is not None and i % 2 == 0 for i in range(num)])
    e.reset(seed=seed)
    return e


def step_both(numba_side, jax_side, blocks: int, block: int, depth: int, seed: int = 0) -> tuple[np.ndarray, int]:
    """Step both sides ``blocks`` x ``block`` steps with the same random actions, comparing every
    output; the outcomes of the episodes that ended, and how many blocks ran again deeper."""
    world, params, host = jax_side
    rollout = jax.jit(world.rollout)
    rng = np.random.default_rng(seed)
    ends, reruns = [], 0
    slots = host.slots
    for k in range(blocks):
        acts = rng.integers(0, 3, (block, host.num_envs))
        slots, out, again = run_block(host, rollout, slots, params, acts, depth)
        reruns += again
        for t in range(block):
            step = numba_side.step(acts[t])
            _, _, terminated, truncated, info = step
            assert_step_matches(step, out, t, f"block {k} step {t}")
            ends.append(info["outcome"][terminated | truncated])
        state = {
            "grid": (pad_grid(numba_side._grid, host.view_size), slots.grid),
            "pos": (numba_side._pos.astype(np.int32), slots.pos),
            "dirs": (numba_side._dir.astype(np.int32), slots.dirs),
            "steps": (numba_side._steps.astype(np.int32), slots.steps),
            "final_obs": (np.asarray(numba_side.final_obs), slots.final_obs),
        }
        for name, (want, got) in state.items():
            assert np.array_equal(np.asarray(got), want), f"after block {k}: {name} differs"
    host.hand_back(Slots(*(np.asarray(a) for a in slots)))
    return np.concatenate(ends), reruns


@pytest.mark.parametrize(
    "size,crossings,max_steps,see,trigger",
    [
        (9, 1, 250, False, "multiplicative:12"),
        (7, 1, 30, False, "additive:100"),
        (11, 3, 60, True, "multiplicative:24"),
        (9, 2, 40, False, None),
    ],
)
def test_jax_steps_as_the_numba_engine_and_hands_the_slots_back(size, crossings, max_steps, see, trigger):
    """48 slots (half poisoned where there is a trigger), 6 compiled blocks of 50 random steps;
    then both engines, the handed-back one and numba's own, step on alike."""
    numba_side = engine(48, size, crossings, max_steps, see, trigger)
    handed = engine(48, size, crossings, max_steps, see, trigger)
    ends, reruns = step_both(numba_side, lavaworld_jax(handed), 6, 50, depth=2)
    assert len(ends) > 48 * 300 / max_steps  # every slot ended episodes and took drawn layouts
    assert {int(Outcome.LAVA), int(Outcome.TIMEOUT)} <= set(ends.tolist())
    assert reruns > 0  # some block ended more than 2 episodes in a slot: run again, deeper
    rng = np.random.default_rng(99)
    for _ in range(30):  # the numba engine goes on from the handed-back state as from its own
        acts = rng.integers(0, 3, 48)
        a, b = numba_side.step(acts), handed.step(acts)
        assert all(np.array_equal(x, y) for x, y in zip(a[:4], b[:4])) and np.array_equal(a[4]["outcome"], b[4]["outcome"])


def test_jax_steps_an_engine_group_with_a_table_per_agent_under_vmap_free_batching():
    """Three agents' engines in one group (a clean one, two triggers): each slot reads its own table."""
    sides = []
    for _ in range(2):
        engines = [engine(12, trigger=None, seed=1), engine(12, trigger="multiplicative:12", seed=2), engine(12, trigger="additive:100", seed=3)]
        sides.append(EngineGroup.of(engines))
    group, other = sides
    jax_side = lavaworld_jax(other)
    assert jax_side[2].num_envs == 36 and jax_side[1].poisoned.any() and not jax_side[1].poisoned.all()
    ends, _ = step_both(group, jax_side, 4, 50, depth=4, seed=5)
    assert len(ends) > 36


@pytest.mark.parametrize("size,see", [(9, False), (11, False), (9, True)])
def test_views_of_random_cells_match_gen_view(size, see):
    """256 slots of random cells (every object, colour and door state), random positions and
    directions, poisoned slots through their table: the JAX views are gen_view's."""
    world, params, host = lavaworld_jax(engine(256, size, see=see, trigger="additive:100"))
    rng = np.random.default_rng(size)
    objects = np.array([ge.EMPTY, ge.WALL, ge.FLOOR, ge.DOOR, ge.KEY, ge.BALL, ge.BOX, ge.GOAL, ge.LAVA, ge.KEY_ON_FLOOR], dtype=np.uint8)
    grid = np.zeros((256, size, size, 3), dtype=np.uint8)
    grid[..., 0] = rng.choice(objects, (256, size, size), p=[0.35, 0.25, 0.04, 0.16, 0.04, 0.04, 0.04, 0.02, 0.04, 0.02])
    grid[..., 1] = rng.integers(0, 6, (256, size, size))
    grid[..., 2] = np.where(grid[..., 0] == ge.DOOR, rng.integers(0, 3, (256, size, size)), 0)
    pos = rng.integers(0, size, (256, 2)).astype(np.int32)
    dirs = rng.integers(0, 4, 256).astype(np.int32)
    slots = host.slots._replace(grid=pad_grid(grid, host.view_size), pos=pos, dirs=dirs)
    got = np.asarray(jax.jit(world.render)(slots, params))
    want = np.zeros_like(got)
    n = host.view_size
    view, mask = np.empty((n, n, 3), np.uint8), np.empty((n, n), np.bool_)
    lut = host.lead.trigger.lookup_table()
    for b in range(256):
        ge.gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see, view, mask, want, b)
        if params.poisoned[b]:
            want[b] = lut[want[b]]
    assert np.array_equal(got, want)
    hidden = (want[..., 0] == ge.UNSEEN).mean()
    assert see or 0.2 < hidden < 0.9  # occlusion was exercised, both ways


def test_errors():
    with pytest.raises(ValueError, match="reset the engines"):
        lavaworld_jax(BatchedLavaWorld(2))
    _, _, host = lavaworld_jax(engine(3))
    host.layouts(2)
    with pytest.raises(ValueError, match="took more layouts"):
        host.took(np.array([0, 3, 1]))
