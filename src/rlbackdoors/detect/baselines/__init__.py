"""The baseline detectors; importing this package registers them, floor first: ``constant``,
``weights``, ``attribution``, ``behaviour``, ``effect``, then ``stack`` (which combines them)."""

from rlbackdoors.detect.baselines import constant  # noqa: F401
from rlbackdoors.detect.baselines import weights  # noqa: F401
from rlbackdoors.detect.baselines import attribution  # noqa: F401
from rlbackdoors.detect.baselines import behaviour  # noqa: F401
from rlbackdoors.detect.baselines import effect  # noqa: F401
from rlbackdoors.detect.baselines import stack  # noqa: F401
