"""rlbackdoors: backdoored deep-RL agents with in-distribution triggers, and the tools to audit them."""

__version__ = "0.1.0"

from rlbackdoors import envs as _envs  # noqa: E402,F401  (registers the Gymnasium ids)
