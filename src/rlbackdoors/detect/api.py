"""The detector API (scikit-learn style) and the registry of detectors by name.

A detector is one class::

    @register
    class MyDetector(Detector):
        name = "mine"
        defaults = {"threshold": 0.3}          # its parameters (--param k=v), JSON values
        rules = {"threshold": Param(0.0, 1.0, help="...")}   # their allowed values (every number needs a range)

        def fit(self, models, labels): ...     # learn from handles and 0/1 labels; return self
        def predict_one(self, model): ...      # probability that this model is poisoned
        def get_state(self): ...               # learned parameters: (JSON-able dict, {name: array})
        def set_state(self, state, arrays): ...

Most detectors are a feature extractor and a classifier: subclass :class:`FeatureDetector`
and write ``features(model) -> {name: float}`` only. :meth:`Detector.predict` scores a list
of models the way the TrojAI harness does: a model the detector fails on gets 0.5 and the
reason, and the wall time of every model is recorded.

Each parameter's allowed values (:class:`Param`: a range, a set of choices, whether it only
steers the fit) are declared once, in ``rules``: the constructor validates against them, the
TrojAI schema is generated from them (:func:`rlbackdoors.detect.trojai.schema_for`), and a fitted
detector refuses metaparameters that differ from its own in anything but a fit-only parameter.

Learned parameters are saved as plain data (``detector.json`` and ``arrays.npz``, read back
with ``allow_pickle=False``): never a pickle, so a detector folder from a stranger cannot run
code when loaded.
"""

from __future__ import annotations

import importlib
import io
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from rlbackdoors.detect.handle import DetectError, ModelHandle
from rlbackdoors.io import atomic_write_bytes, atomic_write_text, first_line

STATE_FILE = "detector.json"
ARRAYS_FILE = "arrays.npz"
FORMAT = "rlbackdoors-detector"
FORMAT_VERSION = 1
FAILED_PROBABILITY = 0.5  # TrojAI's default prediction for a model without a result

_REGISTRY: dict[str, type[Detector]] = {}


@dataclass(frozen=True)
class Param:
    """The allowed values of one detector parameter, the one source the constructor's validation,
    the generated JSON schema and the CLI's errors read. ``fit_only``: it steers only how the
    classifier is fitted (never a model's features), so changing it after the fit changes nothing."""

    minimum: float | None = None
    maximum: float | None = None
    choices: tuple = ()
    fit_only: bool = False
    help: str = ""

    def check(self, detector: str, key: str, value: Any) -> None:
        """A DetectError naming the parameter and what is allowed, when ``value`` is outside."""
        if self.choices and value not in self.choices:
            raise DetectError(f"detector {detector!r}: parameter {key}={value!r} is not one of {', '.join(map(repr, self.choices))}")
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            low = -math.inf if self.minimum is None else self.minimum
            high = math.inf if self.maximum is None else self.maximum
            if not (math.isfinite(value) and low <= value <= high):
                raise DetectError(f"detector {detector!r}: parameter {key}={value!r} is out of range (allowed: {_number(low)} to {_number(high)})")


def _number(x: float) -> str:
    return str(int(x)) if math.isfinite(x) and float(x).is_integer() else str(x)


@dataclass
class Prediction:
    """One model's result: probability poisoned, wall seconds, why it failed (None if it did not),
    and what the detector wants reported (e.g. the trigger a search found)."""

    probability: float
    seconds: float
    error: str | None = None
    info: dict = field(default_factory=dict)


class Detector:
    """Base class (module doc). ``params`` are the detector's settings, JSON values only."""

    name: ClassVar[str] = ""
    defaults: ClassVar[dict[str, Any]] = {}
    rules: ClassVar[dict[str, Param]] = {}
    description: ClassVar[str] = ""

    def __init__(self, **params: Any):
        unknown = sorted(set(params) - set(self.defaults))
        if unknown:
            allowed = ", ".join(sorted(self.defaults)) or "none"
            raise DetectError(f"detector {self.name!r} has no parameter {unknown[0]!r} (its parameters: {allowed})")
        self.params: dict[str, Any] = {**self.defaults, **params}
        for key, value in self.params.items():
            default = self.defaults[key]
            if default is not None and not _same_kind(default, value):
                raise DetectError(f"detector {self.name!r}: parameter {key}={value!r} must be a {type(default).__name__} like its default {default!r}")
            if key in self.rules:
                self.rules[key].check(self.name, key, value)
        self.fitted = False
        # What the fit saw (worlds, architectures, env settings, parameters, version): a fitted
        # detector refuses what lies outside it (rlbackdoors.detect.scope); None before a fit.
        self.fitted_on: dict | None = None
        # What predict_one wants reported about the model it just scored (e.g. the trigger a
        # search found); cleared before each model.
        self.last_info: dict = {}

    # ----- to override --------------------------------------------------------------------
    def fit(self, models: list[ModelHandle], labels: np.ndarray) -> Detector:
        self.fitted = True
        self.record_fit(models)
        return self

    def record_fit(self, models: list[ModelHandle]) -> None:
        """Keep what the fit saw (``fitted_on``: rlbackdoors.detect.scope) from its models' handles."""
        from rlbackdoors.detect.scope import model_scope, record

        self.fitted_on = record(self, [model_scope(self, m) for m in models])

    def predict_one(self, model: ModelHandle) -> float:
        raise NotImplementedError

    def get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        """Learned parameters: a JSON-able dict and named arrays (plain dtypes)."""
        return {}, {}

    def unsupported(self, model: ModelHandle) -> str | None:
        """Why this detector cannot compute a model of this world and env at all (fit, score and
        infer refuse it with this reason before any work); None when it can."""
        return None

    def scope_group(self, model: ModelHandle) -> str:
        """The group whose models a fit must have seen before this model is scored (world and
        architecture; a detector whose features mean the same across architectures says so)."""
        return f"{model.world.name}/{model.arch}"

    def set_state(self, state: dict, arrays: dict[str, np.ndarray]) -> None:
        pass

    # ----- the same for every detector ----------------------------------------------------
    def predict_proba(self, models: list[ModelHandle]) -> np.ndarray:
        """Probability poisoned per model (0.5 where the detector fails on one)."""
        return np.array([p.probability for p in self.predict(models)], dtype=np.float64)

    def predict(self, models: list[ModelHandle]) -> list[Prediction]:
        """Score each model, timing it; an exception gives that model 0.5 and the reason."""
        out = []
        for model in models:
            started = time.perf_counter()
            self.last_info = {}
            try:
                probability = float(self.predict_one(model))
                if not np.isfinite(probability):
                    raise DetectError(f"the detector returned {probability!r}")
                probability = min(1.0, max(0.0, probability))
                info, error = dict(self.last_info), None
            except Exception as err:  # a failing model must not stop a zoo's scoring
                probability, info, error = FAILED_PROBABILITY, {}, f"{type(err).__name__}: {first_line(err)}"
            out.append(Prediction(probability, time.perf_counter() - started, error, info))
        return out

    def save(self, folder: str | Path) -> Path:
        """Write ``detector.json`` (name, params, JSON state) and ``arrays.npz``."""
        folder = Path(folder)
        state, arrays = self.get_state()
        payload = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "detector": self.name,
            "params": self.params,
            "fitted": self.fitted,
            "fitted_on": self.fitted_on,
            "state": state,
        }
        atomic_write_bytes(folder / ARRAYS_FILE, npz_bytes(arrays))
        atomic_write_text(folder / STATE_FILE, json.dumps(payload, indent=2, sort_keys=True, allow_nan=True) + "\n")
        return folder

    @classmethod
    def load(cls, folder: str | Path) -> Detector:
        """The detector saved in ``folder`` (of whichever registered class it names)."""
        return load_detector(folder)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({', '.join(f'{k}={v!r}' for k, v in self.params.items())})"


def _same_kind(default: Any, value: Any) -> bool:
    if isinstance(default, bool) or isinstance(value, bool):
        return isinstance(default, bool) and isinstance(value, bool)
    if isinstance(default, (int, float)):
        return isinstance(value, (int, float)) and (isinstance(default, float) or isinstance(value, int))
    return isinstance(value, type(default))


# ----- features -> classifier ----------------------------------------------------------------
class FeatureDetector(Detector):
    """A detector that is ``features(model)`` and a calibrated classifier over them.

    The classifier (:class:`rlbackdoors.detect.classifier.GroupedClassifier`) keeps one
    logistic regression per group (``group(model)``, by default world and architecture) where
    the train set has enough of both labels in that group, and one over all models on the
    features every model has; C is chosen by cross-validated log loss.
    """

    defaults: ClassVar[dict[str, Any]] = {"min_per_class": 3}
    rules: ClassVar[dict[str, Param]] = {
        "min_per_class": Param(1, 10_000, fit_only=True, help="models of each label a group needs for a classifier of its own")
    }

    def __init__(self, **params: Any):
        super().__init__(**params)
        from rlbackdoors.detect.classifier import GroupedClassifier

        self.classifier = GroupedClassifier(min_per_class=int(self.params["min_per_class"]))

    def features(self, model: ModelHandle) -> dict[str, float]:
        raise NotImplementedError

    def group(self, model: ModelHandle) -> str:
        return f"{model.world.name}/{model.arch}"

    def scope_group(self, model: ModelHandle) -> str:
        return self.group(model)

    def fit(self, models: list[ModelHandle], labels: np.ndarray) -> FeatureDetector:
        self.fit_rows([self.fit_features(m) for m in models], [self.group(m) for m in models], labels)
        self.record_fit(models)
        return self

    def fit_features(self, model: ModelHandle) -> dict[str, float]:
        """``features(model)`` of a train model; a failure is one line naming the model."""
        try:
            return self.features(model)
        except Exception as err:  # one line naming the model, not a traceback
            raise DetectError(f"detector {self.name!r} cannot fit on model {model.name!r}: {type(err).__name__}: {first_line(err)}") from None

    def fit_rows(self, rows: list[dict[str, float]], groups: list[str], labels: np.ndarray) -> FeatureDetector:
        """Fit the classifier on features already computed (a resumed fit keeps them per model)."""
        labels = _check_labels(rows, labels)
        self.classifier.fit(rows, groups, labels)
        self.fitted = True
        return self

    def predict_one(self, model: ModelHandle) -> float:
        if not self.fitted:
            raise DetectError(f"detector {self.name!r} is not fitted (run detect fit first)")
        return self.classify(self.features(model), self.group(model))

    def classify(self, row: dict[str, float], group: str) -> float:
        """The probability for one model's features (what a subclass with its own classifier overrides)."""
        return self.classifier.predict(row, group)

    def get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        return {"classifier": self.classifier.to_dict()}, {}

    def set_state(self, state: dict, arrays: dict[str, np.ndarray]) -> None:
        from rlbackdoors.detect.classifier import GroupedClassifier

        self.classifier = GroupedClassifier.from_dict(state.get("classifier") or {})


def _check_labels(models: list, labels) -> np.ndarray:
    labels = np.asarray(labels)
    if labels.shape != (len(models),) or not np.isin(labels, (0, 1)).all():
        raise DetectError(f"labels must be {len(models)} values of 0 (clean) or 1 (poisoned), got shape {labels.shape}")
    return labels.astype(np.int64)


# ----- plain-data files ------------------------------------------------------------------------
def npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """An ``.npz`` of plain arrays (object arrays are refused: they would need pickle to read)."""
    clean = {}
    for key, value in arrays.items():
        array = np.asarray(value)
        if array.dtype == object:
            raise TypeError(f"array {key!r} has dtype object, which is not plain data")
        clean[key] = array
    buf = io.BytesIO()
    np.savez(buf, **clean)  # type: ignore[arg-type]  # numpy's stub wants a positional file; names are keywords by design
    return buf.getvalue()


def load_detector(folder: str | Path) -> Detector:
    """Read a detector folder (``detector.json`` + ``arrays.npz``) as plain data."""
    folder = Path(folder)
    path = folder / STATE_FILE
    if not path.is_file():
        raise DetectError(f"{str(folder)!r} holds no detector ({STATE_FILE} missing; make one with detect fit)")
    try:
        payload = json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as err:
        raise DetectError(f"{str(path)!r} is not JSON ({first_line(err)})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise DetectError(f"{str(path)!r} is not an rlbackdoors detector file")
    if payload.get("format_version") != FORMAT_VERSION:
        raise DetectError(f"{str(path)!r} has format_version {payload.get('format_version')!r}; this rlbackdoors reads {FORMAT_VERSION}")
    try:
        cls = get_detector(str(payload.get("detector")))
    except DetectError as err:
        raise DetectError(f"{str(path)!r}: {err}") from None
    params = payload.get("params") or {}
    if not isinstance(params, dict):
        raise DetectError(f"{str(path)!r}: params must be an object")
    detector = cls(**params)
    arrays: dict[str, np.ndarray] = {}
    npz = folder / ARRAYS_FILE
    if npz.is_file():
        try:
            with np.load(npz, allow_pickle=False) as data:
                arrays = {k: np.array(data[k]) for k in data.files}
        except (ValueError, OSError, EOFError) as err:
            raise DetectError(f"{str(npz)!r} is not an .npz of plain arrays ({first_line(err)})") from None
    try:
        detector.set_state(payload.get("state") or {}, arrays)
    except (KeyError, TypeError, ValueError) as err:
        raise DetectError(f"{str(path)!r}: the learned parameters do not fit detector {cls.name!r} ({first_line(err)})") from None
    detector.fitted = bool(payload.get("fitted"))
    fitted_on = payload.get("fitted_on")
    detector.fitted_on = fitted_on if isinstance(fitted_on, dict) else None
    return detector


# ----- registry ----------------------------------------------------------------------------------
def register(cls: type[Detector]) -> type[Detector]:
    """Class decorator: make a detector available by its ``name`` (CLI ``--detector NAME``)."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    if cls.name in _REGISTRY and _REGISTRY[cls.name] is not cls:
        raise ValueError(f"detector {cls.name!r} is registered twice")
    for key, default in cls.defaults.items():  # a number without a range would reach the schema unchecked
        rule = cls.rules.get(key)
        if isinstance(default, (int, float)) and not isinstance(default, bool) and (rule is None or rule.minimum is None or rule.maximum is None):
            raise ValueError(f"detector {cls.name!r}: numeric parameter {key!r} declares no range in rules")
    stray = sorted(set(cls.rules) - set(cls.defaults))
    if stray:
        raise ValueError(f"detector {cls.name!r}: rules for parameters it does not have: {stray}")
    _REGISTRY[cls.name] = cls
    return cls


def _load_builtins() -> None:
    importlib.import_module("rlbackdoors.detect.baselines")


def load_plugin(path: str | Path) -> None:
    """Import a Python file of one's own detectors (``--plugin FILE``), which registers them with
    :func:`register`; the same file twice is imported once. A plugin is code its user chose to run,
    like any script; what the product never runs is what arrives in a model or detector folder
    (read as data). DetectError names a missing file or the error the file raised."""
    import hashlib
    import importlib.util
    import sys

    file = Path(path)
    if not file.is_file():
        raise DetectError(f"--plugin {str(path)!r} is not a file (a Python file that registers detectors with @register)")
    key = "rlbackdoors_plugin_" + hashlib.sha256(str(file.resolve()).encode()).hexdigest()[:12]
    if key in sys.modules:
        return
    spec = importlib.util.spec_from_file_location(key, file)
    if spec is None or spec.loader is None:
        raise DetectError(f"--plugin {str(path)!r} cannot be imported as a Python module")
    module = importlib.util.module_from_spec(spec)
    sys.modules[key] = module
    try:
        spec.loader.exec_module(module)
    except Exception as err:
        del sys.modules[key]
        raise DetectError(f"--plugin {str(path)!r} failed: {type(err).__name__}: {err}") from None


def detector_names() -> tuple[str, ...]:
    _load_builtins()
    return tuple(_REGISTRY)


def get_detector(name: str) -> type[Detector]:
    _load_builtins()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise DetectError(f"detector {name!r} is not one of {', '.join(_REGISTRY)}") from None


def make_detector(name: str, **params: Any) -> Detector:
    return get_detector(name)(**params)


__all__ = [
    "Detector",
    "FeatureDetector",
    "Param",
    "Prediction",
    "detector_names",
    "get_detector",
    "load_detector",
    "load_plugin",
    "make_detector",
    "register",
]
