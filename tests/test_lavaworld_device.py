"""LavaWorld stepped by torch ops (envs/lavaworld_device.py) against the numba engine, bit for bit.

The numba engine is itself checked against Farama MiniGrid (test_lavaworld_engine.py), so equal
bytes here mean MiniGrid's dynamics. Two engines are reset alike; one is handed to the device
engine, the other stepped by numba with the same random actions, and every output of every step
is compared: observations, rewards (float64), terminations, truncations, outcomes, episode steps
and the terminal views. The views are also compared on random cells of every object MiniGrid has
(doors open, closed, locked; keys, balls, boxes) at random positions, border included, which the
crossing layouts alone never show. Runs on the CPU; tests/test_group_cuda.py repeats the stepping
on a GPU.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from rlbackdoors.envs import grid_engine as ge
from rlbackdoors.envs.batched_base import EngineGroup
from rlbackdoors.envs.grid_device import pad_grid, visibility_table
from rlbackdoors.envs.lavaworld_batched import BatchedLavaWorld
from rlbackdoors.envs.lavaworld_device import DeviceLavaWorld
from rlbackdoors.envs.outcome import Outcome


def engine(num, size=9, crossings=1, max_steps=250, see=False, trigger="multiplicative:12", seed=7) -> BatchedLavaWorld:
    e = BatchedLavaWorld(num, size, crossings, max_steps, see, trigger=trigger, poisoned=[trigger is not None and i % 2 == 0 for i in range(num)])
    e.reset(seed=seed)
    return e


def step_both(host, numba_step, device: DeviceLavaWorld, steps: int, seed: int = 0) -> np.ndarray:
    """Step both sides with the same random actions, comparing every output; the outcomes seen."""
    rng = np.random.default_rng(seed)
    seen = []
    for t in range(steps):
        acts = rng.integers(0, 3, device.num_envs)
        obs, reward, terminated, truncated, info = numba_step(acts)
        d_obs, d_reward, d_term, d_trunc, d_outcome, d_steps = device.step(torch.from_numpy(acts).to(device.device))
        pairs = {
            "obs": (obs, d_obs),
            "reward": (reward, d_reward),
            "terminated": (terminated, d_term),
            "truncated": (truncated, d_trunc),
            "outcome": (info["outcome"], d_outcome),
            "steps": (info["steps"], d_steps),
            "final_obs": (np.asarray(host.final_obs), device.final_obs),
        }
        for name, (want, got) in pairs.items():
            got = got.cpu().numpy()
            assert got.dtype == want.dtype and np.array_equal(got, want), f"step {t}: {name} differs at {np.argwhere(got != want)[:3].tolist()}"
        seen.append(info["outcome"][terminated | truncated])
    return np.concatenate(seen)


@pytest.mark.parametrize(
    "size,crossings,max_steps,see,refill_every,trigger",
    [
        (9, 1, 250, False, 8, "multiplicative:12"),
        (7, 1, 30, False, 1, "additive:100"),
        (11, 3, 60, True, 3, "multiplicative:12"),
        (9, 2, 40, False, 5, None),
    ],
)
def test_device_steps_as_the_numba_engine(size, crossings, max_steps, see, refill_every, trigger):
    """48 slots (half poisoned where there is a trigger), 600 steps of random actions."""
    numba_side = engine(48, size, crossings, max_steps, see, trigger)
    device = DeviceLavaWorld(engine(48, size, crossings, max_steps, see, trigger), "cpu", refill_every)
    ends = step_both(numba_side, numba_side.step, device, 600)
    assert len(ends) > 48 * 600 / max_steps  # every slot ended episodes and took queued layouts
    assert {int(Outcome.LAVA), int(Outcome.TIMEOUT)} <= set(ends.tolist())


def test_device_steps_an_engine_group_with_a_table_per_agent():
    """Three agents' engines in one group (a clean one, two triggers): each slot reads its own table."""
    sides = []
    for _ in range(2):
        engines = [engine(12, trigger=None, seed=1), engine(12, trigger="multiplicative:12", seed=2), engine(12, trigger="additive:100", seed=3)]
        sides.append((engines, EngineGroup.of(engines)))
    (engines, group), (_, other) = sides
    device = DeviceLavaWorld(other, "cpu", refill_every=4)
    assert device.num_envs == 36 and bool(device.poisoned.any()) and not bool(device.poisoned.all())
    ends = step_both(group, group.step, device, 400, seed=5)
    assert len(ends) > 36


@pytest.mark.parametrize("size,see", [(9, False), (11, False), (9, True)])
def test_views_of_random_cells_match_gen_view(size, see):
    """256 slots of random cells (every object, colour and door state), random positions and
    directions, poisoned slots through their table: the device's views are gen_view's."""
    host = engine(256, size, see=see, trigger="additive:100")
    device = DeviceLavaWorld(host, "cpu")
    rng = np.random.default_rng(size)
    objects = np.array([ge.EMPTY, ge.WALL, ge.FLOOR, ge.DOOR, ge.KEY, ge.BALL, ge.BOX, ge.GOAL, ge.LAVA, ge.KEY_ON_FLOOR], dtype=np.uint8)
    grid = np.zeros((256, size, size, 3), dtype=np.uint8)
    grid[..., 0] = rng.choice(objects, (256, size, size), p=[0.35, 0.25, 0.04, 0.16, 0.04, 0.04, 0.04, 0.02, 0.04, 0.02])
    grid[..., 1] = rng.integers(0, 6, (256, size, size))
    grid[..., 2] = np.where(grid[..., 0] == ge.DOOR, rng.integers(0, 3, (256, size, size)), 0)
    pos = rng.integers(0, size, (256, 2))
    dirs = rng.integers(0, 4, 256)
    device.grid, device.pos, device.dirs = torch.from_numpy(pad_grid(grid, host.view_size)), torch.from_numpy(pos), torch.from_numpy(dirs)
    got = device.render().numpy()
    want = np.zeros_like(got)
    n = host.view_size
    view, mask = np.empty((n, n, 3), np.uint8), np.empty((n, n), np.bool_)
    lut = host.trigger.lookup_table()
    for b in range(256):
        ge.gen_view(grid, b, pos[b, 0], pos[b, 1], dirs[b], see, view, mask, want, b)
        if host.poisoned[b]:
            want[b] = lut[want[b]]
    assert np.array_equal(got, want)
    hidden = (want[..., 0] == ge.UNSEEN).mean()
    assert see or 0.2 < hidden < 0.9  # occlusion was exercised, both ways


def test_visibility_table_rows():
    """Spot checks of the tabulated row sweep (7 columns, the agent in column 3)."""
    table, n = visibility_table(7), 7
    agent = 1 << 3
    # nothing blocks: the sweeps light the whole row and mark the whole next row
    assert table[(agent << n) | 0b1111111] == (0b1111111 << n) | 0b1111111
    # the agent's cell cannot be seen behind: only it is visible, nothing marked
    assert table[(agent << n) | 0b1110111] == (agent << n) | 0
    # a wall at column 5: the sweep right stops on it (visible, not passed); left runs to column 0
    assert table[(agent << n) | 0b1011111] == (0b0111111 << n) | 0b0111111


def test_errors():
    with pytest.raises(ValueError, match="reset the engines"):
        DeviceLavaWorld(BatchedLavaWorld(2))
    with pytest.raises(ValueError, match="refill_every"):
        DeviceLavaWorld(engine(2), refill_every=0)
    with pytest.raises(ValueError, match="graph=True needs a CUDA device"):
        DeviceLavaWorld(engine(2), graph=True)
    device = DeviceLavaWorld(engine(3))
    with pytest.raises(ValueError, match=r"action 3 \(env 1\)"):
        device.step(torch.tensor([0, 3, 1]))
    with pytest.raises(ValueError, match="shape"):
        device.step(torch.tensor([0, 1]))
