"""Model zoo architectures, built by name from a config, and weight loading that accepts TrojAI files.

Weights are read as data: ``torch.load(weights_only=True)``, and for a file that holds Python
objects (TrojAI's rounds pickled modules, gymnasium spaces, a ``box.Box``) the inert reader
:func:`rlbackdoors.torchfile.read_torch_file`, which runs nothing. Such a file is accepted only
for a world that names TrojAI classes (:attr:`~rlbackdoors.worlds.World.trojai_archs`) and only
when every global it names belongs to a known format (:data:`FORMAT_GLOBALS`, the world's
TrojAI classes); anything else (``os.system``, an unknown class) is refused as before.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from pathlib import Path

import torch

from rlbackdoors import worlds
from rlbackdoors.io import UnsafeFileError, load_torch
from rlbackdoors.models.minigrid import ActorCritic, CNNModel, FCModel

# Architecture classes per world come from the World registry: the same names ("fc", "cnn") mean
# the paper's model for that world.
# Names other tools used for the same layers (rl-starter-files calls the CNN ``image_conv``).
KEY_ALIASES = {"image_conv.": "state_emb."}


def __getattr__(name: str):
    """A world's architecture class by its class name (imported on first use, from the registry)."""
    from rlbackdoors.worlds.base import load_symbol

    for world in worlds.registered("ppo"):
        for _, path in world.archs:
            if path.rpartition(":")[2] == name:
                return load_symbol(path)
    raise AttributeError(f"module 'rlbackdoors.models' has no attribute {name!r}")


def build_model(arch: str, env: str = worlds.DEFAULT_WORLD, num_actions: int = 3) -> ActorCritic:
    grid = worlds.names("ppo")
    if env not in grid:
        raise ValueError(f"env {env!r} is not one of {', '.join(grid)}")
    return worlds.get(env).arch_class(arch)(num_actions=num_actions)


def _as_state_dict(obj) -> dict:
    if isinstance(obj, dict) and obj and all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in obj.items()):
        return obj
    for key in ("model_state", "state_dict", "model"):
        if isinstance(obj, dict) and key in obj:
            return _as_state_dict(obj[key])
    raise ValueError("it holds no state dict (a dict of tensors)")


# Globals a TrojAI weights file may name besides its model class: the pieces of a pickled torch
# module, gymnasium spaces, numpy arrays and generators, python-box. Prefixes of "module.name".
# The inert reader turns each into a placeholder; this list only decides what is a known format.
FORMAT_GLOBALS = (
    "torch._utils._rebuild_",
    "torch._tensor._rebuild_from_type_v2",
    "torch.Size",
    "torch.nn.modules.",
    "torch.nn.parameter.Parameter",
    "collections.OrderedDict",
    "builtins.set",
    "builtins.frozenset",
    "_codecs.encode",
    "copyreg._reconstructor",
    "gymnasium.spaces.",
    "gym.spaces.",
    "numpy.dtype",
    "numpy.ndarray",
    "numpy.core.multiarray._reconstruct",
    "numpy.core.multiarray.scalar",
    "numpy._core.multiarray._reconstruct",
    "numpy._core.multiarray.scalar",
    "numpy.random.",  # generators, bit generators, seed sequences
    "box.box.Box",
    "box.box_list.BoxList",
)
_STORAGE_GLOBALS = tuple(f"torch.{t}Storage" for t in ("Float", "Double", "Half", "BFloat16", "Long", "Int", "Short", "Char", "Byte", "Bool"))


def unexplained_globals(names: Iterable[str], model_classes: Iterable[str]) -> list[str]:
    """The globals of ``names`` that are neither a known format's (:data:`FORMAT_GLOBALS`) nor
    one of ``model_classes`` (class names, any module)."""
    classes = set(model_classes)
    return sorted(name for name in names if not (name.startswith(FORMAT_GLOBALS) or name in _STORAGE_GLOBALS or name.rpartition(".")[2] in classes))


def read_weights(path: str | Path, world: str | None = None) -> tuple[dict[str, torch.Tensor], str | None]:
    """(flat state dict, the model class the file names or None) of a weights file.

    Plain data is read with ``weights_only=True``. A file that holds objects is refused
    (:class:`~rlbackdoors.io.UnsafeFileError`) unless ``world`` names TrojAI classes and the file
    is one of their formats (module doc); then the inert reader gives its tensors, mapped to our
    keys by the world's :attr:`~rlbackdoors.worlds.World.trojai_weights` where it has one.
    """
    try:
        obj = load_torch(path, "weights file")
    except UnsafeFileError:
        w = worlds.get(world) if world is not None else None
        known = w.trojai_archs if w is not None else ()
        if w is None or not known:
            raise
        from rlbackdoors.torchfile import read_torch_file

        file = read_torch_file(path, "weights file")
        if unexplained_globals(file.globals, (name for name, _ in known)):
            raise  # the same refusal: objects that no known format explains
        if w.trojai_weights is not None:
            try:
                return w.trojai_weights(file.tensors()), file.model_class()
            except ValueError as err:
                raise ValueError(f"weights file {str(path)!r}: {err}") from None
        state = file.state_dict()
        if state is None:
            raise ValueError(f"weights file {str(path)!r}: it holds no state dict (a dict of tensors) or module") from None
        return state, file.model_class()
    name = obj.get("model") if isinstance(obj, dict) and isinstance(obj.get("model"), str) else None
    try:
        return _as_state_dict(obj), name
    except ValueError as err:
        raise ValueError(f"weights file {str(path)!r}: {err}") from None


def sibling_model_class(path: str | Path) -> str | None:
    """The model class the round files beside ``path`` name (a TrojAI ``reduced-config.json``,
    ``config.json`` or ``model.info.json``; our own reduced config's or config's arch), read as
    JSON data (:mod:`rlbackdoors.trojai_round`); None if there is none or they cannot be read."""
    from rlbackdoors.trojai_round import read_round

    try:
        files = read_round(Path(path).parent)
    except (OSError, ValueError):
        return None
    own = files.own_reduced() or files.own_config()
    if own is not None:
        arch = own.get("arch", (own.get("model") or {}).get("arch"))
        return arch if isinstance(arch, str) else None
    return files.model_class()[0]


def resolve_arch(world: str, state: dict[str, torch.Tensor], model_class: str | None = None, path: str | Path | None = None) -> str:
    """Our arch for weights of ``world`` given without one: the TrojAI class the file names, else
    the one a TrojAI config beside it names, else the only arch whose shapes fit."""
    w = worlds.get(world)
    shown = f"weights file {str(path)!r}" if path is not None else "weights"
    for source, name in (("holds", model_class), ("has a config beside it naming", sibling_model_class(path) if path is not None else None)):
        if name is None:
            continue
        if name in w.arch_names:
            return name
        arch = w.trojai_arch(name)
        if arch is None:
            known = ", ".join(n for n, _ in w.trojai_archs) or "none"
            raise ValueError(f"{shown} {source} a {name!r}, which is no architecture of {world} (TrojAI classes: {known}; archs: {', '.join(w.arch_names)})")
        return arch
    shapes = {k: tuple(v.shape) for k, v in renamed(state).items()}
    fits = [arch for arch in w.arch_names if {k: tuple(v.shape) for k, v in build_model(arch, world).state_dict().items()} == shapes]
    if len(fits) == 1:
        return fits[0]
    if fits:
        raise ValueError(f"{shown} fits several architectures of {world} ({', '.join(fits)})")
    raise ValueError(f"{shown} fits no architecture of {world} (allowed: {', '.join(w.arch_names)})")


def renamed(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """``state`` with other tools' layer names (:data:`KEY_ALIASES`) turned into ours."""
    renamed = {}
    for key, value in state.items():
        for old, new in KEY_ALIASES.items():
            if key.startswith(old):
                key = new + key[len(old) :]
        renamed[key] = value
    return renamed


def load_weights(model: ActorCritic, path: str | Path, world: str | None = None) -> ActorCritic:
    """Load a ``torch.save``-d state dict into ``model``; one clear error if it does not fit.

    Plain data only, except TrojAI's formats for a ``world`` that names them (:func:`read_weights`):
    a pickled module or anything else needing the unpickler is refused unread, since
    unpickling a stranger's file can run its code.
    """
    state, _ = read_weights(path, world)
    return load_state(model, state, path)


def load_state(model: ActorCritic, state: dict[str, torch.Tensor], path: str | Path) -> ActorCritic:
    """``state`` (a flat state dict read from ``path``) into ``model``, checked by key, shape and value."""
    ours = renamed(state)
    expected = model.state_dict()
    missing = sorted(set(expected) - set(ours))
    unexpected = sorted(set(ours) - set(expected))
    if missing or unexpected:
        raise ValueError(f"weights in {str(path)!r} do not fit {type(model).__name__}: missing {missing or 'none'}, unexpected {unexpected or 'none'}")
    for key, value in ours.items():
        if value.shape != expected[key].shape:
            raise ValueError(f"weights in {str(path)!r}: {key} has shape {tuple(value.shape)}, {type(model).__name__} expects {tuple(expected[key].shape)}")
    check_finite(ours, path)
    model.load_state_dict(ours)
    return model


def check_finite(state: dict, path) -> None:
    """A NaN or inf weight is no policy: refuse it by name rather than report SRs of 0."""
    for key, value in state.items():
        if isinstance(value, torch.Tensor) and value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise ValueError(f"weights file {str(path)!r}: {key} holds non-finite values (NaN or inf)")


__all__ = [
    "ActorCritic",
    "CNNModel",
    "FCModel",
    "build_model",
    "check_finite",
    "load_state",
    "load_weights",
    "read_weights",
    "resolve_arch",
    "sibling_model_class",
    "unexplained_globals",
]
