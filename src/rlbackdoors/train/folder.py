"""The model folder lives in :mod:`rlbackdoors.folder` (loading needs it without the trainer)."""

from rlbackdoors.folder import CHECKPOINT_FORMAT, FILES, FolderError, ModelFolder, stack_versions

__all__ = ["CHECKPOINT_FORMAT", "FILES", "FolderError", "ModelFolder", "stack_versions"]
