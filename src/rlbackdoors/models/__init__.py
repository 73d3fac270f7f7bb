"""Model zoo architectures, built by name from a config, and weight loading that accepts TrojAI files."""

from __future__ import annotations

from pathlib import Path

import torch

from rlbackdoors import worlds
from rlbackdoors.io import load_torch
from rlbackdoors.models.minigrid import ActorCritic, CNNModel, FCModel

# Architecture classes per world come from the World registry: the same names ("fc", "cnn") mean
# the paper's model for that world.
# Names other tools used for the same layers (rl-starter-files calls the CNN ``image_conv``).
KEY_ALIASES = {"image_conv.": "state_emb."}


def __getattr__(name: str):
    """A world's architecture class by its class name (imported on first use, from the registry)."""
    from rlbackdoors.worlds.base import load_symbol

    for world in worlds.registered("ppo"):
        for _, path in world.archs:
            if path.rpartition(":")[2] == name:
                return load_symbol(path)
    raise AttributeError(f"module 'rlbackdoors.models' has no attribute {name!r}")


def build_model(arch: str, env: str = worlds.DEFAULT_WORLD, num_actions: int = 3) -> ActorCritic:
    grid = worlds.names("ppo")
    if env not in grid:
        raise ValueError(f"env {env!r} is not one of {', '.join(grid)}")
    return worlds.get(env).arch_class(arch)(num_actions=num_actions)


def _as_state_dict(obj) -> dict:
    if isinstance(obj, dict) and obj and all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in obj.items()):
        return obj
    for key in ("model_state", "state_dict", "model"):
        if isinstance(obj, dict) and key in obj:
            return _as_state_dict(obj[key])
    raise ValueError("it holds no state dict (a dict of tensors)")


def load_weights(model: ActorCritic, path: str | Path) -> ActorCritic:
    """Load a ``torch.save``-d state dict (or module) into ``model``; one clear error if it does not fit."""
    # Plain data only: a pickled module (or anything else needing the unpickler) is refused
    # unread, since unpickling a stranger's file can run its code.
    obj = load_torch(path, "weights file")
    try:
        state = _as_state_dict(obj)
    except ValueError as err:
        raise ValueError(f"weights file {str(path)!r}: {err}") from None
    renamed = {}
    for key, value in state.items():
        for old, new in KEY_ALIASES.items():
            if key.startswith(old):
                key = new + key[len(old) :]
        renamed[key] = value
    expected = model.state_dict()
    missing = sorted(set(expected) - set(renamed))
    unexpected = sorted(set(renamed) - set(expected))
    if missing or unexpected:
        raise ValueError(f"weights in {str(path)!r} do not fit {type(model).__name__}: missing {missing or 'none'}, unexpected {unexpected or 'none'}")
    for key, value in renamed.items():
        if value.shape != expected[key].shape:
            raise ValueError(f"weights in {str(path)!r}: {key} has shape {tuple(value.shape)}, {type(model).__name__} expects {tuple(expected[key].shape)}")
    check_finite(renamed, path)
    model.load_state_dict(renamed)
    return model


def check_finite(state: dict, path) -> None:
    """A NaN or inf weight is no policy: refuse it by name rather than report SRs of 0."""
    for key, value in state.items():
        if isinstance(value, torch.Tensor) and value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise ValueError(f"weights file {str(path)!r}: {key} holds non-finite values (NaN or inf)")


__all__ = ["ActorCritic", "CNNModel", "FCModel", "build_model", "check_finite", "load_weights"]
