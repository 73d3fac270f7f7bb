"""Observation batches as torch tensors: a plain array or a dict of arrays
(e.g. ``{"image", "direction"}``), handled by the same few helpers so the
algorithms never branch on the world."""

from __future__ import annotations

from typing import Callable, TypeVar

import numpy as np
import torch

Obs = torch.Tensor | dict
Batch = TypeVar("Batch", torch.Tensor, np.ndarray)


def obs_map(fn: Callable[[Batch], Batch], obs: Batch | dict) -> Batch | dict:
    """Apply ``fn`` to the tensor (or numpy array), or to every one of a dict observation."""
    if isinstance(obs, dict):
        return {k: fn(v) for k, v in obs.items()}
    return fn(obs)


def to_torch(obs: np.ndarray | dict, device: torch.device | str = "cpu") -> Obs:
    """numpy observation batch -> torch (zero-copy on the CPU)."""
    if isinstance(obs, dict):
        return {k: torch.from_numpy(np.asarray(v)).to(device) for k, v in obs.items()}
    return torch.from_numpy(obs).to(device)


def empty_buffer(obs: np.ndarray | dict, length: int) -> Obs:
    """A (length, B, ...) buffer with the dtypes of one observation batch."""
    return obs_map(lambda x: torch.empty((length, *x.shape), dtype=x.dtype), to_torch(obs))


def store(buffer: Obs, t: int, obs: np.ndarray | dict) -> None:
    """``buffer[t] = obs`` for either kind of observation."""
    if isinstance(buffer, dict):
        for k, v in buffer.items():
            v[t] = torch.from_numpy(np.asarray(obs[k]))
    else:
        buffer[t] = torch.from_numpy(obs)


def stack_numpy(batches: list) -> np.ndarray | dict:
    """K numpy observation batches (arrays or dicts of them) stacked on a new leading dimension."""
    if isinstance(batches[0], dict):
        return {k: np.stack([np.asarray(b[k]) for b in batches]) for k in batches[0]}
    return np.stack(batches)


def stack(batches: list) -> Obs:
    """K observation batches (tensors or dicts of tensors) stacked on a new leading dimension."""
    if isinstance(batches[0], dict):
        return {k: torch.stack([b[k] for b in batches]) for k in batches[0]}
    return torch.stack(batches)
