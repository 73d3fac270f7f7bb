"""The detector API (scikit-learn style) and the registry of detectors by name.

A detector is one class::

    @register
    class MyDetector(Detector):
        name = "mine"
        defaults = {"threshold": 0.3}          # its parameters (--param k=v), JSON values

        def fit(self, models, labels): ...     # learn from handles and 0/1 labels; return self
        def predict_one(self, model): ...      # probability that this model is poisoned
        def get_state(self): ...               # learned parameters: (JSON-able dict, {name: array})
        def set_state(self, state, arrays): ...

Most detectors are a feature extractor and a classifier: subclass :class:`FeatureDetector`
and write ``features(model) -> {name: float}`` only. :meth:`Detector.predict` scores a list
of models the way the TrojAI harness does: a model the detector fails on gets 0.5 and the
reason, and the wall time of every model is recorded.

Learned parameters are saved as plain data (``detector.json`` and ``arrays.npz``, read back
with ``allow_pickle=False``): never a pickle, so a detector folder from a stranger cannot run
code when loaded.
"""

from __future__ import annotations

import importlib
import io
import json
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
        self.fitted = False
        # What predict_one wants reported about the model it just scored (e.g. the trigger a
        # search found); cleared before each model.
        self.last_info: dict = {}

    # ----- to override --------------------------------------------------------------------
    def fit(self, models: list[ModelHandle], labels: np.ndarray) -> Detector:
        self.fitted = True
        return self

    def predict_one(self, model: ModelHandle) -> float:
        raise NotImplementedError

    def get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        """Learned parameters: a JSON-able dict and named arrays (plain dtypes)."""
        return {}, {}

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
        payload = {"format": FORMAT, "format_version": FORMAT_VERSION, "detector": self.name, "params": self.params, "fitted": self.fitted, "state": state}
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

    def __init__(self, **params: Any):
        super().__init__(**params)
        from rlbackdoors.detect.classifier import GroupedClassifier

        self.classifier = GroupedClassifier(min_per_class=int(self.params["min_per_class"]))

    def features(self, model: ModelHandle) -> dict[str, float]:
        raise NotImplementedError

    def group(self, model: ModelHandle) -> str:
        return f"{model.world.name}/{model.arch}"

    def fit(self, models: list[ModelHandle], labels: np.ndarray) -> FeatureDetector:
        return self.fit_rows([self.fit_features(m) for m in models], [self.group(m) for m in models], labels)

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
    cls = get_detector(str(payload.get("detector")))
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
    return detector


# ----- registry ----------------------------------------------------------------------------------
def register(cls: type[Detector]) -> type[Detector]:
    """Class decorator: make a detector available by its ``name`` (CLI ``--detector NAME``)."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    if cls.name in _REGISTRY and _REGISTRY[cls.name] is not cls:
        raise ValueError(f"detector {cls.name!r} is registered twice")
    _REGISTRY[cls.name] = cls
    return cls


def _load_builtins() -> None:
    importlib.import_module("rlbackdoors.detect.baselines")


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
    "Prediction",
    "detector_names",
    "get_detector",
    "load_detector",
    "make_detector",
    "register",
]
