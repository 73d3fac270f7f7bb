"""The floor: every model is poisoned with probability 0.5 (TrojAI's example detector).

Its cross-entropy is ln 2 = 0.693 and its AUC 0.5 on any zoo; a detector that does not beat
it has learned nothing.
"""

from __future__ import annotations

from typing import Any, ClassVar

from rlbackdoors.detect.api import Detector, register
from rlbackdoors.detect.handle import ModelHandle


@register
class ConstantDetector(Detector):
    name = "constant"
    description = "probability `value` (0.5) for every model: the floor, CE ln 2"
    defaults: ClassVar[dict[str, Any]] = {"value": 0.5}

    def __init__(self, **params: Any):
        super().__init__(**params)
        if not 0.0 <= float(self.params["value"]) <= 1.0:
            from rlbackdoors.detect.handle import DetectError

            raise DetectError(f"detector 'constant': value={self.params['value']!r} must be in [0, 1]")
        self.fitted = True  # nothing to learn

    def predict_one(self, model: ModelHandle) -> float:
        return float(self.params["value"])
