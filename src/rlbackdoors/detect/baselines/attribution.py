"""Attribution: how the policy's outputs respond to its input along clean rollouts.

A backdoor is a feature the network watches for; that can show in the Jacobian of its outputs
with respect to its input even when the trigger is absent (a poisoned net may be unusually
sensitive to some channel or cell). For each clean example state (or a few seeded clean
rollouts when a model ships none) this takes the Jacobian of the centred action logits (PPO)
or action means (OPAC²) and of the value with respect to the first layer's input (the raw
observation, or the one-hot planes of a one-hot net; the normalised observation of OPAC²),
by autograd, one backward pass per output over the whole batch (samples are independent).

Per model, for the actor and the value: log10 of the per-state gradient norm (mean, std,
quantiles), a histogram of log10 |dJ| over all entries, and where the input is an image the
saliency map's entropy and largest share over cells and over channels (plus the share of each
channel); also the value and action entropy on the clean states. A logistic regression per
architecture (pooled over shared features across architectures) turns them into a probability.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

from rlbackdoors.detect import rollouts
from rlbackdoors.detect.api import FeatureDetector, Param, register
from rlbackdoors.detect.handle import ModelHandle

LOG_EDGES = (-6.0, -4.0, -3.0, -2.0, -1.0, 0.0, 1.0)  # log10 |dJ| histogram bin edges (8 bins with the tails)


class _Capture(nn.Module):
    """Stands in for a network's first layer: makes its input a leaf that keeps its gradient.

    The grid models run their layers through ``run_sequential`` (no module hooks), which calls
    any layer type it does not know as a module, so a wrapper sees the input."""

    def __init__(self, inner: nn.Module):
        super().__init__()
        self.inner = inner
        self.captured: torch.Tensor | None = None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x.detach().requires_grad_(True)
        self.captured = x
        return self.inner(x)


def _install_capture(model: nn.Module) -> _Capture:
    """Wrap the first Linear/Conv2d (in registration order, inside a Sequential) of ``model``."""
    for parent in model.modules():
        if isinstance(parent, nn.Sequential):
            for index, child in enumerate(parent):
                if isinstance(child, (nn.Linear, nn.Conv2d)):
                    capture = _Capture(child)
                    parent[index] = capture
                    return capture
    raise ValueError(f"{type(model).__name__} has no Linear or Conv2d layer inside a Sequential")


def _memories(policy: nn.Module, episodes: list) -> list[torch.Tensor]:
    """The recurrent memory before each step of each episode (played from a fresh memory)."""
    from rlbackdoors.algos.obs import to_torch

    out = []
    with torch.no_grad():
        for episode in episodes:
            memory = policy.initial_memory(1, "cpu")  # type: ignore[operator]  # recurrent nets define it (agent.recurrent)
            steps = []
            for t in range(rollouts.length(episode)):
                steps.append(memory[0])
                _, _, memory = policy(to_torch(rollouts.take(episode, slice(t, t + 1))), memory)
            out.append(torch.stack(steps))
    return out


def jacobians(agent, episodes: list, max_states: int) -> tuple[np.ndarray, np.ndarray, tuple[int, ...], dict[str, float]]:
    """(actor J (N, A, D), value J (N, D), the input's shape per state, output statistics)."""
    from rlbackdoors.algos.obs import to_torch

    total = sum(rollouts.length(e) for e in episodes)
    if total == 0:
        raise ValueError("no clean observations to differentiate at")
    keep = np.unique(np.linspace(0, total - 1, min(max_states, total)).round().astype(int))
    batch = rollouts.take(rollouts.concat(episodes), keep)
    policy = agent.policy
    if not isinstance(policy, nn.Module):  # OPAC²: Gaussian means and V of the normalised observation
        x = torch.as_tensor(policy.normalize(np.asarray(batch, np.float32))).requires_grad_(True)
        actor = policy.policy(x)[0]
        value = policy.v(x)
        stats = {
            "out.value_mean": float(value.detach().mean()),
            "out.value_std": float(value.detach().std()),
            "out.action_abs_mean": float(actor.detach().tanh().abs().mean()),
        }
    else:
        capture = _install_capture(policy)
        obs = to_torch(batch)
        if agent.recurrent:
            memory = torch.cat(_memories(policy, episodes))[torch.as_tensor(keep)]
            logits, value, _ = policy(obs, memory)
        else:
            logits, value = policy(obs)
        captured = capture.captured
        assert captured is not None
        x = captured
        actor = logits - logits.mean(1, keepdim=True)
        probs = torch.softmax(logits.detach(), 1)
        entropy = -(probs * torch.log(probs.clamp_min(1e-12))).sum(1)
        stats = {"out.value_mean": float(value.detach().mean()), "out.value_std": float(value.detach().std()), "out.entropy_mean": float(entropy.mean())}
    grads_actor = []
    for k in range(actor.shape[1]):
        (g,) = torch.autograd.grad(actor[:, k].sum(), x, retain_graph=True)
        grads_actor.append(g)
    (g_value,) = torch.autograd.grad(value.sum(), x)
    j_actor = torch.stack(grads_actor, 1).detach().double().numpy()
    return j_actor, g_value.detach().double().numpy(), tuple(x.shape[1:]), stats


def _spatial(j: np.ndarray, shape: tuple[int, ...], image: tuple[int, ...] | None) -> np.ndarray | None:
    """|J| as (N, ..., C, H, W) when the input is an image (conv input, or a flattened one)."""
    n = j.shape[0]
    lead = j.shape[1 : -len(shape)] if j.ndim > len(shape) + 1 else ()
    if len(shape) == 3:
        return np.abs(j).reshape(n, *lead, *shape)
    if len(shape) == 1 and image is not None and int(np.prod(image)) == shape[0]:
        h, w, c = image
        return np.abs(j).reshape(n, *lead, c, h, w)  # flattened channels-first (c, x, y), as the grid nets do
    return None


def _entropy_share(weights: np.ndarray) -> tuple[float, float]:
    total = weights.sum()
    if not total > 0 or weights.size < 2:
        return 0.0, 1.0
    p = weights.reshape(-1) / total
    nz = p[p > 0]
    return float(-(nz * np.log(nz)).sum() / math.log(p.size)), float(p.max())


def summarize(j: np.ndarray, shape: tuple[int, ...], image: tuple[int, ...] | None, prefix: str) -> dict[str, float]:
    """Features of one output group's Jacobian (module doc)."""
    n = j.shape[0]
    flat = j.reshape(n, -1)
    norms = np.log10(np.linalg.norm(flat, axis=1) + 1e-12)
    out = {
        f"{prefix}.lognorm_mean": float(norms.mean()),
        f"{prefix}.lognorm_std": float(norms.std()),
        f"{prefix}.lognorm_q10": float(np.quantile(norms, 0.1)),
        f"{prefix}.lognorm_q50": float(np.quantile(norms, 0.5)),
        f"{prefix}.lognorm_q90": float(np.quantile(norms, 0.9)),
        f"{prefix}.lognorm_max": float(norms.max()),
    }
    magnitudes = np.log10(np.abs(flat).reshape(-1) + 1e-30)
    counts = np.histogram(magnitudes, bins=(-np.inf, *LOG_EDGES, np.inf))[0]
    out.update({f"{prefix}.hist{b}": float(c) / magnitudes.size for b, c in enumerate(counts)})
    spatial = _spatial(j, shape, image)
    if spatial is not None:
        per_cell = spatial.reshape(-1, *spatial.shape[-3:]).sum(axis=(0, 1))  # (H, W)
        per_channel = spatial.reshape(-1, *spatial.shape[-3:]).sum(axis=(0, 2, 3))  # (C,)
        out[f"{prefix}.cell_entropy"], out[f"{prefix}.cell_max_share"] = _entropy_share(per_cell)
        out[f"{prefix}.channel_entropy"], out[f"{prefix}.channel_max_share"] = _entropy_share(per_channel)
        shares = per_channel / max(per_channel.sum(), 1e-300)
        out.update({f"{prefix}.channel{c}_share": float(s) for c, s in enumerate(shares)})
    return out


def attribution_features(handle: ModelHandle, episodes: int = 4, max_states: int = 200, seed: int = 3_000_000) -> dict[str, float]:
    agent = handle.build_agent()
    sequences = rollouts.observations(handle, agent, episodes, seed)
    j_actor, j_value, shape, stats = jacobians(agent, sequences, max_states)
    first = sequences[0]
    raw = first["image"] if isinstance(first, dict) and "image" in first else first
    image = tuple(np.asarray(raw).shape[1:]) if not isinstance(raw, dict) and np.asarray(raw).ndim == 4 else None
    features = dict(stats)
    features.update(summarize(j_actor, shape, image, "actor"))
    features.update(summarize(j_value, shape, image, "value"))
    features["states"] = float(j_actor.shape[0])
    return features


@register
class AttributionDetector(FeatureDetector):
    name = "attribution"
    description = "Jacobians of action logits and value w.r.t. observations on clean states -> logistic regression"
    defaults: ClassVar[dict[str, Any]] = {**FeatureDetector.defaults, "max_states": 200, "episodes": 4, "seed": 3_000_000}
    rules: ClassVar[dict[str, Param]] = {
        **FeatureDetector.rules,
        "max_states": Param(1, 100_000, help="clean states whose Jacobians are taken"),
        "episodes": Param(1, 10_000, help="clean episodes played to collect them"),
        "seed": Param(0, 2**31 - 1, help="seed of those episodes"),
    }

    def features(self, model: ModelHandle) -> dict[str, float]:
        with torch.enable_grad():
            return attribution_features(model, int(self.params["episodes"]), int(self.params["max_states"]), int(self.params["seed"]))
