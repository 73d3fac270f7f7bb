"""Zoos: TrojAI-round datasets of clean and poisoned agents, planned from one master seed, trained on
one machine or a Ray cluster without losing work, and reported like the paper (docs/zoos.md).

``plan`` (spec -> model folders with their configs) -> ``run`` (train, top up cells until they
have their converged models) -> ``status`` / ``split`` (train and test datasets, disjoint by
trigger) / ``report`` (Tables 1-5 and plots).
"""

from rlbackdoors.zoo.plan import Zoo, build_config, plan
from rlbackdoors.zoo.spec import ZooSpec, load_spec, parse_spec

__all__ = ["Zoo", "ZooSpec", "build_config", "load_spec", "parse_spec", "plan"]
