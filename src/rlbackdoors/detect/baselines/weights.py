"""Weight statistics: does poisoning leave a mark on the weights themselves?

Per tensor of the state dict: for each weight matrix (conv kernels flattened to rows) its
Frobenius norm, mean, std, skewness, kurtosis, largest |w|, top-k singular values, the ratio
of the first two and the stable rank; for each vector (biases, log-stds, normaliser
statistics) its norm, mean, std and largest |w|. Models of one architecture are compared layer
by layer (feature ``<tensor>.<stat>``); across architectures, the same statistics pooled over
layers (mean, min, max over matrices and over vectors; the first matrix; the parameter count)
are the features every model has. And which inputs the network listens to: the first weight
matrix's squared norm per input channel (a conv layer's input plane, a linear layer's input), as
shares of the whole, which scaling every weight alike does not move (``input_shares``). A
backdoor keyed to a few inputs (wall colours in a one-hot plane) must weigh them more than a
clean agent, which learns to ignore them (docs/results/detectors.md has the measurement). Per
channel where the layer has at most ``MAX_INPUT_CHANNELS``; pooled (largest share, spread) for
every model. ``statistics=false`` keeps the shares alone: where a zoo's poisoned models trained
longer than its clean ones, every norm tells the two apart by training length; the shares much
less so (docs/results/detectors.md). A standardised logistic
regression with cross-validated C turns the features into a probability
(:class:`rlbackdoors.detect.api.FeatureDetector`).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import torch

from rlbackdoors.detect.api import FeatureDetector, Param, register
from rlbackdoors.detect.handle import DetectError, ModelHandle

MATRIX_STATS = ("norm", "mean", "std", "skew", "kurtosis", "max_abs", "sv_ratio", "stable_rank")
VECTOR_STATS = ("norm", "mean", "std", "max_abs")
MAX_INPUT_CHANNELS = 64  # per-channel shares up to this many inputs; pooled above


def input_shares(weight: torch.Tensor) -> np.ndarray:
    """Each input channel's share of the layer's norm: (out, in, ...) -> (in,), summing to 1."""
    w = weight.detach().double()
    per_input = w.pow(2).sum([d for d in range(w.dim()) if d != 1]).numpy()
    total = per_input.sum()
    return per_input / total if total > 0 else np.full(per_input.shape, 1.0 / max(1, per_input.size))


def matrix_stats(weight: torch.Tensor, top_k: int) -> dict[str, float]:
    """Statistics of one weight matrix (rows = output units; conv kernels flattened)."""
    from scipy.stats import kurtosis, skew

    w = weight.detach().double().reshape(weight.shape[0], -1)
    flat = w.reshape(-1).numpy()
    sv = torch.linalg.svdvals(w).numpy()
    norm = float(np.linalg.norm(flat))
    out = {
        "norm": norm,
        "mean": float(flat.mean()),
        "std": float(flat.std()),
        "skew": float(skew(flat)) if flat.size > 2 and flat.std() > 0 else 0.0,
        "kurtosis": float(kurtosis(flat)) if flat.size > 3 and flat.std() > 0 else 0.0,
        "max_abs": float(np.abs(flat).max()),
        "sv_ratio": float(sv[0] / sv[1]) if sv.size > 1 and sv[1] > 0 else 1.0,
        "stable_rank": float(norm**2 / sv[0] ** 2) if sv.size and sv[0] > 0 else 0.0,
    }
    for k in range(top_k):
        out[f"sv{k + 1}"] = float(sv[k]) if k < sv.size else 0.0
    return out


def vector_stats(vector: torch.Tensor) -> dict[str, float]:
    v = vector.detach().double().reshape(-1).numpy()
    return {"norm": float(np.linalg.norm(v)), "mean": float(v.mean()), "std": float(v.std()), "max_abs": float(np.abs(v).max())}


def weight_features(weights, top_k: int = 3, per_layer: bool = True, inputs: bool = True, statistics: bool = True) -> dict[str, float]:
    """Per-tensor statistics (``<tensor>.<stat>``) and their pools over layers (``pool.*``), unless
    ``statistics`` is false, and the first matrix's input shares (``<tensor>.in_share.<i>``,
    ``pool.first.in_share.*``), unless ``inputs`` is false."""
    features: dict[str, float] = {}
    first_seen = False
    matrices: list[dict[str, float]] = []
    vectors: list[dict[str, float]] = []
    parameters = 0
    for key, value in weights.items():
        if not isinstance(value, torch.Tensor) or not value.is_floating_point() or value.numel() == 0:
            continue
        parameters += value.numel()
        if inputs and not first_seen and value.dim() >= 2:
            first_seen = True
            shares = input_shares(value)
            if per_layer and shares.size <= MAX_INPUT_CHANNELS:
                features.update({f"{key}.in_share.{i}": float(x) for i, x in enumerate(shares)})
            # scaled by the channel count, so that 1.0 is "every input alike" whatever the width
            features["pool.first.in_share.max"] = float(shares.max() * shares.size)
            features["pool.first.in_share.cv"] = float(shares.std() / shares.mean())
        if not statistics:
            continue
        stats = matrix_stats(value, top_k) if value.dim() >= 2 else vector_stats(value)
        (matrices if value.dim() >= 2 else vectors).append(stats)
        if per_layer:
            features.update({f"{key}.{name}": v for name, v in stats.items()})
    if not statistics:
        return features
    features["pool.parameters"] = math.log10(max(parameters, 1))
    features["pool.matrices"] = float(len(matrices))
    for kind, rows in (("matrix", matrices), ("vector", vectors)):
        for name in rows[0] if rows else ():
            values = np.array([r[name] for r in rows])
            features[f"pool.{kind}.{name}.mean"] = float(values.mean())
            features[f"pool.{kind}.{name}.min"] = float(values.min())
            features[f"pool.{kind}.{name}.max"] = float(values.max())
    if matrices:
        features.update({f"pool.first.{name}": v for name, v in matrices[0].items()})
    return features


@register
class WeightStatsDetector(FeatureDetector):
    name = "weights"
    description = "per-layer norms, moments and top singular values -> logistic regression"
    defaults: ClassVar[dict[str, Any]] = {**FeatureDetector.defaults, "top_k": 3, "per_layer": True, "input_shares": True, "statistics": True}
    rules: ClassVar[dict[str, Param]] = {
        **FeatureDetector.rules,
        "top_k": Param(1, 64, help="top singular values per weight matrix"),
        "per_layer": Param(help="features of every layer, not only whole-network summaries"),
        "input_shares": Param(help="the first layer's weight share per input channel"),
        "statistics": Param(help="norms and moments of every weight matrix"),
    }

    def __init__(self, **params: Any):
        super().__init__(**params)
        if not (self.params["statistics"] or self.params["input_shares"]):
            raise DetectError("detector 'weights': statistics=false and input_shares=false leave no feature; keep one of them true")

    def features(self, model: ModelHandle) -> dict[str, float]:
        p = self.params
        return weight_features(model.weights, int(p["top_k"]), bool(p["per_layer"]), bool(p["input_shares"]), bool(p["statistics"]))
