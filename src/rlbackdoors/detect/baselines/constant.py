"""The floor: every model is poisoned with probability 0.5 (TrojAI's example detector).

Its cross-entropy is ln 2 = 0.693 and its AUC 0.5 on any zoo; a detector that does not beat
it has learned nothing.
"""

from __future__ import annotations

from typing import Any, ClassVar

from rlbackdoors.detect.api import Detector, Param, register
from rlbackdoors.detect.handle import ModelHandle


@register
class ConstantDetector(Detector):
    name = "constant"
    description = "probability `value` (0.5) for every model: the floor, CE ln 2"
    defaults: ClassVar[dict[str, Any]] = {"value": 0.5}
    rules: ClassVar[dict[str, Param]] = {"value": Param(0.0, 1.0, help="the probability given to every model")}

    def __init__(self, **params: Any):
        super().__init__(**params)
        self.fitted = True  # nothing to learn

    def predict_one(self, model: ModelHandle) -> float:
        return float(self.params["value"])
