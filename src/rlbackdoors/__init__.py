"""rlbackdoors: backdoored deep-RL agents with in-distribution triggers, and the tools to audit them."""

__version__ = "0.1.0"

from rlbackdoors.worlds import register_gym_ids as _register_gym_ids  # noqa: E402

_register_gym_ids()


def load(folder, allow_unfinished: bool = False):
    """The trained agent of a model folder of any world: ``act(obs, state) -> (actions, state)``
    (see :mod:`rlbackdoors.agent`). Loads data only; a model.pt that carries code is refused."""
    from rlbackdoors.agent import load as _load

    return _load(folder, allow_unfinished)
