"""Checks on optimiser state read from a checkpoint (untrusted input).

``Optimizer.load_state_dict`` takes moment tensors as they come; a fused Adam step then runs
over them unchecked, and a moment of the wrong size crashes the process. Checked here first.
"""

from __future__ import annotations

import torch


def check_optimizer_state(optimizer: torch.optim.Optimizer, name: str = "optimizer") -> None:
    """Raise ValueError unless every parameter's state matches it in shape and dtype."""
    for group in optimizer.param_groups:
        for param in group["params"]:
            state = optimizer.state.get(param, {})
            for key, value in state.items():
                if not isinstance(value, torch.Tensor):
                    raise ValueError(f"{name}: state {key!r} is not a tensor")
                if key == "step":
                    if value.numel() != 1 or not value.is_floating_point():
                        raise ValueError(f"{name}: state 'step' must be one float")
                elif value.shape != param.shape or value.dtype != param.dtype or value.device != param.device:
                    raise ValueError(f"{name}: state {key!r} has shape {tuple(value.shape)}, the parameter {tuple(param.shape)}")
