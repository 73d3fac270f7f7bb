"""One way to load a trained agent and make it act: ``rlbackdoors.load(folder)``.

Evaluation, videos and detectors all need the same thing from a model folder: an object that
maps a batch of observations (and its recurrent state, if any) to actions. :class:`Agent` is
that object for every world, whichever algorithm trained it::

    agent = rlbackdoors.load("runs/p0")
    state = agent.initial_state(n)            # None for feed-forward agents
    actions, state = agent.act(obs, state)    # obs: a batch of n observations

Loading reads ``config.json`` as data and ``model.pt`` with ``torch.load(weights_only=True)``:
a file that holds Python objects is refused, never unpickled.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from rlbackdoors import worlds
from rlbackdoors.train.folder import FolderError, ModelFolder


class Agent:
    """A trained policy of one world: ``act(obs, state) -> (actions, state)``.

    ``deterministic`` picks the most likely action (grid worlds: argmax of the logits; OPAC²:
    ``tanh`` of the Gaussian's mean); otherwise actions are sampled from ``generator``.
    """

    def __init__(self, world: worlds.World, config: Any, policy: Any, folder: Path | None = None):
        self.world, self.config, self.policy, self.folder = world, config, policy, folder

    @property
    def recurrent(self) -> bool:
        return bool(getattr(self.policy, "recurrent", False))

    def initial_state(self, n: int):
        """The state of ``n`` fresh episodes (a GRU memory for recurrent agents, else None)."""
        return self.policy.initial_memory(n, "cpu") if self.recurrent else None

    @torch.inference_mode()
    def act(self, obs, state=None, deterministic: bool = False, generator: torch.Generator | None = None):
        if self.world.algorithm == "opac2":
            return self.policy.act(np.asarray(obs, np.float32), deterministic=deterministic, generator=generator), state
        from rlbackdoors.algos.obs import to_torch
        from rlbackdoors.algos.ppo import sample_actions

        if self.recurrent:
            logits, _, state = self.policy(to_torch(obs, "cpu"), state if state is not None else self.initial_state(_batch(obs)))
        else:
            logits, _ = self.policy(to_torch(obs, "cpu"))
        actions = logits.argmax(-1) if deterministic else sample_actions(logits, generator or torch.Generator().manual_seed(0))
        return actions.numpy(), state

    def __repr__(self) -> str:
        where = f" from {str(self.folder)!r}" if self.folder else ""
        return f"Agent({self.world.name}, {type(self.policy).__name__}{where})"


def _batch(obs) -> int:
    return len(next(iter(obs.values())) if isinstance(obs, dict) else obs)


def load(folder: str | Path, allow_unfinished: bool = False) -> Agent:
    """The agent of a model folder of any world (on the CPU).

    An unfinished folder (no ``metrics.json``: still training, interrupted or failed) is refused
    unless ``allow_unfinished``.
    """
    path = Path(folder)
    if not path.is_dir():
        raise FolderError(f"model folder {str(path)!r} does not exist")
    model_folder = ModelFolder(path)
    for name in ("config.json", "model.pt"):
        if not model_folder.file(name).is_file():
            raise FolderError(f"{str(path)!r} is not a finished model folder ({name} missing)")
    if not model_folder.complete and not allow_unfinished:
        raise FolderError(f"{str(path)!r} holds an unfinished run (no metrics.json); pass allow_unfinished=True to load its weights anyway")
    from rlbackdoors.safety_config import is_safety_config

    import json

    try:
        raw = json.loads(model_folder.file("config.json").read_bytes().decode("utf-8"))
    except (ValueError, RecursionError) as err:
        raise FolderError(f"config file {str(model_folder.file('config.json'))!r} is not valid JSON ({err})") from None
    if is_safety_config(raw):
        from rlbackdoors.train.safety import load_agent

        config, policy = load_agent(path)
        return Agent(worlds.get(config.env.name), config, policy, path)
    from rlbackdoors.models import build_model, load_weights

    run_config = model_folder.read_config()
    assert run_config.model.arch is not None  # a loaded config is a built and checked RunConfig
    model = load_weights(build_model(run_config.model.arch, run_config.env.name), model_folder.file("model.pt"))
    model.eval()
    return Agent(run_config.env.world, run_config, model, path)


def load_weights_file(path: str | Path, world: str, arch: str) -> Agent:
    """An agent from a bare state dict (e.g. a TrojAI round's ``model.pt``) of ``world``'s ``arch``."""
    from rlbackdoors.models import build_model, load_weights

    model = load_weights(build_model(arch, world), path)
    model.eval()
    return Agent(worlds.get(world), None, model, None)


__all__ = ["Agent", "load", "load_weights_file"]
