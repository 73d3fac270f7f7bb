"""A calibrated classifier that is plain data: standardised features, logistic regression.

scikit-learn fits it (``LogisticRegression``, C chosen by stratified cross-validated log loss);
the fitted numbers (feature names, imputation values, mean, scale, coefficients, intercept)
are kept as lists of floats and the prediction is computed here with numpy, so a detector saved
as JSON predicts bit for bit what it predicted before it was saved, and loading it never
unpickles anything.

Zoos mix architectures whose features differ, so :class:`GroupedClassifier` keeps one model
per group (world/arch) where the train set has enough of both labels, and one pooled model on
the features every train model has, used for every other group.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

C_GRID = (0.01, 0.1, 1.0, 10.0, 100.0)
PLATT_C = 1e6  # Platt scaling's fit is unpenalised (the smoothed targets bound it), up to numerics
PROBABILITY_FLOOR = 0.01  # a one-class train set predicts its rate, kept off 0 and 1


@dataclass
class LogisticModel:
    """``p = sigmoid(((x - mean) / scale) . coef + intercept)``; missing features take ``impute``.

    ``kind`` "constant" predicts ``rate`` for everything (a train set with one label only).
    """

    kind: str = "constant"
    rate: float = 0.5
    features: list[str] = field(default_factory=list)
    impute: list[float] = field(default_factory=list)
    mean: list[float] = field(default_factory=list)
    scale: list[float] = field(default_factory=list)
    coef: list[float] = field(default_factory=list)
    intercept: float = 0.0
    C: float = 1.0
    cv_log_loss: float | None = None
    n: int = 0

    def matrix(self, rows: Sequence[Mapping[str, float]]) -> np.ndarray:
        x = np.array([[_number(row.get(name)) for name in self.features] for row in rows], dtype=np.float64).reshape(len(rows), len(self.features))
        missing = ~np.isfinite(x)
        if missing.any():
            x[missing] = np.broadcast_to(np.asarray(self.impute, dtype=np.float64), x.shape)[missing]
        return x

    def predict_rows(self, rows: Sequence[Mapping[str, float]]) -> np.ndarray:
        if self.kind == "constant" or not self.features:
            return np.full(len(rows), float(self.rate))
        z = (self.matrix(rows) - np.asarray(self.mean)) / np.asarray(self.scale)
        logits = z @ np.asarray(self.coef, dtype=np.float64) + float(self.intercept)
        return 1.0 / (1.0 + np.exp(-np.clip(logits, -500.0, 500.0)))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping) -> LogisticModel:
        model = cls(**{k: data[k] for k in data if k in cls.__dataclass_fields__})
        d = len(model.features)
        if model.kind == "logistic" and not all(len(getattr(model, k)) == d for k in ("impute", "mean", "scale", "coef")):
            raise ValueError("a logistic model's impute, mean, scale and coef must each have one value per feature")
        return model


def _number(value) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        return math.nan
    return out if math.isfinite(out) else math.nan


def _standardised(rows: Sequence[Mapping[str, float]], features: Sequence[str], n: int) -> tuple[LogisticModel, np.ndarray]:
    """A logistic model's imputation, mean and scale over ``rows`` (its coefficients unset), and the standardised matrix."""
    model = LogisticModel(kind="logistic", features=list(features), n=n)
    raw = np.array([[_number(row.get(name)) for name in features] for row in rows], dtype=np.float64)
    with np.errstate(all="ignore"):
        impute = np.nanmean(np.where(np.isfinite(raw), raw, np.nan), axis=0)
    model.impute = [float(v) if math.isfinite(v) else 0.0 for v in impute]
    x = model.matrix(rows)
    mean, std = x.mean(0), x.std(0)
    scale = np.where(std > 1e-12 * np.maximum(1.0, np.abs(mean)), std, 1.0)
    model.mean, model.scale = [float(v) for v in mean], [float(v) for v in scale]
    return model, (x - mean) / scale


def _held_out_log_loss(z: np.ndarray, y: np.ndarray, fit, folds) -> float:
    """The log loss of ``fit(z_train, y_train)``'s predictions on each fold it did not see (a fold
    whose train part holds one label predicts that part's rate)."""
    from sklearn.metrics import log_loss

    oof = np.zeros(len(y))
    for train, test in folds.split(z, y):
        if len(np.unique(y[train])) < 2:
            oof[test] = y[train].mean()
            continue
        oof[test] = fit(z[train], y[train]).predict_proba(z[test])[:, 1]
    return float(log_loss(y, np.clip(oof, 1e-12, 1 - 1e-12), labels=[0, 1]))


def fit_logistic(rows: Sequence[Mapping[str, float]], labels: np.ndarray, features: Sequence[str], seed: int = 0) -> LogisticModel:
    """Fit on ``features`` of ``rows``; C from :data:`C_GRID` by cross-validated log loss."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.model_selection import StratifiedKFold

    y = np.asarray(labels, dtype=np.int64)
    n = len(y)
    positives = int(y.sum())
    if n == 0 or positives in (0, n) or not features:
        rate = positives / n if n else 0.5
        return LogisticModel(kind="constant", rate=float(min(1 - PROBABILITY_FLOOR, max(PROBABILITY_FLOOR, rate))), n=n)
    model, z = _standardised(rows, features, n)

    def estimator(c: float):
        return LogisticRegression(C=c, max_iter=5000, random_state=seed)

    smallest = min(positives, n - positives)
    best_c, best_loss = 1.0, None
    if smallest >= 2:
        folds = StratifiedKFold(n_splits=min(5, smallest), shuffle=True, random_state=seed)
        for c in C_GRID:
            loss = _held_out_log_loss(z, y, lambda zt, yt, c=c: estimator(c).fit(zt, yt), folds)
            if best_loss is None or loss < best_loss - 1e-12:
                best_c, best_loss = c, loss
    fitted = estimator(best_c).fit(z, y)
    model.coef = [float(v) for v in fitted.coef_[0]]
    model.intercept = float(fitted.intercept_[0])
    model.C, model.cv_log_loss = float(best_c), best_loss
    return model


def fit_platt(rows: Sequence[Mapping[str, float]], labels: np.ndarray, feature: str, folds: int = 5, seed: int = 0) -> LogisticModel:
    """Platt scaling of one score: a logistic regression on ``feature`` fitted to Platt's (1999)
    smoothed targets, ``(N+ + 1) / (N+ + 2)`` for a positive and ``1 / (N- + 2)`` for a negative,
    not to 0 and 1, and without a penalty to choose. Why: on a few dozen separable models a fit to
    hard labels (any C the cross-validation picks) drives the slope to the largest allowed and
    reads unseen models at 0 or 1; the targets keep the fit as sure as that many models allow.
    ``cv_log_loss`` is the held-out log loss (against the hard labels) of the same fit over
    stratified folds."""
    from sklearn.linear_model import LogisticRegression
    from sklearn.model_selection import StratifiedKFold

    y = np.asarray(labels, dtype=np.int64)
    n, positives = len(y), int(y.sum())
    if n == 0 or positives in (0, n):
        return fit_logistic(rows, y, [], seed)
    model, z = _standardised(rows, [feature], n)

    def fit(z: np.ndarray, y: np.ndarray) -> LogisticRegression:
        n1, n0 = int(y.sum()), int(len(y) - y.sum())
        target = np.where(y == 1, (n1 + 1) / (n1 + 2), 1 / (n0 + 2))
        return LogisticRegression(C=PLATT_C, max_iter=10_000, random_state=seed).fit(
            np.concatenate([z, z]), np.r_[np.ones(len(z)), np.zeros(len(z))], sample_weight=np.r_[target, 1 - target]
        )

    smallest = min(positives, n - positives)
    if smallest >= 2:
        model.cv_log_loss = _held_out_log_loss(z, y, fit, StratifiedKFold(n_splits=min(folds, smallest), shuffle=True, random_state=seed))
    fitted = fit(z, y)
    model.coef, model.intercept, model.C = [float(fitted.coef_[0][0])], float(fitted.intercept_[0]), PLATT_C
    return model


class GroupedClassifier:
    """One :class:`LogisticModel` per group with at least ``min_per_class`` models of each label,
    and a pooled one (features all train models share) for the rest (module doc)."""

    def __init__(self, min_per_class: int = 3, seed: int = 0):
        self.min_per_class, self.seed = int(min_per_class), int(seed)
        self.pooled = LogisticModel()
        self.groups: dict[str, LogisticModel] = {}

    def fit(self, rows: Sequence[Mapping[str, float]], groups: Sequence[str], labels: np.ndarray) -> GroupedClassifier:
        y = np.asarray(labels, dtype=np.int64)
        self.pooled = fit_logistic(rows, y, shared_features(rows), self.seed)
        self.groups = {}
        for group in sorted(set(groups)):
            index = [i for i, g in enumerate(groups) if g == group]
            labels_g = y[index]
            if min(int(labels_g.sum()), len(index) - int(labels_g.sum())) >= self.min_per_class:
                members = [rows[i] for i in index]
                self.groups[group] = fit_logistic(members, labels_g, shared_features(members), self.seed)
        return self

    def predict(self, row: Mapping[str, float], group: str) -> float:
        return float(self.groups.get(group, self.pooled).predict_rows([row])[0])

    def to_dict(self) -> dict:
        return {
            "min_per_class": self.min_per_class,
            "seed": self.seed,
            "pooled": self.pooled.to_dict(),
            "groups": {g: m.to_dict() for g, m in self.groups.items()},
        }

    @classmethod
    def from_dict(cls, data: Mapping) -> GroupedClassifier:
        out = cls(int(data.get("min_per_class", 3)), int(data.get("seed", 0)))
        out.pooled = LogisticModel.from_dict(data.get("pooled") or {})
        out.groups = {str(g): LogisticModel.from_dict(m) for g, m in dict(data.get("groups") or {}).items()}
        return out


def shared_features(rows: Sequence[Mapping[str, float]]) -> list[str]:
    """The feature names every row has, in the first row's order."""
    if not rows:
        return []
    common = set(rows[0])
    for row in rows[1:]:
        common &= set(row)
    return [k for k in rows[0] if k in common]


__all__ = ["GroupedClassifier", "LogisticModel", "fit_logistic", "fit_platt", "shared_features"]
