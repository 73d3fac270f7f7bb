"""Trojan detectors: the API a detector implements, what it sees of a model, scoring on a zoo,
the TrojAI container interface, and the baselines (docs/detectors.md).

    from rlbackdoors.detect import make_detector, open_model
    det = make_detector("weights").fit([open_model(f) for f in train], labels)
    p = det.predict_proba([open_model(f) for f in test])
"""

from rlbackdoors.detect.api import Detector, FeatureDetector, Prediction, detector_names, get_detector, load_detector, make_detector, register
from rlbackdoors.detect.handle import DetectError, ModelHandle, open_files, open_model

__all__ = [
    "DetectError",
    "Detector",
    "FeatureDetector",
    "ModelHandle",
    "Prediction",
    "detector_names",
    "get_detector",
    "load_detector",
    "make_detector",
    "open_files",
    "open_model",
    "register",
]
