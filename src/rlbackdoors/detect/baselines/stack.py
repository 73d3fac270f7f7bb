"""Stacking: the baselines' evidence averaged and recalibrated on out-of-fold scores.

Each baseline alone may rank well but is calibrated conservatively on a small train zoo: its
classifier sees a hundred correlated features and few models, so cross-validation keeps C small
and the probabilities near 0.5, which costs cross-entropy, not AUC. Here each member (at its
defaults, or ``member_params``) computes its features and fits its own classifier, and its logits
on the train models *out of fold* (``folds``-fold stratified cross-validation: scores on models
it did not see) are averaged and Platt-scaled (``meta``: ``platt``, a one-feature logistic
regression on Platt's smoothed targets, :func:`~rlbackdoors.detect.classifier.fit_platt`;
``logistic``, the same on hard labels with C chosen by cross-validated log loss, which on a
separable train split reads unseen models at 0 or 1). One feature, not one per member: with
twenty-odd train models a regression on every member's logit picked wild weights (even negative
ones) on synthetic zoos, where the average was steadier. With one member this is Platt scaling of that member. Scoring a
model costs the sum of its members' costs.

Each member's logit is bounded (``logit_bound``: ``cv`` picks the bound from :data:`BOUNDS` by the
meta model's cross-validated log loss on the out-of-fold logits; ``none`` keeps them whole) before
the average. Why: a member fitted on a few dozen models can be certain and wrong; on issue 80's
round ``weights`` read a poisoned model at p = 1e-4 and its logit (-9.3) outvoted the other two members
(0.38, 0.77), giving 0.012 alone: one such model was a third of the stack's cross-entropy. A stack
saved before the bound existed keeps its unbounded average (and its meta model).

A member that scores its features its own way (``effect``: an anomaly against the clean fit
models, not a classifier) takes part as itself: its out-of-fold logits come from copies of it fitted
on the other folds' rows, and the member fitted on every row is kept (its state in the stack's).
Why: on issue 80's first round the detectors err on different families (``effect`` misses
action-level trojans under offsets that break clean policies too, ``weights`` the env mix), so the
strongest pair is one with ``effect`` in it (docs/results/detectors.md).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar, cast

import numpy as np

from rlbackdoors.detect.api import DetectError, FeatureDetector, Param, _check_labels, get_detector, make_detector, register
from rlbackdoors.detect.classifier import GroupedClassifier, LogisticModel, fit_logistic, fit_platt
from rlbackdoors.detect.handle import ModelHandle

LOGIT_CLIP = 1e-6  # member probabilities are kept in [1e-6, 1 - 1e-6] before the logit
BOUNDS = (math.inf, 6.0, 4.0, 3.0, 2.0)  # the member-logit bounds ``logit_bound=cv`` chooses from (inf: none)


def logit(p: float) -> float:
    p = min(1.0 - LOGIT_CLIP, max(LOGIT_CLIP, float(p)))
    return math.log(p / (1.0 - p))


@register
class StackDetector(FeatureDetector):
    name = "stack"
    description = "members' out-of-fold logits (weights + behaviour by default), averaged and Platt-scaled"
    defaults: ClassVar[dict[str, Any]] = {
        **FeatureDetector.defaults,
        "members": "weights,behaviour",
        "member_params": {},  # {member: {parameter: value}}; a member's other parameters are its defaults
        "folds": 5,
        "seed": 0,
        "logit_bound": "cv",
        "meta": "platt",
    }
    rules: ClassVar[dict[str, Param]] = {
        **FeatureDetector.rules,
        "members": Param(help="member detectors, comma-separated (features-and-classifier detectors)"),
        "member_params": Param(help="{member: {parameter: value}}; other member parameters are their defaults"),
        "folds": Param(2, 100, fit_only=True, help="folds of the members' out-of-fold logits"),
        "seed": Param(0, 2**31 - 1, fit_only=True, help="seed of the folds and classifiers"),
        "logit_bound": Param(choices=("cv", "none"), fit_only=True, help="bound on each member's logit: chosen by cross-validated log loss, or none"),
        "meta": Param(
            choices=("platt", "logistic"), fit_only=True, help="the meta model: Platt scaling (smoothed targets) or a logistic regression with C by CV"
        ),
    }

    def __init__(self, **params: Any):
        super().__init__(**params)
        names = [n.strip() for n in str(self.params["members"]).split(",") if n.strip()]
        if not names or len(set(names)) != len(names) or self.name in names:
            raise DetectError(f"detector 'stack': members={self.params['members']!r} must name distinct other detectors, comma-separated")
        extra = self.params["member_params"]
        stray = sorted(set(extra) - set(names))
        if stray or not all(isinstance(v, dict) for v in extra.values()):
            raise DetectError(f"detector 'stack': member_params must map members ({', '.join(names)}) to parameter tables, got {extra!r}")
        if not all(issubclass(get_detector(n), FeatureDetector) for n in names):
            raise DetectError(f"detector 'stack': every member must be a features-and-classifier detector, got {names}")
        self.members = [self._member(n) for n in names]
        # a classifier member's fitted state; an own-scoring member (its own way, module doc) is its own state
        self.member_classifiers: list[GroupedClassifier | None] = [
            None if self.scores_itself(j) else GroupedClassifier(int(self.params["min_per_class"]), int(self.params["seed"])) for j in range(len(names))
        ]
        self.meta = LogisticModel()
        self.bound = math.inf  # the fitted bound on each member's logit
        self.oof_logits = np.zeros((0, len(names)))  # the members' out-of-fold logits of the last fit (for study; not saved)

    def _member(self, name: str) -> FeatureDetector:
        """A fresh, unfitted member at its parameters (the defaults and ``member_params``)."""
        extra = self.params["member_params"].get(name, {})
        return cast(FeatureDetector, make_detector(name, **{"min_per_class": int(self.params["min_per_class"]), **extra}))

    def scores_itself(self, j: int) -> bool:
        """Whether member ``j`` scores its features its own way rather than by a classifier over them."""
        return type(self.members[j]).classify is not FeatureDetector.classify

    # Each member groups models its own way (by world and architecture, or by world); the
    # stack's group carries all of them, '|'-joined in member order.
    def group(self, model: ModelHandle) -> str:
        return "|".join(m.group(model) for m in self.members)

    def unsupported(self, model: ModelHandle) -> str | None:
        return next((why for m in self.members if (why := m.unsupported(model))), None)

    def features(self, model: ModelHandle) -> dict[str, float]:
        row: dict[str, float] = {}
        info: dict = {}
        for member in self.members:
            member.last_info = {}
            row.update({f"{member.name}:{k}": v for k, v in member.features(model).items()})
            info.update(member.last_info)
        self.last_info = info
        return row

    def _split(self, row: dict[str, float], j: int) -> dict[str, float]:
        prefix = f"{self.members[j].name}:"
        return {k[len(prefix) :]: v for k, v in row.items() if k.startswith(prefix)}

    def _meta_row(self, logits, bound: float | None = None) -> dict[str, float]:
        b = self.bound if bound is None else bound
        return {"mean_logit": float(np.mean(np.clip(logits, -b, b)))}

    def fit_rows(self, rows: list[dict[str, float]], groups: list[str], labels: np.ndarray) -> StackDetector:
        from sklearn.model_selection import StratifiedKFold

        y = _check_labels(rows, labels)
        n, k = len(rows), len(self.members)
        member_rows = [[self._split(row, j) for row in rows] for j in range(k)]
        member_groups = [[g.split("|")[j] for g in groups] for j in range(k)]
        seed = int(self.params["seed"])
        smallest = min(int(y.sum()), n - int(y.sum()))
        oof = np.zeros((n, k))
        if smallest >= 2:
            folds = StratifiedKFold(n_splits=min(int(self.params["folds"]), smallest), shuffle=True, random_state=seed)
            for train, test in folds.split(np.zeros(n), y):
                for j in range(k):
                    part = self._fit_member(j, [member_rows[j][i] for i in train], [member_groups[j][i] for i in train], y[train])
                    for i in test:
                        oof[i, j] = logit(part.predict(member_rows[j][i], member_groups[j][i]))
        fitted = [self._fit_member(j, member_rows[j], member_groups[j], y) for j in range(k)]
        for j, member in enumerate(fitted):
            if isinstance(member, _OwnScoring):
                self.members[j] = member.detector
            else:
                self.member_classifiers[j] = member
        bounds = BOUNDS if self.params["logit_bound"] == "cv" and smallest >= 2 else (math.inf,)
        self.bound, self.meta = min(((bound, self._fit_meta(oof, y, bound, smallest)) for bound in bounds), key=_held_out_loss)  # ties: the loosest
        self.oof_logits = oof
        self.fitted = True
        return self

    def _fit_meta(self, oof: np.ndarray, y: np.ndarray, bound: float, smallest: int) -> LogisticModel:
        """The meta model on the out-of-fold logits bounded at ``bound`` (too few models of a label
        to cross-validate: the train rate)."""
        rows = [self._meta_row(logits, bound) for logits in oof]
        if self.params["meta"] == "platt" and smallest >= 2:
            return fit_platt(rows, y, "mean_logit", int(self.params["folds"]), int(self.params["seed"]))
        return fit_logistic(rows, y, list(rows[0]) if smallest >= 2 else [], int(self.params["seed"]))

    def _fit_member(self, j: int, rows: list[dict[str, float]], groups: list[str], y: np.ndarray) -> GroupedClassifier | _OwnScoring:
        if self.scores_itself(j):
            return _OwnScoring(self._member(self.members[j].name).fit_rows(rows, groups, y))
        return GroupedClassifier(int(self.params["min_per_class"]), int(self.params["seed"])).fit(rows, groups, y)

    def classify(self, row: dict[str, float], group: str) -> float:
        probability, members = self.predict_row(row, group)
        self.last_info = {**self.last_info, **{f"{name}_probability": round(p, 6) for name, p in members.items()}}
        return probability

    def predict_row(self, row: dict[str, float], group: str) -> tuple[float, dict[str, float]]:
        """The stack's probability for one model's features, and each member's own."""
        groups = group.split("|")
        members = {
            m.name: m.classify(self._split(row, j), groups[j]) if clf is None else clf.predict(self._split(row, j), groups[j])
            for j, (m, clf) in enumerate(zip(self.members, self.member_classifiers))
        }
        return float(self.meta.predict_rows([self._meta_row([logit(p) for p in members.values()])])[0]), members

    # An own-scoring member's state is ``{"detector": its state}``, its arrays under "member:key".
    def get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        states: list[dict] = []
        arrays: dict[str, np.ndarray] = {}
        for member, clf in zip(self.members, self.member_classifiers):
            if clf is not None:
                states.append(clf.to_dict())
                continue
            own, own_arrays = member.get_state()
            states.append({"detector": own})
            arrays.update({f"{member.name}:{key}": value for key, value in own_arrays.items()})
        bound = {} if math.isinf(self.bound) else {"logit_bound": self.bound}  # a stack without it keeps its bytes
        return {"members": states, "meta": self.meta.to_dict(), **bound}, arrays

    def set_state(self, state: dict, arrays: dict[str, np.ndarray]) -> None:
        members = list(state.get("members") or [])
        if len(members) != len(self.members):
            raise ValueError(f"{len(members)} member classifiers saved for {len(self.members)} members")
        for j, saved in enumerate(members):
            if self.scores_itself(j) != ("detector" in saved):
                raise ValueError(f"member {self.members[j].name!r} was saved as {'its own scorer' if 'detector' in saved else 'a classifier'}, which it is not")
            if self.member_classifiers[j] is not None:
                self.member_classifiers[j] = GroupedClassifier.from_dict(saved)
                continue
            prefix = f"{self.members[j].name}:"
            self.members[j].set_state(saved["detector"], {k[len(prefix) :]: v for k, v in arrays.items() if k.startswith(prefix)})
            self.members[j].fitted = True
        self.meta = LogisticModel.from_dict(state.get("meta") or {})
        self.bound = float(state.get("logit_bound", math.inf))


def _held_out_loss(fitted: tuple[float, LogisticModel]) -> float:
    loss = fitted[1].cv_log_loss
    return math.inf if loss is None else loss


class _OwnScoring:
    """A fitted own-scoring member, with a classifier's ``predict`` (the stack's folds call either)."""

    def __init__(self, detector: FeatureDetector):
        self.detector = detector

    def predict(self, row: dict[str, float], group: str) -> float:
        return self.detector.classify(row, group)


__all__ = ["StackDetector", "logit"]
