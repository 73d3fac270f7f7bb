"""Training: one driver for every world (:func:`train`), the algorithms' loops, checkpoints and the model folder."""

from rlbackdoors.train.driver import train
from rlbackdoors.folder import FolderError, ModelFolder

__all__ = ["FolderError", "ModelFolder", "train"]
