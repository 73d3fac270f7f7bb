"""What every batched grid engine shares: argument checks, seeding and slot indexing.

The engines differ in their numba kernels and layout state; the gymnasium-facing checks
(num_envs, per-env masks, seeds, actions, slot indices) are the same and live here, so an
error reads the same whichever world raised it.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv

NUM_ACTIONS = 3
ACTIONS_DOC = f"Discrete({NUM_ACTIONS}) (0 left, 1 right, 2 forward)"


def seed_array(seed, num_envs: int) -> np.ndarray:
    """Per-env uint64 seeds: ``seed + i`` for an int, a given list, or fresh entropy for None."""
    if seed is None:
        return np.random.SeedSequence().generate_state(num_envs, dtype=np.uint64)
    if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
        seeds = [int(seed) + i for i in range(num_envs)]
    else:
        seeds = list(seed)
        if len(seeds) != num_envs:
            raise ValueError(f"got {len(seeds)} seeds for {num_envs} envs")
    fresh = None
    out = np.empty(num_envs, dtype=np.uint64)
    for i, s in enumerate(seeds):
        if s is None:
            if fresh is None:
                fresh = np.random.SeedSequence().generate_state(num_envs, dtype=np.uint64)
            out[i] = fresh[i]
            continue
        if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or not 0 <= int(s) < 2**64:
            raise ValueError(f"seed {s!r} must be a non-negative integer below 2**64 (or None)")
        out[i] = int(s)
    return out


def bool_mask(values, num_envs: int, name: str) -> np.ndarray:
    """A per-env bool mask of exactly ``num_envs`` entries (a copy)."""
    arr = np.asarray(values, dtype=np.bool_).copy()
    if arr.shape != (num_envs,):
        raise ValueError(f"{name} mask has shape {arr.shape}, expected ({num_envs},)")
    return arr


class BatchedGridEnv(VectorEnv):
    """Base of the numba engines: SAME_STEP autoreset, B envs in one process, no rendering."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def _init_batch(self, num_envs, render_mode) -> int:
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs={num_envs!r} must be a positive integer")
        if render_mode is not None:
            raise ValueError(f"render_mode={render_mode!r} is not supported by {type(self).__name__} (use None)")
        self.num_envs = int(num_envs)
        self.render_mode = None
        self._has_reset = False
        return self.num_envs

    def _check_actions(self, actions) -> np.ndarray:
        """Actions as int64[B]; shape, dtype and call order are checked here, values by the kernel."""
        if not self._has_reset:
            raise RuntimeError(f"{type(self).__name__}.step() called before reset()")
        acts = np.asarray(actions)
        if acts.shape != (self.num_envs,):
            raise ValueError(f"actions have shape {acts.shape}, expected ({self.num_envs},)")
        if acts.dtype.kind not in "iub":
            raise ValueError(f"actions must be integers in {ACTIONS_DOC}, got dtype {acts.dtype}")
        return acts.astype(np.int64, copy=False)

    def _step_outputs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Fresh (reward, terminated, truncated, outcome, steps) arrays for one step's kernel to fill."""
        b = self.num_envs
        return (
            np.empty(b, dtype=np.float64), np.empty(b, dtype=np.bool_), np.empty(b, dtype=np.bool_),
            np.empty(b, dtype=np.int64), np.empty(b, dtype=np.int64),
        )

    def _reset_info(self, **extra) -> dict:
        """Mark the batch reset and return reset's info: no outcome yet, step 0 (plus ``extra``)."""
        self._has_reset = True
        zeros = np.zeros(self.num_envs, dtype=np.int64)
        return {"outcome": zeros, "steps": zeros.copy(), **extra}

    @staticmethod
    def _bad_action(acts: np.ndarray, env: int) -> ValueError:
        return ValueError(f"action {acts[env]!r} (env {env}) is not in {ACTIONS_DOC}")

    def _check_index(self, i) -> int:
        if isinstance(i, bool) or not isinstance(i, (int, np.integer)) or not 0 <= i < self.num_envs:
            raise IndexError(f"env index {i!r} is not in 0..{self.num_envs - 1}")
        return int(i)

    def _check_cell(self, cell, name: str) -> tuple[int, int]:
        try:
            x, y = (int(v) for v in cell)
        except (TypeError, ValueError):
            raise ValueError(f"{name}={cell!r} must be an (x, y) pair") from None
        if not (0 <= x < self.size and 0 <= y < self.size):
            raise ValueError(f"{name} {(x, y)} is outside the {self.size}x{self.size} grid")
        return x, y

    def _check_state(self, i, grid, agent_pos, agent_dir, step_count) -> tuple[int, np.ndarray, tuple[int, int]]:
        """Validate a slot state for ``load_layout``: ``(slot, grid array, agent cell)``.

        Engines check their own extras after this and only then call :meth:`_write_state`,
        so a rejected state leaves the slot untouched.
        """
        i = self._check_index(i)
        arr = np.asarray(grid)
        if arr.shape != self._grid.shape[1:]:
            raise ValueError(f"grid has shape {arr.shape}, expected {self._grid.shape[1:]}")
        if arr.dtype.kind not in "iub" or arr.min() < 0 or arr.max() > 255:
            raise ValueError("grid must hold uint8 (object, colour, state) triples")
        pos = self._check_cell(agent_pos, "agent_pos")
        if not 0 <= int(agent_dir) <= 3:
            raise ValueError(f"agent_dir={agent_dir!r} must be in 0..3")
        if not 0 <= int(step_count):
            raise ValueError(f"step_count={step_count!r} must be >= 0")
        return i, arr, pos

    def _write_state(self, i: int, arr: np.ndarray, pos: tuple[int, int], agent_dir, step_count) -> None:
        self._grid[i] = arr
        self._pos[i] = pos
        self._dir[i] = int(agent_dir)
        self._steps[i] = int(step_count)
        self._has_reset = True

    def state_dict(self) -> dict:
        """The engine's whole state as plain data (layouts, positions, RNG words): a checkpoint."""
        from rlbackdoors.state import snapshot

        return snapshot(self)

    def load_state_dict(self, state: dict) -> None:
        """Put a :meth:`state_dict` of an engine built with the same arguments back."""
        from rlbackdoors.state import restore

        restore(self, state)

    def close_extras(self, **kwargs):
        pass


__all__ = ["ACTIONS_DOC", "BatchedGridEnv", "NUM_ACTIONS", "bool_mask", "seed_array"]
