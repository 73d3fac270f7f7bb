"""Input directions a policy is made blind to: a mitigation's exact removal of an additive trigger.

Why: a trigger that adds the same vector to every observation (an offset ``o + b`` on every byte,
where no byte wraps) reaches a policy whose first layer is linear only as
``W (x + d) = W x + W d``. Fine-tuning under the clean reward cannot unteach it: the trigger blinds
the policy, which then never reaches the goal, so PPO is paid nothing for trying
(docs/results/mitigation.md). Projecting ``d`` out of ``W``'s rows makes ``W (x + d) = W x``
exactly: the trigger, and every multiple of it, is no longer seen, whatever the later layers
learnt. The cost is one input direction each (the view's sum, for an offset of every byte), which the
fine-tuning's clean frames and teacher make up for. A restored trigger that is no such shift (a
multiplier, a pattern) is left to the fine-tuning.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import nn

RANK_TOL = 1e-6  # a shift whose part outside the earlier ones is below this (relative) adds no direction


def first_linear(model: nn.Module) -> nn.Linear | None:
    """The layer that reads the model's input, where it is linear (None: a convolution, or no ``state_emb``)."""
    emb = getattr(model, "state_emb", None)
    layer = emb[0] if isinstance(emb, nn.Sequential) and len(emb) else None
    return layer if isinstance(layer, nn.Linear) else None


@torch.no_grad()
def constant_shift(model: nn.Module, obs: np.ndarray, stamp: Callable[[np.ndarray], np.ndarray]) -> torch.Tensor | None:
    """The vector ``stamp`` adds to every one of ``obs`` as the model's first layer reads them
    (``embed_input``), or None where it adds different ones (a multiplier; an offset that wraps)."""
    x = model.embed_input(torch.as_tensor(obs)).double()  # type: ignore[operator]  # ActorCritic's
    d = model.embed_input(torch.as_tensor(stamp(obs))).double() - x  # type: ignore[operator]
    d = d.reshape(d.shape[0], -1)
    if not d.abs().max() > 0 or not torch.equal(d, d[:1].expand_as(d)):
        return None
    return d[0]


def shift_basis(shifts: Sequence[torch.Tensor | None]) -> torch.Tensor | None:
    """An orthonormal basis (D, r) of the span of the given shifts (Gram-Schmidt in their order,
    deterministic); None where there are none."""
    basis: list[torch.Tensor] = []
    for d in shifts:
        if d is None:
            continue
        v = d.clone()
        for u in basis:
            v -= (v @ u) * u
        if v.norm() > RANK_TOL * d.norm():
            basis.append(v / v.norm())
    return torch.stack(basis, 1) if basis else None


@torch.no_grad()
def project_out(layer: nn.Linear, basis: torch.Tensor) -> None:
    """``W <- W (I - U U^T)``: the layer no longer reads any input direction in ``basis`` (U)."""
    w = layer.weight
    u = basis.to(dtype=torch.float64, device=w.device)
    w.sub_(((w.double() @ u) @ u.T).to(w.dtype))


def observation_sample(vector_env, seed: int, steps: int = 20) -> np.ndarray:
    """Clean observations to read shifts on: the copies' first ones and ``steps`` more under
    actions drawn from ``seed`` (deterministic: the same run, the same sample)."""
    obs, _ = vector_env.reset(seed=seed)
    frames = [obs]
    rng = np.random.default_rng(seed)
    n = vector_env.single_action_space.n
    for _ in range(steps):
        obs, *_ = vector_env.step(rng.integers(0, n, vector_env.num_envs))
        frames.append(obs)
    return np.concatenate(frames)


def clean_sample(env, poison, mix_seed: int, seed: int) -> np.ndarray:
    """:func:`observation_sample` of a clean mix of ``env`` (``poison``'s copies, unpoisoned), closed after."""
    import dataclasses

    from rlbackdoors.poison.mix import make_env_mix

    envs = make_env_mix(env, dataclasses.replace(poison, poisoned=False, evasion={}), mix_seed)
    try:
        return observation_sample(envs, seed)
    finally:
        envs.close()


__all__ = ["RANK_TOL", "clean_sample", "constant_shift", "first_linear", "observation_sample", "project_out", "shift_basis"]
