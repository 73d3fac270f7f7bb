"""Training loop, early stopping, checkpoints and the model folder."""

from rlbackdoors.train.folder import FolderError, ModelFolder
from rlbackdoors.train.loop import train

__all__ = ["FolderError", "ModelFolder", "train"]
