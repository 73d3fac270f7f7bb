"""Colorful Memory stepped by JAX (envs/colorful_memory_jax.py) against the numba engine, bit for bit.

The numba engine is itself checked against its MiniGrid reference (test_colorful_memory_engine.py),
so equal bytes here mean the reference's dynamics. Two engines are reset alike; one is handed to
the JAX side, which steps it in compiled blocks (``lax.scan`` of the step, as the compiled
trainer's rollout does), the other is stepped by numba with the same random actions; every output
of every step is compared (image, reward as float32, termination, truncation, outcome, episode
step, and ``trigger_in_sight``), and at each block's end the whole state (grid, position,
direction, step count, terminal view, the success and failure cells, the trigger squares shown
this episode and whether it was drawn triggered). Layouts are handed over shallow (2 a slot) so
that blocks starve and run again deeper, and after the last block the slots are handed back and
the numba engine goes on from there. The slots are poisoned, triggered with the clean reward,
close to the trigger or clean; each case steps 40 slots x 300 steps (12,000 slot-steps; 60,000
over the cases, 36,000 in the default run, across thousands of autoresets), and a group of three
engines 120 x 200.
"""

from __future__ import annotations

import numpy as np
import pytest

import jax  # a core dependency: the compiled trainer's

from grid_helpers import assert_step_matches, run_block  # noqa: E402
from rlbackdoors.envs.batched_base import EngineGroup  # noqa: E402
from rlbackdoors.envs.colorful_memory import target_cells  # noqa: E402
from rlbackdoors.envs.colorful_memory_batched import BatchedColorfulMemory  # noqa: E402
from rlbackdoors.envs.colorful_memory_jax import colorful_memory_jax, targets  # noqa: E402
from rlbackdoors.envs.grid_device import pad_grid  # noqa: E402
from rlbackdoors.envs.outcome import Outcome  # noqa: E402

N = 40
END9 = "end:red,green,blue,purple,yellow,grey,red,green,blue"
ROOM = "room:purple,yellow,red"
BOTH = "end+room:grey,grey,blue,blue,red,red,green,green,yellow;yellow,blue,red"
BOTH9 = "end+room:grey,grey,blue,blue,red,red,green,green,yellow,red,red;yellow,blue,red"  # a 9 x 9 world's: 11 end squares


def engine(trigger=END9, size=7, max_steps=40, see=False, seed=7) -> BatchedColorfulMemory:
    """Slots by fours: poisoned, triggered with the clean reward, close to the trigger, clean."""
    kind = np.arange(N) % 4
    e = BatchedColorfulMemory(
        N,
        size,
        max_steps,
        see,
        trigger=trigger,
        poisoned=kind == 0 if trigger else None,
        triggered=kind <= 1 if trigger else None,
        close_to_trigger=kind == 2 if trigger else None,
    )
    e.reset(seed=seed)
    return e


def state_of(e) -> dict[str, np.ndarray]:
    w = e.world if isinstance(e, EngineGroup) else e._world()
    return {
        "grid": e._grid,
        "pos": e._pos,
        "dirs": e._dir,
        "steps": e._steps,
        "final_image": e.final_obs,
        "succ": w[0],
        "fail": w[1],
        "seen": w[6],
        "armed": w[7],
    }


def step_both(numba_side, jax_side, blocks: int, block: int, depth: int, seed: int = 0) -> tuple[np.ndarray, int, int]:
    """Step both sides ``blocks`` x ``block`` steps with the same random actions, comparing every
    output; the outcomes of the episodes that ended, how many blocks ran again deeper, and how
    many steps had a triggered episode that had shown the whole trigger."""
    world, params, host = jax_side
    rollout = jax.jit(world.rollout)
    rng = np.random.default_rng(seed)
    ends, reruns, sights = [], 0, 0
    slots = host.slots
    for k in range(blocks):
        acts = rng.integers(0, 3, (block, host.num_envs))
        slots, out, again = run_block(host, rollout, slots, params, acts, depth)
        reruns += again
        for t in range(block):
            step = numba_side.step(acts[t])
            assert_step_matches(step, out, t, f"block {k} step {t}")
            engines = numba_side.engines if isinstance(numba_side, EngineGroup) else [numba_side]
            want = np.concatenate([e.trigger_in_sight() for e in engines])  # (each engine its own squares)
            assert np.array_equal(np.asarray(out.sight[t]), want), f"block {k} step {t}: trigger in sight differs"
            sights += int(want.sum())
            ends.append(step[4]["outcome"][step[2] | step[3]])
        got = dict(zip(("grid", "pos", "dirs", "steps", "final_image"), (slots.grid, slots.pos, slots.dirs, slots.steps, slots.final_obs)))
        succ, fail, seen, armed = (np.asarray(a) for a in slots.world)
        got |= {"succ": succ, "fail": fail, "armed": armed}
        targets = np.asarray(world.memory_targets(world, jax.tree_util.tree_map(jax.numpy.asarray, slots)))
        assert np.array_equal(targets, numba_side.memory_targets()) and len(set(targets.tolist())) == 2  # what each episode asks to remember
        want = state_of(numba_side)
        valid = np.arange(seen.shape[1])[None, :] < (np.asarray(params.valid).sum(1))[:, None]
        got["seen"] = seen & valid
        want["grid"] = pad_grid(want["grid"], host.view_size)
        for name, value in want.items():
            assert np.array_equal(np.asarray(got[name]), value), f"after block {k}: {name} differs"
    host.hand_back(jax.tree_util.tree_map(np.asarray, slots))
    return np.concatenate(ends), reruns, sights


@pytest.mark.parametrize(
    "trigger,size,max_steps,see",
    [
        (END9, 7, 40, False),
        pytest.param(ROOM, 7, 250, False, marks=pytest.mark.slow),  # (the default run keeps three cases: 36,000 slot-steps)
        (BOTH, 7, 30, True),
        pytest.param(BOTH9, 9, 60, True, marks=pytest.mark.slow),
        (None, 7, 40, False),
    ],
)
def test_jax_steps_as_the_numba_engine_and_hands_the_slots_back(trigger, size, max_steps, see):
    """40 slots (poisoned, triggered, close, clean), 6 compiled blocks of 50 random steps; then
    both engines, the handed-back one and numba's own, step on alike, and their states are equal."""
    numba_side, handed = (engine(trigger, size, max_steps, see) for _ in range(2))
    ends, reruns, sights = step_both(numba_side, colorful_memory_jax(handed), 6, 50, depth=2)
    assert len(ends) > N * 300 / max_steps  # every slot ended episodes and took drawn layouts
    assert int(Outcome.TIMEOUT) in set(ends.tolist()) and {int(Outcome.GOAL), int(Outcome.LAVA)} & set(ends.tolist())
    assert (sights > 0) == (trigger is not None)  # triggered episodes showed the whole trigger, and were told so
    assert reruns > 0  # some block ended more than 2 episodes in a slot: run again, deeper
    for name, value in state_of(numba_side).items():  # handed back: the numba engine's own state
        assert np.array_equal(state_of(handed)[name], value), name
    rng = np.random.default_rng(99)
    for _ in range(30):  # the numba engine goes on from the handed-back state as from its own
        acts = rng.integers(0, 3, N)
        a, b = numba_side.step(acts), handed.step(acts)
        assert all(np.array_equal(x, y) for x, y in zip(a[:4], b[:4])) and np.array_equal(a[4]["outcome"], b[4]["outcome"])
        assert np.array_equal(numba_side.trigger_in_sight(), handed.trigger_in_sight())


def test_jax_steps_an_engine_group_of_several_triggers():
    """Three agents' engines in one group (a clean one, two triggers of 9 and 3 squares): each slot
    reads its own trigger's squares (the group's seen padded to the most)."""
    sides = [EngineGroup.of([engine(None, seed=1), engine(END9, seed=2), engine(ROOM, seed=3)]) for _ in range(2)]
    group, other = sides
    jax_side = colorful_memory_jax(other)
    assert jax_side[2].num_envs == 3 * N and jax_side[1].poisoned.any() and not jax_side[1].poisoned.all()
    ends, _, sights = step_both(group, jax_side, 4, 50, depth=4, seed=5)
    assert len(ends) > 3 * N and sights > 0


def test_targets_are_memory_envs_cells():
    """The success and failure cells read from drawn grids, many at once, are target_cells' of each."""
    e = engine(BOTH9, size=9)
    grids = np.asarray(e.grids())
    succ, fail = targets(grids)
    assert [tuple(map(int, s)) for s in succ] == [target_cells(g)[0] for g in grids]
    assert [tuple(map(int, f)) for f in fail] == [target_cells(g)[1] for g in grids]
    assert len({tuple(map(int, s)) for s in succ}) == 2  # both corridor ends occur


def test_errors():
    with pytest.raises(ValueError, match="reset the engines"):
        colorful_memory_jax(BatchedColorfulMemory(2))
    from rlbackdoors.envs.lavaworld_batched import BatchedLavaWorld

    with pytest.raises(TypeError, match="not a BatchedColorfulMemory"):
        colorful_memory_jax(BatchedLavaWorld(2))
