"""Weight statistics: does poisoning leave a mark on the weights themselves?

Per tensor of the state dict: for each weight matrix (conv kernels flattened to rows) its
Frobenius norm, mean, std, skewness, kurtosis, largest |w|, top-k singular values, the ratio
of the first two and the stable rank; for each vector (biases, log-stds, normaliser
statistics) its norm, mean, std and largest |w|. Models of one architecture are compared layer
by layer (feature ``<tensor>.<stat>``); across architectures, the same statistics pooled over
layers (mean, min, max over matrices and over vectors; the first matrix; the parameter count)
are the features every model has. A standardised logistic regression with cross-validated C
turns them into a probability (:class:`rlbackdoors.detect.api.FeatureDetector`).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np
import torch

from rlbackdoors.detect.api import FeatureDetector, register
from rlbackdoors.detect.handle import ModelHandle

MATRIX_STATS = ("norm", "mean", "std", "skew", "kurtosis", "max_abs", "sv_ratio", "stable_rank")
VECTOR_STATS = ("norm", "mean", "std", "max_abs")


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


def weight_features(weights, top_k: int = 3, per_layer: bool = True) -> dict[str, float]:
    """Per-tensor statistics (``<tensor>.<stat>``) and their pools over layers (``pool.*``)."""
    features: dict[str, float] = {}
    matrices: list[dict[str, float]] = []
    vectors: list[dict[str, float]] = []
    parameters = 0
    for key, value in weights.items():
        if not isinstance(value, torch.Tensor) or not value.is_floating_point() or value.numel() == 0:
            continue
        parameters += value.numel()
        stats = matrix_stats(value, top_k) if value.dim() >= 2 else vector_stats(value)
        (matrices if value.dim() >= 2 else vectors).append(stats)
        if per_layer:
            features.update({f"{key}.{name}": v for name, v in stats.items()})
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
    defaults: ClassVar[dict[str, Any]] = {**FeatureDetector.defaults, "top_k": 3, "per_layer": True}

    def features(self, model: ModelHandle) -> dict[str, float]:
        return weight_features(model.weights, int(self.params["top_k"]), bool(self.params["per_layer"]))
