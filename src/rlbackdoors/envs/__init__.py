"""Environments of the paper, one module per world (``rlbackdoors.envs.<world>``); their Gymnasium
ids (``rlbackdoors/<World>-v0``) are registered from the World registry when ``rlbackdoors`` is
imported (:func:`rlbackdoors.worlds.register_gym_ids`), and a world's env class is
``rlbackdoors.worlds.get(name).env_class()``.

Nothing is imported here but :class:`Outcome`, so importing one world's env does not import
MiniGrid or MuJoCo for the others.
"""

from rlbackdoors.envs.outcome import Outcome

__all__ = ["Outcome"]
