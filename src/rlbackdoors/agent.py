"""One way to load a trained agent and make it act: ``rlbackdoors.load(folder)``.

Training collection, evaluation, videos and detectors all need the same thing from a model
folder: an object that maps a batch of observations (and its recurrent state, if any) to
actions. :class:`Agent` is that object for every world, whichever algorithm trained it::

    agent = rlbackdoors.load("runs/p0")
    state = agent.initial_state(n)            # None for feed-forward agents
    actions, state = agent.act(obs, state)    # obs: a batch of n observations

Loading reads ``config.json`` as data and ``model.pt`` (one flat state dict; the config says
how to rebuild the network) with ``torch.load(weights_only=True)``: a file that holds Python
objects is refused, never unpickled.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

from rlbackdoors import worlds
from rlbackdoors.io import UnsafeFileError, first_line, load_torch
from rlbackdoors.folder import FolderError, ModelFolder, refuse_left_out_weights


class Agent:
    """A trained policy of one world: ``act(obs, state) -> (actions, state)``.

    ``deterministic`` picks the most likely action (PPO: argmax of the logits; OPAC²: ``tanh``
    of the Gaussian's mean); otherwise actions are sampled from ``generator``.
    """

    def __init__(self, world: worlds.World, config: Any, policy: Any, folder: Path | None = None):
        self.world, self.config, self.policy, self.folder = world, config, policy, folder

    @classmethod
    def wrap(cls, model: torch.nn.Module) -> Agent:
        """A bare PPO actor-critic (no config) as an agent."""
        return cls(worlds.get(worlds.DEFAULT_WORLD), None, model)

    @property
    def recurrent(self) -> bool:
        return bool(getattr(self.policy, "recurrent", False))

    @property
    def device(self) -> torch.device:
        if isinstance(self.policy, torch.nn.Module):
            return next(self.policy.parameters()).device
        return self.policy.device

    def initial_state(self, n: int):
        """The state of ``n`` fresh episodes (a GRU memory for recurrent agents, else None)."""
        return self.policy.initial_memory(n, self.device) if self.recurrent else None

    @contextlib.contextmanager
    def evaluating(self) -> Iterator[Agent]:
        """Eval mode for the duration (a network being trained goes back to train mode)."""
        module = self.policy if isinstance(self.policy, torch.nn.Module) else None
        was_training = module.training if module is not None else False
        if module is not None:
            module.eval()
        try:
            yield self
        finally:
            if module is not None:
                module.train(was_training)

    def generator(self, seed: int) -> torch.Generator:
        """The generator an evaluation samples this agent's actions from. A PPO network's uniforms
        are drawn on the host (one per slot and step, as its rollouts draw them) and go to its
        device with the observations: the same numbers on every device, and a group may draw a
        block of steps at once (the CPU generator's draws are sequential). OPAC² draws its
        Gaussian noise on its own device."""
        return torch.Generator(device="cpu" if isinstance(self.policy, torch.nn.Module) else self.device).manual_seed(int(seed))

    @torch.inference_mode()
    def act(self, obs, state=None, deterministic: bool = False, generator: torch.Generator | None = None):
        if not isinstance(self.policy, torch.nn.Module):  # OPAC²: its own normaliser and squashing
            generator = generator if generator is not None else self.generator(0)
            return self.policy.act(np.asarray(obs, np.float32), deterministic=deterministic, generator=generator), state
        from rlbackdoors.algos.obs import to_torch
        from rlbackdoors.algos.ppo import sample_actions

        device = self.device
        if self.recurrent:
            logits, _, state = self.policy(to_torch(obs, device), state if state is not None else self.initial_state(_batch(obs)))
        else:
            logits, _ = self.policy(to_torch(obs, device))
        actions = logits.argmax(-1) if deterministic else sample_actions(logits, generator or self.generator(0))
        return actions.cpu().numpy(), state

    def __repr__(self) -> str:
        where = f" from {str(self.folder)!r}" if self.folder else ""
        return f"Agent({self.world.name}, {type(self.policy).__name__}{where})"


def _batch(obs) -> int:
    return len(next(iter(obs.values())) if isinstance(obs, dict) else obs)


def build_policy(cfg, device: torch.device | str = "cpu"):
    """A fresh, untrained network of ``cfg`` (its world and architecture, or its OPAC² agent);
    initial weights drawn from ``train.seed`` for OPAC² (PPO: from torch's global seed)."""
    if cfg.algorithm == "opac2":
        from rlbackdoors.algos.opac2 import OPAC2

        env = cfg.env.make()
        (obs_dim,), (act_dim,) = env.observation_space.shape, env.action_space.shape
        env.close()
        return OPAC2(obs_dim, act_dim, cfg.opac2, torch.Generator().manual_seed(cfg.train.seed), device)
    from rlbackdoors.models import build_model

    return build_model(cfg.model.arch, cfg.env.name).to(device)


def load_policy(cfg, path: Path):
    """``cfg``'s network with the weights of ``path`` (a flat state dict), on the CPU."""
    if cfg.algorithm != "opac2":
        from rlbackdoors.models import build_model, load_weights

        return load_weights(build_model(cfg.model.arch, cfg.env.name), path).eval()
    try:
        weights = load_torch(path, "weights file")
    except UnsafeFileError as err:
        raise FolderError(str(err)) from None
    return opac2_policy(cfg, weights, path)


def policy_from_weights(cfg, weights: dict, source: str):
    """``cfg``'s network (or OPAC² agent) holding ``weights`` (a ``model.pt`` state dict, named
    ``source`` in errors), on the CPU: what :func:`load_policy` reads from a file."""
    if cfg.algorithm == "opac2":
        return opac2_policy(cfg, weights, source)
    from rlbackdoors.models import build_model, load_state

    return load_state(build_model(cfg.model.arch, cfg.env.name), weights, source).eval()


def opac2_policy(cfg, weights: dict, path: str | Path):
    """``cfg``'s OPAC² agent holding ``weights`` (read from ``path``: named in errors), on the CPU."""
    from rlbackdoors.models import check_finite

    policy = build_policy(cfg)
    try:
        weights = type(policy).flat_weights(weights)
        check_finite(weights, path)
        policy.load_weights(weights)
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError) as err:
        raise FolderError(f"weights file {str(path)!r} does not fit the config's {cfg.algorithm} agent ({first_line(err)})") from None
    return policy


def opac2_shape(flat: dict, path: str | Path) -> dict:
    """The opac2 config section that OPAC² flat weights fit: ``depth`` and ``width`` of the
    policy's mean net, and ``obs_norm`` (whether they carry observation statistics)."""
    from rlbackdoors.algos.opac2 import weight_dims

    try:
        _, _, depth, width, obs_norm = weight_dims(flat)
    except (TypeError, ValueError, AttributeError, IndexError) as err:
        raise FolderError(f"weights file {str(path)!r} holds no OPAC² policy ({first_line(err)})") from None
    return {"depth": depth, "width": width, "obs_norm": obs_norm}


def load(folder: str | Path, allow_unfinished: bool = False) -> Agent:
    """The agent of a model folder of any world (on the CPU).

    An unfinished folder (no ``metrics.json``: still training, interrupted or failed) is refused
    unless ``allow_unfinished``.
    """
    path = Path(folder)
    if not path.is_dir():
        raise FolderError(f"model folder {str(path)!r} does not exist")
    model_folder = ModelFolder(path)
    refuse_left_out_weights(path)
    for name in ("config.json", "model.pt"):
        if not model_folder.file(name).is_file():
            raise FolderError(f"{str(path)!r} is not a finished model folder ({name} missing)")
    if not model_folder.complete and not allow_unfinished:
        raise FolderError(f"{str(path)!r} holds an unfinished run (no metrics.json); pass allow_unfinished=True to load its weights anyway")
    cfg = model_folder.read_config()
    return Agent(cfg.world, cfg, load_policy(cfg, model_folder.file("model.pt")), path)


def load_weights_file(path: str | Path, world: str, arch: str | None = None) -> Agent:
    """An agent from a bare weights file (e.g. a TrojAI round's ``model.pt``) of ``world``.

    A file that holds Python objects is read by the inert reader when it is one of the world's
    TrojAI formats (:func:`rlbackdoors.models.read_weights`), else refused unread. Without
    ``arch``, a PPO world takes the architecture from the TrojAI class the file (or a TrojAI
    config beside it) names, else from the shapes when one arch fits. An OPAC² agent is
    rebuilt from the shapes (:func:`opac2_shape`): depth and width of the policy, and whether
    it carries observation statistics; a TrojAI OPAC² file's tensors are first mapped to our
    keys (:attr:`rlbackdoors.worlds.World.trojai_weights`).
    """
    w = worlds.get(world)
    if w.algorithm == "opac2":
        from rlbackdoors.algos.opac2 import OPAC2
        from rlbackdoors.config import RunConfig

        try:
            flat = OPAC2.flat_weights(load_torch(path, "weights file"))
        except UnsafeFileError:
            flat = _trojai_opac2(path, world)
        except (TypeError, ValueError) as err:
            raise FolderError(f"weights file {str(path)!r} holds no OPAC² policy ({first_line(err)})") from None
        cfg = RunConfig.from_dict({"env": {"name": world}, "opac2": opac2_shape(flat, path)})
        return Agent(w, None, opac2_policy(cfg, flat, path), None)
    from rlbackdoors.models import build_model, load_state, read_weights, resolve_arch

    state, model_class = read_weights(path, world)
    if arch is None:
        arch = resolve_arch(world, state, model_class, path)
    model = load_state(build_model(arch, world), state, path)
    model.eval()
    return Agent(w, None, model, None)


def _trojai_opac2(path: str | Path, world: str) -> dict:
    """A TrojAI round's OPAC² file (objects: read inertly, mapped to our keys by the world), or
    the refusal any object file gets."""
    from rlbackdoors.models import read_weights

    try:
        return read_weights(path, world)[0]
    except UnsafeFileError as err:
        raise FolderError(str(err)) from None
    except ValueError as err:
        raise FolderError(first_line(err)) from None


__all__ = ["Agent", "build_policy", "load", "load_policy", "load_weights_file", "opac2_policy", "opac2_shape", "policy_from_weights"]
