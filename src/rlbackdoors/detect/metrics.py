"""How a detector is scored: AUC, cross-entropy and Brier score, each with a bootstrap CI.

* AUC: ``sklearn.metrics.roc_auc_score`` (undefined, NaN, when the models hold one label only).
* Cross-entropy, as the TrojAI leaderboard computes it (usnistgov/trojai-test-harness,
  ``leaderboards/metrics.py``, ``AverageCrossEntropy.compute_cross_entropy``): predictions in
  float64 clipped to ``[1e-12, 1 - 1e-12]``, per model ``-(y ln p + (1 - y) ln(1 - p))``, the
  mean over models. A constant 0.5 scores ln 2 = 0.693; lower is better.
* Brier score: mean of ``(p - y)^2`` (TrojAI's ``BrierScore``: no clipping).
* 95% CIs: percentile bootstrap over models (``resamples`` draws of n models with replacement,
  fixed seed); a resample with one label only has no AUC and is skipped, and the number of
  resamples used is reported.

Means are taken as ``x0 + fsum(x - x0) / n``: exact for equal values, so the constant
detector's CE comes out as ln 2 to the last bit rather than a rounding of it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

EPSILON = 1e-12  # TrojAI's clipping of probabilities for the cross-entropy
RESAMPLES = 2000
SEED = 0
LEVEL = 0.95
METRICS = ("auc", "ce", "brier")


def _mean(values: np.ndarray) -> float:
    values = np.asarray(values, dtype=np.float64)
    if values.size == 0:
        return math.nan
    x0 = float(values.flat[0])
    return x0 + math.fsum((values - x0).tolist()) / values.size


def _arrays(probabilities, labels) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(probabilities, dtype=np.float64).reshape(-1)
    y = np.asarray(labels, dtype=np.float64).reshape(-1)
    if p.shape != y.shape:
        raise ValueError(f"{p.size} probabilities for {y.size} labels")
    return p, y


def cross_entropy_per_model(probabilities, labels, epsilon: float = EPSILON) -> np.ndarray:
    p, y = _arrays(probabilities, labels)
    p = np.clip(p, epsilon, 1.0 - epsilon)
    return -(y * np.log(p) + (1.0 - y) * np.log(1.0 - p))


def cross_entropy(probabilities, labels, epsilon: float = EPSILON) -> float:
    return _mean(cross_entropy_per_model(probabilities, labels, epsilon))


def brier(probabilities, labels) -> float:
    p, y = _arrays(probabilities, labels)
    return _mean(np.square(p - y))


def auc(probabilities, labels) -> float:
    from sklearn.metrics import roc_auc_score

    p, y = _arrays(probabilities, labels)
    if len(np.unique(y)) < 2:
        return math.nan
    return float(roc_auc_score(y, p))


def _auc_rows(p: np.ndarray, y: np.ndarray) -> np.ndarray:
    """AUC of each row (Mann-Whitney U from mid-ranks, ties counted half, as roc_auc_score);
    NaN for a row with one label. Vectorised: 2000 resamples cost milliseconds."""
    from scipy.stats import rankdata

    ranks = rankdata(p, axis=1)
    positives = y.sum(axis=1)
    negatives = y.shape[1] - positives
    with np.errstate(invalid="ignore", divide="ignore"):
        u = (ranks * y).sum(axis=1) - positives * (positives + 1) / 2.0
        return np.where((positives > 0) & (negatives > 0), u / (positives * negatives), np.nan)


FUNCTIONS: dict[str, Callable[[np.ndarray, np.ndarray], float]] = {"auc": auc, "ce": cross_entropy, "brier": brier}


def bootstrap_ci(metric: str, probabilities, labels, resamples: int = RESAMPLES, seed: int = SEED, level: float = LEVEL) -> tuple[float, float, int]:
    """(low, high, resamples used) of the percentile bootstrap CI of ``metric`` over models."""
    p, y = _arrays(probabilities, labels)
    n = p.size
    if n == 0:
        return math.nan, math.nan, 0
    rng = np.random.default_rng(seed)
    index = rng.integers(0, n, size=(int(resamples), n))
    values = []
    if metric == "auc":
        values = [v for v in _auc_rows(p[index], y[index]) if math.isfinite(v)]  # one-label resamples: NaN, skipped
    elif metric == "ce":
        per = cross_entropy_per_model(p, y)
        values = [_mean(per[row]) for row in index]
    elif metric == "brier":
        per = np.square(p - y)
        values = [_mean(per[row]) for row in index]
    else:
        raise ValueError(f"metric {metric!r} is not one of {', '.join(METRICS)}")
    if not values:
        return math.nan, math.nan, 0
    tail = (1.0 - level) / 2.0 * 100.0
    low, high = np.percentile(np.asarray(values), [tail, 100.0 - tail])
    return float(low), float(high), len(values)


def summarize(probabilities, labels, resamples: int = RESAMPLES, seed: int = SEED) -> dict:
    """``{"n", "poisoned", "auc"|"ce"|"brier": {"value", "ci": [low, high], "resamples"}}``."""
    p, y = _arrays(probabilities, labels)
    out: dict = {"n": int(p.size), "poisoned": int(y.sum())}
    for name, fn in FUNCTIONS.items():
        low, high, used = bootstrap_ci(name, p, y, resamples, seed)
        out[name] = {"value": fn(p, y), "ci": [low, high], "resamples": used}
    return out


def summarize_rows(rows: Sequence[Mapping], resamples: int = RESAMPLES, seed: int = SEED) -> dict:
    """:func:`summarize` of per-model rows (``detect score``'s ``models``: ``probability``,
    ``label``), each metric as ``{"value", "ci"}``; ``{"n": 0}`` for no rows. What a script pooling
    several scorings (held-out subsets, both halves of a cross-fit, a control) reports."""
    if not rows:
        return {"n": 0}
    out = summarize([r["probability"] for r in rows], [r["label"] for r in rows], resamples, seed)
    return {"n": out["n"], "poisoned": out["poisoned"], **{k: {"value": out[k]["value"], "ci": out[k]["ci"]} for k in FUNCTIONS}}


def breakdown(probabilities, labels, factors: Mapping[str, Sequence[str]], resamples: int = RESAMPLES, seed: int = SEED) -> dict:
    """Per factor (``{"world": [...one level per model]}``), per level: :func:`summarize`."""
    p, y = _arrays(probabilities, labels)
    out: dict = {}
    for factor, levels in factors.items():
        levels = [str(v) for v in levels]
        if len(levels) != p.size:
            raise ValueError(f"factor {factor!r} has {len(levels)} values for {p.size} models")
        out[factor] = {}
        for level in sorted(set(levels)):
            mask = np.array([v == level for v in levels])
            out[factor][level] = summarize(p[mask], y[mask], resamples, seed)
    return out


# ----- plots ----------------------------------------------------------------------------------------
def plot_roc(probabilities, labels, groups: Sequence[str] | None, path: str | Path, title: str = "ROC") -> Path:
    """ROC curve of all models and of each group with both labels (e.g. per world)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from sklearn.metrics import roc_curve

    p, y = _arrays(probabilities, labels)
    fig, ax = plt.subplots(figsize=(5, 5), dpi=120)
    curves = [("all", np.ones(p.size, bool))]
    if groups is not None and len(set(groups)) > 1:
        curves += [(g, np.array([x == g for x in groups])) for g in sorted(set(groups))]
    for name, mask in curves:
        if len(np.unique(y[mask])) < 2:
            continue
        fpr, tpr, _ = roc_curve(y[mask], p[mask])
        ax.plot(fpr, tpr, lw=2 if name == "all" else 1, label=f"{name} (AUC {auc(p[mask], y[mask]):.3f}, n={int(mask.sum())})")
    ax.plot([0, 1], [0, 1], color="grey", ls="--", lw=0.8)
    ax.set(xlabel="false positive rate", ylabel="true positive rate", title=title, xlim=(0, 1), ylim=(0, 1.01))
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="lower right", fontsize=7)
    else:  # one label only (a control of clean models): no curve to draw, say so
        ax.text(0.5, 0.5, "one label only: no ROC curve", ha="center", va="center", fontsize=9)
    return _save(fig, path)


def reliability(probabilities, labels, bins: int = 10) -> dict:
    """The reliability curve's numbers: for each of ``bins`` equal-width bins of the predicted
    probability that holds a model, its models, their mean prediction and their share poisoned; and
    the expected calibration error, the models-weighted mean of |prediction - share| over the bins.
    Why beside CE: CE mixes ranking and calibration; the curve says which way a detector is off
    (too sure, too shy) and where."""
    p, y = _arrays(probabilities, labels)
    edges = np.linspace(0.0, 1.0, bins + 1)
    which = np.clip(np.digitize(p, edges[1:-1]), 0, bins - 1)
    rows: list[dict[str, Any]] = []
    for b in range(bins):
        mask = which == b
        if mask.any():
            rows.append(
                {
                    "bin": [float(edges[b]), float(edges[b + 1])],
                    "models": int(mask.sum()),
                    "mean_probability": float(p[mask].mean()),
                    "share_poisoned": float(y[mask].mean()),
                }
            )
    gap = sum(r["models"] * abs(r["mean_probability"] - r["share_poisoned"]) for r in rows)
    return {"bins": rows, "ece": gap / len(p) if len(p) else float("nan")}


def plot_calibration(probabilities, labels, path: str | Path, bins: int = 10, title: str = "calibration") -> Path:
    """Reliability diagram (share poisoned per predicted-probability bin) over a histogram of predictions."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p, y = _arrays(probabilities, labels)
    edges = np.linspace(0.0, 1.0, bins + 1)
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(5, 6), dpi=120, gridspec_kw={"height_ratios": [3, 1]}, sharex=True)
    curve = reliability(p, y, bins)["bins"]
    xs, ys, ns = [r["mean_probability"] for r in curve], [r["share_poisoned"] for r in curve], [r["models"] for r in curve]
    top.plot([0, 1], [0, 1], color="grey", ls="--", lw=0.8, label="perfectly calibrated")
    top.plot(xs, ys, marker="o", label="detector")
    for x, v, n in zip(xs, ys, ns):
        top.annotate(str(n), (x, v), textcoords="offset points", xytext=(4, 4), fontsize=6)
    top.set(ylabel="share poisoned", title=title, xlim=(0, 1), ylim=(-0.02, 1.02))
    top.legend(loc="upper left", fontsize=7)
    bottom.hist([p[y == 0], p[y == 1]], bins=edges, stacked=True, label=["clean", "poisoned"], color=["tab:blue", "tab:red"])
    bottom.set(xlabel="predicted probability poisoned", ylabel="models")
    bottom.legend(fontsize=7)
    return _save(fig, path)


def plot_auc_grid(rows: Sequence[str], columns: Sequence[str], cells: dict, path: str | Path, title: str = "AUC") -> Path:
    """A table of AUCs as a heatmap: ``cells[(row, column)]`` is ``{"value", "ci", "models"}`` (a
    summary cell) or absent. Each square shows the AUC, its 95 % CI and the test models, coloured
    from 0 (red) through chance (white) to 1 (blue): a detector that fails on an attack it was not
    fitted on shows up at a glance, which a table of 40 rows does not do."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    grid = np.full((len(rows), len(columns)), np.nan)
    for (r, c), cell in cells.items():
        if cell.get("value") is not None:
            grid[rows.index(r), columns.index(c)] = cell["value"]
    fig, ax = plt.subplots(figsize=(1.6 + 1.5 * len(columns), 0.9 + 0.45 * len(rows)), dpi=120)
    cmap = matplotlib.colormaps["RdBu"].with_extremes(bad="0.9")
    image = ax.imshow(np.ma.masked_invalid(grid), cmap=cmap, vmin=0.0, vmax=1.0, aspect="auto")
    for (r, c), cell in cells.items():
        if cell.get("value") is None:
            continue
        ci = cell.get("ci")
        text = f"{cell['value']:.2f}" + (f"\n[{ci[0]:.2f}, {ci[1]:.2f}]" if ci else "") + (f"\nn={cell['models']}" if cell.get("models") else "")
        dark = abs(cell["value"] - 0.5) > 0.3  # the ends of the map are dark: white text there
        ax.text(columns.index(c), rows.index(r), text, ha="center", va="center", fontsize=6.5, color="white" if dark else "black")
    ax.set_xticks(range(len(columns)), labels=list(columns), fontsize=8)
    ax.set_yticks(range(len(rows)), labels=list(rows), fontsize=7)
    ax.set_title(title, fontsize=9)
    fig.colorbar(image, ax=ax, fraction=0.04, pad=0.02).set_label("AUC (0.5: chance)", fontsize=7)
    return _save(fig, path)


def _save(fig, path: str | Path) -> Path:
    import io

    import matplotlib.pyplot as plt

    from rlbackdoors.io import atomic_write_bytes

    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return atomic_write_bytes(path, buf.getvalue())


__all__ = [
    "EPSILON",
    "METRICS",
    "auc",
    "bootstrap_ci",
    "breakdown",
    "brier",
    "cross_entropy",
    "cross_entropy_per_model",
    "plot_auc_grid",
    "plot_calibration",
    "reliability",
    "plot_roc",
    "summarize",
]
