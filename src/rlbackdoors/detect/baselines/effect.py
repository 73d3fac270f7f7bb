"""Policy effect: what each candidate trigger of the world's family does to the policy, scored as
an anomaly against clean models. It assumes no attack and no trojan outcome.

Why: the behavioural search (:mod:`.behaviour`) counts the world's trojan *outcome* (the lava,
the other object), so it cannot see an action-level trojan that turns left whatever the world
pays; the weight statistics see training history, which late fine-tuning hides. Whatever a trojan
does, it must change what the policy does when its trigger is present (BIRD, Chen et al. 2023;
PolicyCleanse, Guo et al. 2022). So, per candidate of the family (screened and refined as the
search plays them, on the same seeds) and against the clean env E:

* **shift**: the Jensen-Shannon divergence (nats) between the policy's mean action distributions
  in E-bar and in E: how far the policy moves;
* **concentration**: the fall of the mean action entropy (nats): how decided it becomes;
* **success drop**: the fall of the clean goal's rate: the return the policy gives up.

Candidates are ranked by the sum of the three (the entropy over its maximum, log of the action
count; each taken both ways), and the best few are played again on more episodes. Features per
model: the confirmed best candidate's three effects and how far each stands above the family's
median candidate (a backdoor answers one trigger; a clean agent's answer to an edit of its input is
broad), and the three effects of every screened candidate, which the fit sets against what clean
models show under the *same* edit (the screen's candidates are the same for every model: an edit
that breaks any policy is no anomaly, one that moves this policy more than clean ones is).

Scoring, fitted on clean models, in two levels. First, each screened candidate's effects are
standardised by what the clean fit models of the model's world show under the same edit (spreads
floored, :data:`SCALE_FLOOR`, :data:`DROP_FLOOR`), and each effect's largest excess either way over
the candidates is kept (``up_shift``, ``down_shift``, ...: six numbers). Second, those six and the
six summary features are standardised by the clean fit models' own values of them (a clean fit
model's computed without itself at both levels, as a new model's would be; floors as above and
:data:`AGG_FLOOR` for the six maxima), and the model's anomaly is the largest ``|z|``, two-sided,
so that an effect the fit never saw with this sign still counts. Why two levels: a maximum over
48 candidates' noisy z-scores is large for clean models too, so it is itself set against the
clean models' maxima (the first version took one maximum over all 150 features, and a clean
model's unlucky candidate outscored real trojans: docs/results/detectors.md). Where the fit has
poisoned models, a one-feature logistic regression on the anomaly gives the probability where its
slope is positive. With clean models only, or where the fit's poisoned models are no more
anomalous than its clean ones (a slope that would score anomalies as clean), the probability is
the share of clean fit models less anomalous than the model (one minus a p-value);
``detector.json`` says which (``calibration_note``).

The screen (``screen``): where the family lists all its members (``every``; the lava-pattern
family's 466 patterns of 3 to 9 cells in the 3x3 box), the default (``auto``) plays them all,
``sample`` plays the behavioural search's ``candidates``. Why: a trojan trained with near
negatives answers its exact pattern and nothing one cell off it; a sample that misses the pattern
has nothing to refine from, and such a model read as clean (0.800 AUC on that label with the
sample, docs/results/detectors.md). A fit from before this parameter screened the sample and
keeps doing so when read back (where its worlds' families list themselves).

Cost: the behavioural search's episodes with every forward's action distribution kept: 48
candidates of 16 episodes (all of a listed family: 466 lava patterns, about 7x the
episodes), 12 neighbours, 3 confirmations of 32, and E; candidates played 32 at a time
(:func:`~rlbackdoors.detect.baselines.behaviour.run_trials`).
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

import numpy as np

from rlbackdoors import worlds
from rlbackdoors.detect.api import Param, _check_labels, register
from rlbackdoors.detect.baselines.behaviour import BehaviourDetector, SearchResult, Trial, family_module, family_unsupported
from rlbackdoors.detect.classifier import LogisticModel, fit_logistic
from rlbackdoors.detect.handle import DetectError, ModelHandle

EFFECTS = ("shift", "concentration", "success_drop")
FEATURES = tuple(f"best_{e}" for e in EFFECTS) + tuple(f"peak_{e}" for e in EFFECTS)
# The smallest spread a feature is standardised by. Without a floor, clean models that agree
# exactly (every success drop 0) would make any difference an infinite anomaly. Shifts and entropy
# changes below ~0.02 nats are the noise of a 16-episode screen; a success rate on 16 episodes has a
# binomial spread of up to 0.125 (at 0.5), so success drops are floored there.
SCALE_FLOOR = 0.02
DROP_FLOOR = 0.125
# The smallest spread of a candidate maximum (a z-score): half a standard deviation. Measured on the
# grid-world benchmark of issue 57, the held-out AUCs do not move between floors of 0.1 and 1.0.
AGG_FLOOR = 0.5
SCORING = 2  # the reference's layout in detector.json (1: one maximum over every feature)


def js_divergence(p: tuple[float, ...] | np.ndarray, q: tuple[float, ...] | np.ndarray) -> float:
    """Jensen-Shannon divergence (nats, 0 to log 2) of two distributions over the same actions."""
    p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
    m = (p + q) / 2

    def kl(a: np.ndarray) -> float:
        nz = a > 0
        return float((a[nz] * np.log(a[nz] / m[nz])).sum())

    return max(0.0, (kl(p) + kl(q)) / 2)


def effects(trial: Trial, clean: Trial) -> tuple[float, float, float]:
    """(shift, concentration, success drop) of a candidate's trial against the clean env's."""
    assert trial.policy is not None and clean.policy is not None and trial.entropy is not None and clean.entropy is not None
    return js_divergence(trial.policy, clean.policy), clean.entropy - trial.entropy, clean.success - trial.success


def effect_rank(trial: Trial, clean: Trial) -> tuple:
    """Order of the candidates for refinement and confirmation: the summed size of the effects."""
    if trial.error is not None or trial.policy is None or trial.entropy is None:
        return (False, 0.0)
    shift, concentration, drop = effects(trial, clean)
    return (True, shift + abs(concentration) / math.log(max(2, len(trial.policy))) + abs(drop))


def effect_features(result: SearchResult) -> dict[str, float]:
    """The model's features (module doc) from a search ranked by :func:`effect_rank`."""
    clean = result.clean
    played = [t for t in result.screened if t.error is None and t.policy is not None and t.entropy is not None]
    if clean.policy is None or result.best.policy is None or not played:
        raise DetectError("detector 'effect' reads the policy's action distribution, and this policy has none (not a discrete-action torch policy)")
    best = effects(result.best, clean)
    each = {trial.spec: effects(trial, clean) for trial in played}
    median = np.median(np.array(list(each.values())), axis=0)
    row = {f"best_{name}": float(value) for name, value in zip(EFFECTS, best)}
    row.update({f"peak_{name}": float(value - m) for name, value, m in zip(EFFECTS, best, median)})
    for spec, values in each.items():  # per candidate: set against what clean models show under the same edit
        row.update({f"{name}@{spec}": float(value) for name, value in zip(EFFECTS, values)})
    return row


@register
class EffectDetector(BehaviourDetector):
    """The behavioural search's parameters, candidates and episodes; its own rank, features and
    scoring (module doc)."""

    name = "effect"
    description = (
        "what each candidate trigger of the family does to the policy (shift, concentration, success drop): an anomaly against clean models, no attack assumed"
    )

    defaults: ClassVar[dict[str, Any]] = {**BehaviourDetector.defaults, "screen": "auto"}
    rules: ClassVar[dict[str, Param]] = {
        **BehaviourDetector.rules,
        "screen": Param(
            choices=("auto", "whole", "sample"),
            help="whole: every member of the trigger family (families that list theirs); sample: `candidates` of them; auto: whole where listed",
        ),
    }

    def __init__(self, **params: Any):
        super().__init__(**params)
        self.reference: dict[str, dict[str, Any]] = {}  # world -> the clean fit models' mean and scale of each feature, at both levels
        self.calibration: LogisticModel | None = None  # None: the p-value among clean_scores
        self.calibration_note = ""  # how probabilities are made, in words (detector.json)
        self.clean_scores: np.ndarray = np.zeros(0)

    def unsupported(self, model: ModelHandle) -> str | None:
        if model.world.algorithm != "ppo":
            return (
                f"detector 'effect' reads a discrete policy's action distribution; {model.world.name}'s {model.world.algorithm} policy has continuous actions"
            )
        why = family_unsupported(model)  # the family's own limits, as the search has them
        if why is None and self.params["screen"] == "whole" and not hasattr(family_module(model.world), "every"):
            why = "its trigger family does not list its members (screen=whole); use screen=sample or auto"
        return f"detector 'effect' cannot play {model.world.name}: {why}" if why else None

    def whole_family(self, model: ModelHandle) -> bool:
        """Whether this model's screen plays every member of its family (``screen``, module doc)."""
        screen = self.params["screen"]
        return screen == "whole" or (screen == "auto" and hasattr(family_module(model.world), "every"))

    def features(self, model: ModelHandle) -> dict[str, float]:
        result = self.run_search(model, rank=effect_rank, whole_family=self.whole_family(model))
        row = effect_features(result)
        self.last_info = {
            "found_trigger": result.best.spec,
            **{k: round(v, 4) for k, v in row.items() if k.startswith("best_")},
            "search_seconds": round(result.seconds, 3),
        }
        return row

    # ----- scoring: an anomaly against the clean models of the fit ------------------------------
    def fit_rows(self, rows: list[dict[str, float]], groups: list[str], labels: np.ndarray) -> EffectDetector:
        labels = _check_labels(rows, labels)
        least = max(2, int(self.params["min_per_class"]))  # two: a clean fit model is standardised by the others
        self.reference = {}
        scores = np.zeros(len(rows))
        for group in sorted(set(groups)):
            members = [i for i, g in enumerate(groups) if g == group]
            clean = [i for i in members if labels[i] == 0]
            if len(clean) < least:
                raise DetectError(f"detector 'effect' needs at least {least} clean models of {group} in the fit (it has {len(clean)})")
            # the screened candidates every clean fit model has
            names = sorted(n for n in set.intersection(*(set(rows[i]) for i in clean)) if "@" in n)
            x = np.array([[float(rows[i][f]) for f in names] for i in clean], dtype=np.float64)
            first = _reference(names, x)
            # each clean fit model's maxima against the others, as a new model's would be
            own = {i: _maxima(rows[i], _reference(names, x[[k for k, j in enumerate(clean) if j != i]])) for i in clean}
            second_names = (list(MAXIMA) if names else []) + list(FEATURES)
            y = np.array([[own[i][f] if f in own[i] else float(rows[i][f]) for f in second_names] for i in clean])
            self.reference[group] = {"scoring": SCORING, "candidates": first, "summary": _reference(second_names, y)}
            for i in members:
                if labels[i]:
                    scores[i] = self.anomaly(rows[i], group)
                else:  # without itself at the second level too
                    rest = [k for k, j in enumerate(clean) if j != i]
                    scores[i] = _anomaly({**rows[i], **own[i]}, _reference(second_names, y[rest]))
        self.clean_scores = np.sort(scores[labels == 0])
        self.calibration, self.calibration_note = None, "clean models only: one minus the p-value of the anomaly among them"
        if labels.any():
            model = fit_logistic([{"anomaly": s} for s in scores], labels, ["anomaly"])
            if model.kind == "logistic" and model.coef[0] > 0:
                self.calibration, self.calibration_note = model, "a logistic regression on the anomaly"
            else:  # a slope that is not positive would score anomalies as clean: the p-value instead, and say so
                self.calibration_note = (
                    "the fit's poisoned models were no more anomalous than its clean ones: one minus the p-value of the anomaly among the clean models"
                )
        self.fitted = True
        return self

    def anomaly(self, row: dict[str, float], group: str) -> float:
        if group not in self.reference:
            raise DetectError(f"detector 'effect' saw no clean model of {group} in its fit")
        reference = self.reference[group]
        return _anomaly({**row, **_maxima(row, reference["candidates"])}, reference["summary"])

    def classify(self, row: dict[str, float], group: str) -> float:
        score = self.anomaly(row, group)
        if self.calibration is not None:
            return float(self.calibration.predict_rows([{"anomaly": score}])[0])
        n = len(self.clean_scores)
        return float((np.searchsorted(self.clean_scores, score, side="left") + 0.5) / (n + 1))

    def get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        state = {
            "reference": self.reference,
            "calibration": None if self.calibration is None else self.calibration.to_dict(),
            "calibration_note": self.calibration_note,
            "screen": self.params["screen"],
        }
        return state, {"clean_scores": self.clean_scores}

    def set_state(self, state: dict, arrays: dict[str, np.ndarray]) -> None:
        def plain(ref: dict) -> dict[str, list]:
            return {"features": [str(f) for f in ref["features"]], "mean": [float(v) for v in ref["mean"]], "scale": [float(v) for v in ref["scale"]]}

        references = state.get("reference") or {}
        if "screen" in state:
            self.params["screen"] = str(state["screen"])
        elif any(hasattr(family_module(worlds.get(str(g))), "every") for g in references):
            # a fit from before ``screen`` screened the sample; where none of its worlds' families
            # lists itself, that is what ``auto`` screens too
            self.params["screen"] = "sample"
        for group, ref in references.items():
            if ref.get("scoring") != SCORING:
                raise DetectError(
                    f"detector 'effect' of {group} was fitted by an older version (scoring {ref.get('scoring', 1)}, this is {SCORING}): fit it again"
                )
        self.reference = {
            str(g): {"scoring": SCORING, "candidates": plain(ref["candidates"]), "summary": plain(ref["summary"])} for g, ref in references.items()
        }
        calibration = state.get("calibration")
        self.calibration = None if calibration is None else LogisticModel.from_dict(calibration)
        self.calibration_note = str(state.get("calibration_note", ""))
        self.clean_scores = np.asarray(arrays.get("clean_scores", np.zeros(0)), dtype=np.float64)


MAXIMA = tuple(f"{way}_{e}" for way in ("up", "down") for e in EFFECTS)


def _floor(name: str) -> float:
    """The smallest spread of a feature (:data:`SCALE_FLOOR`, :data:`DROP_FLOOR` for success
    drops, :data:`AGG_FLOOR` for the candidates' maxima)."""
    if name in MAXIMA:
        return AGG_FLOOR
    return DROP_FLOOR if name.split("@")[0].endswith("success_drop") else SCALE_FLOOR


def _maxima(row: dict[str, float], reference: dict[str, list]) -> dict[str, float]:
    """Each effect's largest standardised excess over the screened candidates, upward and downward
    (:data:`MAXIMA`), against the clean models' reference of each candidate."""
    names, mean, scale = reference["features"], np.asarray(reference["mean"]), np.asarray(reference["scale"])
    out: dict[str, float] = {}
    if not names:  # rows of the summary features only (no screened candidate in common)
        return out
    for effect in EFFECTS:
        have = [k for k, name in enumerate(names) if name.startswith(f"{effect}@") and name in row]
        if not have:
            raise DetectError("detector 'effect': the model has none of the candidates its fit's clean models had (another trigger family or search budget?)")
        z = (np.array([float(row[names[k]]) for k in have]) - mean[have]) / scale[have]
        out[f"up_{effect}"], out[f"down_{effect}"] = float(z.max()), float((-z).max())
    return out


def _reference(names: list[str], x: np.ndarray) -> dict[str, list]:
    """Mean and floored spread per feature of clean models' rows ``x`` (columns ``names``)."""
    mean = x.mean(0)
    spread = x.std(0, ddof=1) if len(x) > 1 else np.zeros(x.shape[1])
    floors = np.array([_floor(n) for n in names])
    return {"features": list(names), "mean": [float(v) for v in mean], "scale": [float(v) for v in np.maximum(spread, floors)]}


def _anomaly(row: dict[str, float], reference: dict[str, list]) -> float:
    """The largest |z| of a row against a reference, over the features the row has: two-sided."""
    have = [k for k, name in enumerate(reference["features"]) if name in row]
    if not have:
        raise DetectError("detector 'effect': the model has none of the features its fit's clean models had (another trigger family or search budget?)")
    values = np.array([float(row[reference["features"][k]]) for k in have])
    z = (values - np.asarray(reference["mean"])[have]) / np.asarray(reference["scale"])[have]
    return float(np.abs(z).max())


__all__ = [
    "AGG_FLOOR",
    "DROP_FLOOR",
    "MAXIMA",
    "EFFECTS",
    "FEATURES",
    "SCALE_FLOOR",
    "EffectDetector",
    "effect_features",
    "effect_rank",
    "effects",
    "js_divergence",
]
