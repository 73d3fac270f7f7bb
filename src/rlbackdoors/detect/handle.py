"""What a detector sees of one model: :class:`ModelHandle`, and how it is opened.

A TrojAI performer got a model's weights, its reduced config (architecture), the round's world
with its clean environment and trigger *family*, and a few clean example episodes; never the
model's full config, its metrics, its trigger or its label. A handle holds exactly that, as
in-memory data: :func:`open_model` copies the allowed files of a model folder into a private
temp dir, reads them from there as plain data (``load_torch``, JSON, ``.npz`` without pickle)
and deletes the copy, so nothing in a handle names the folder or can lead back to it.

The world record (:class:`rlbackdoors.worlds.World`) is the registry's, shared by every model
of that world: it gives the clean env and the trigger family (``parse_trigger``,
``draw_trigger``, ``trigger_help``) and knows nothing about any one model.
"""

from __future__ import annotations

import re
import shutil
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import torch

from rlbackdoors import worlds
from rlbackdoors.io import UnsafeFileError, first_line, load_torch
from rlbackdoors.trojai_round import ENV_STRING, ROUND_FILES, read_round

MODEL_FILE = "model.pt"
REDUCED_CONFIG = "reduced-config.json"
EXAMPLES_DIR = "clean-example-data"
MAX_EXAMPLE_FILES = 256  # a handle is small; a folder of thousands of files is not an example set
# Keys a reduced config must never carry to a detector, whatever wrote it.
SECRET_KEYS = re.compile(r"trigger|poison|ground|label|metric|seed", re.IGNORECASE)
ID_NAME = re.compile(r"^id-[0-9]+$")


class DetectError(ValueError):
    """A model or detector that cannot be used: one line naming the file or field."""


class Contradiction(DetectError):
    """A model folder whose settings name an architecture its weights are not: refused, or (with
    ``allow_contradiction``) opened as the weights say and flagged (``ModelHandle.contradiction``).
    Scoring it quietly as whatever the weights fit would give a number for a model nobody knows."""

    def __init__(self, message: str, world: worlds.World, arch: str):
        super().__init__(message)
        self.world, self.arch = world, arch


@dataclass(frozen=True, eq=False)
class ModelHandle:
    """One model as a detector sees it (module doc). Everything is in memory; nothing is a path.

    ``weights``: the flat state dict (read-only mapping of CPU tensors); ``reduced_config``: the
    architecture facts; ``world``: the registry record; ``arch``: the architecture name the
    weights fit; ``examples``: clean episodes (dicts of arrays: ``obs`` or ``obs_<key>``,
    ``actions``, ``rewards``, ...); ``env_settings``: the env fields the reduced config gives
    (world defaults for the rest); ``name``: an opaque id (``id-XXXXXXXX`` or ``model-N``);
    ``contradiction``: None, or why its settings disagree with its weights (:class:`Contradiction`,
    only on a handle opened with ``allow_contradiction``).
    """

    name: str
    weights: Mapping[str, torch.Tensor]
    reduced_config: Mapping[str, Any]
    world: worlds.World
    arch: str
    examples: tuple[Mapping[str, np.ndarray], ...] = ()
    env_settings: Mapping[str, Any] = field(default_factory=dict)
    contradiction: str | None = None  # opened with allow_contradiction: what its settings said otherwise

    # ----- the world's clean env -----------------------------------------------------------
    def env_config(self, **overrides):
        """A fresh :class:`rlbackdoors.config.EnvConfig` of this world (defaults, the reduced
        config's env fields, then ``overrides``)."""
        from rlbackdoors.config import EnvConfig

        settings = {**self.env_settings, **overrides}
        return EnvConfig(name=self.world.name, **settings)

    def make_env(self, trigger: str | None = None, **overrides):
        """One env of this world: clean (E), or E-bar with a *candidate* trigger of the family."""
        return self.env_config(**overrides).make(trigger)

    # ----- the agent -----------------------------------------------------------------------
    def build_agent(self):
        """The model as an :class:`rlbackdoors.agent.Agent` (a fresh network each call, CPU, eval mode)."""
        return build_agent(self.world, self.arch, dict(self.weights))

    # ----- the clean examples --------------------------------------------------------------
    def episode_observations(self) -> list[np.ndarray | dict[str, np.ndarray]]:
        """The observations of each clean example episode: an array, or a dict for dict observations."""
        out: list[np.ndarray | dict[str, np.ndarray]] = []
        for episode in self.examples:
            if "obs" in episode:
                out.append(np.asarray(episode["obs"]))
            else:
                keys = {k[len("obs_") :]: np.asarray(v) for k, v in episode.items() if k.startswith("obs_")}
                if keys:
                    out.append(keys)
        return out

    def __repr__(self) -> str:
        return f"ModelHandle({self.name}, {self.world.name}/{self.arch}, {len(self.weights)} tensors, {len(self.examples)} example episodes)"


# ----- opening ---------------------------------------------------------------------------------
def open_model(folder: str | Path, name: str | None = None, reduced_optional: bool = False, allow_contradiction: bool = False) -> ModelHandle:
    """The handle of a model folder (TrojAI layout): ``model.pt``, the round's settings files
    (``reduced-config.json``, or where a round put them instead: :data:`ROUND_FILES`) and
    ``clean-example-data/`` only. Raises :class:`DetectError` naming a missing or bad file. With
    ``reduced_optional`` a folder without any settings file (a training run's) opens from its
    weights alone, with the world's default env settings. A folder whose settings name another
    architecture than its weights fit raises :class:`Contradiction`, unless ``allow_contradiction``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DetectError(f"model folder {str(folder)!r} does not exist")
    examples = folder / EXAMPLES_DIR
    return open_files(
        folder / MODEL_FILE,
        folder,
        examples if examples.is_dir() else None,
        name=name or _opaque_name(folder.name),
        required=not reduced_optional,
        allow_contradiction=allow_contradiction,
    )


def open_files(
    model_file: str | Path,
    round_dir: str | Path | None,
    examples_dir: str | Path | None = None,
    name: str = "model",
    scratch: str | Path | None = None,
    required: bool = True,
    allow_contradiction: bool = False,
) -> ModelHandle:
    """A handle from the allowed files (TrojAI's ``--model_filepath``, the round's settings files
    in ``round_dir`` (the folder beside it), ``--examples_dirpath``), read from a private copy (in
    ``scratch`` if given). ``required``: one settings file must be there (a model whose env is not
    said would be played in the world's defaults without a word); ``round_dir`` None asks for the
    weights alone (world defaults)."""
    model_file = Path(model_file)
    if not model_file.is_file():
        raise DetectError(f"weights file {str(model_file)!r} does not exist")
    found = [n for n in ROUND_FILES if round_dir is not None and (Path(round_dir) / n).is_file() and not (Path(round_dir) / n).is_symlink()]
    if REDUCED_CONFIG in found:  # our zoo's reduced config says all a detector may see: nothing else is opened
        try:
            if read_round(Path(str(round_dir)), (REDUCED_CONFIG,)).own_reduced() is not None:
                found = [REDUCED_CONFIG]
        except ValueError as err:
            raise DetectError(f"reduced config: {err}") from None
    elif required and "config.json" in found:  # train's config.json (trigger, label) is no detector's view
        try:
            if read_round(Path(str(round_dir)), ("config.json",)).own_config() is not None:
                found.remove("config.json")
        except ValueError as err:
            raise DetectError(f"config: {err}") from None
    if required and round_dir is not None and not found:  # round_dir None: the weights alone, asked for
        where = str(Path(round_dir)) if round_dir is not None else str(model_file.parent)
        raise DetectError(f"no {', '.join(ROUND_FILES[:3])} in {where!r} beside the weights (a zoo writes reduced-config.json beside model.pt)")
    with tempfile.TemporaryDirectory(prefix="rlbackdoors-handle-", dir=scratch) as tmp:
        private = Path(tmp)
        shutil.copyfile(model_file, private / MODEL_FILE)
        for n in found:
            shutil.copyfile(Path(str(round_dir)) / n, private / n)
        copied: list[Path] = []
        (private / EXAMPLES_DIR).mkdir()
        if examples_dir is not None:
            source = Path(examples_dir)
            if not source.is_dir():
                raise DetectError(f"examples folder {str(source)!r} does not exist")
            files = sorted(p for p in source.iterdir() if p.suffix == ".npz" and p.is_file() and not p.is_symlink())[:MAX_EXAMPLE_FILES]
            for path in files:
                target = private / EXAMPLES_DIR / path.name
                shutil.copyfile(path, target)
                copied.append(target)

        # the env string names the clean env (a round's lava count is only there): in the examples
        # folder given, else in the model folder's own clean-example-data/
        places = (Path(examples_dir) if examples_dir is not None else None, Path(round_dir) / EXAMPLES_DIR if round_dir is not None else None)
        for place in places:
            if place is not None and (place / ENV_STRING).is_file() and not (place / ENV_STRING).is_symlink():
                shutil.copyfile(place / ENV_STRING, private / EXAMPLES_DIR / ENV_STRING)
                break
        weights = _read_weights(private / MODEL_FILE, str(model_file))
        try:
            files_read = read_round(private, tuple(found))
        except ValueError as err:
            raise DetectError(str(err).replace(str(private), str(round_dir))) from None
        episodes = tuple(_read_npz(path, str(Path(str(examples_dir)) / path.name)) for path in copied)
    # What the detector sees of the settings files: our reduced config, else the first TrojAI one;
    # train's own config.json (trigger, label) only ever gives its env section to RoundFiles.env
    own = files_read.own_config()
    if own is not None and files_read.own_reduced() is not None:  # the reduced config is the detector's view
        files_read.configs.pop("config.json")
    view = _strip_secrets(files_read.own_reduced() or next((c for c in files_read.configs.values() if c is not own), {}))
    model_class, _ = files_read.model_class()
    if model_class is not None and not isinstance(view.get("arch", view.get("model")), str):
        view["model"] = model_class
    contradiction = None
    try:
        world, arch = identify(view, weights, str(model_file))
    except Contradiction as err:
        if not allow_contradiction:
            raise
        world, arch, contradiction = err.world, err.arch, str(err)
    try:
        settings = {k: s.value for k, s in files_read.env(world).items() if k != "engine"}
    except ValueError as err:
        raise DetectError(f"settings of {str(model_file)!r}: {err}") from None
    return ModelHandle(
        name=name,
        weights=MappingProxyType(weights),
        reduced_config=MappingProxyType(view),
        world=world,
        arch=arch,
        examples=tuple(MappingProxyType(e) for e in episodes),
        env_settings=MappingProxyType(settings),
        contradiction=contradiction,
    )


def _opaque_name(name: str) -> str:
    """A zoo's ``id-XXXXXXXX`` (drawn independently of ground truth); any other folder name may
    say what the model is ("poisoned-fc"), so it becomes ``model``."""
    return name if ID_NAME.match(name) else "model"


def _read_weights(path: Path, shown: str) -> dict[str, torch.Tensor]:
    try:
        obj = load_torch(path, "weights file")
    except UnsafeFileError as err:
        obj = _trojai_weights(path, err)
        if obj is None:
            raise DetectError(str(err).replace(str(path), shown)) from None
    except (ValueError, FileNotFoundError) as err:
        raise DetectError(str(err).replace(str(path), shown)) from None
    for key in ("model_state", "state_dict", "model"):  # wrappers other tools save around a state dict
        if isinstance(obj, dict) and isinstance(obj.get(key), dict):
            obj = obj[key]
            break
    if isinstance(obj, dict) and all(isinstance(v, dict) for v in obj.values()) and obj:  # nested per net (old OPAC² files)
        obj = {f"{net}.{k}": v for net, sub in obj.items() for k, v in sub.items()}
    if not (isinstance(obj, dict) and obj and all(isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in obj.items())):
        raise DetectError(f"weights file {shown!r} holds no flat state dict (a dict of tensors)")
    for key, value in obj.items():
        if value.is_floating_point() and not bool(torch.isfinite(value).all()):
            raise DetectError(f"weights file {shown!r}: {key} holds non-finite values (NaN or inf)")
    return {k: v.detach().cpu().clone() for k, v in obj.items()}


def _trojai_weights(path: Path, refusal: UnsafeFileError) -> dict[str, torch.Tensor] | None:
    """The tensors of a TrojAI round file that holds objects (a pickled module, a status dict, a
    python-box), read by the inert reader when some world's TrojAI classes explain every object
    in it (:func:`rlbackdoors.models.read_weights`); None: refused as any other object file."""
    from rlbackdoors.models import read_weights

    for world in worlds.registered():
        if world.trojai_archs:
            try:
                return read_weights(path, world.name)[0]
            except ValueError:  # UnsafeFileError included: not this world's classes
                continue
    return None


def _strip_secrets(data):
    """Drop keys a detector must not see (trigger, poisoning, labels, metrics, seeds) at any depth."""
    if isinstance(data, dict):
        return {k: _strip_secrets(v) for k, v in data.items() if not SECRET_KEYS.search(str(k))}
    if isinstance(data, list):
        return [_strip_secrets(v) for v in data]
    return data


def _read_npz(path: Path, shown: str) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {k: np.array(npz[k]) for k in npz.files}
    except (ValueError, OSError, EOFError) as err:
        raise DetectError(f"example file {shown!r} is not an .npz of plain arrays ({first_line(err)})") from None


# ----- which network -----------------------------------------------------------------------------
def named_arch(world: worlds.World, wanted: str) -> str | None:
    """Our architecture of ``world`` that a settings file's ``arch`` / ``model`` names: one of
    ours, a TrojAI class of the world's round, or (an OPAC² world, whose reduced config names its
    algorithm) the algorithm; None when it names none of them."""
    if wanted in world.arch_names:
        return wanted
    if (arch := world.trojai_arch(wanted)) is not None:
        return arch
    if world.algorithm == "opac2" and wanted == world.algorithm:
        return world.arch_names[0]
    return None


def identify(reduced: Mapping, weights: Mapping[str, torch.Tensor], shown: str = "model.pt") -> tuple[worlds.World, str]:
    """(world, arch) of the weights: the one registered architecture whose state-dict keys and
    shapes match (of the reduced config's ``world`` when it names one). A reduced config whose
    ``arch`` (or ``model``) names an architecture the world does not know, or another one than
    the weights fit, raises :class:`Contradiction` (carrying what the weights fit)."""
    name = reduced.get("world")
    candidates = [worlds.get(name)] if isinstance(name, str) and name in worlds.names() else worlds.registered()
    if isinstance(name, str) and name not in worlds.names():
        raise DetectError(f"reduced config of {shown!r}: world {name!r} is not one of {', '.join(worlds.names())}")
    wanted = reduced.get("arch", reduced.get("model"))
    wanted = wanted if isinstance(wanted, str) else None
    fits = []
    for world in candidates:
        named = named_arch(world, wanted) if wanted is not None else None
        names = [named, *(n for n in world.arch_names if n != named)] if named is not None else list(world.arch_names)
        for arch in names:
            if _fits(world, arch, weights):
                fits.append((world, arch))
                break
    if not fits:
        where = f"{candidates[0].name}" if len(candidates) == 1 else "any registered world"
        raise DetectError(f"weights file {shown!r} fits no architecture of {where} (reduced config arch: {wanted!r})")
    if len(fits) > 1:
        named_fits = [(w, a) for w, a in fits if wanted is not None and named_arch(w, wanted) == a]
        if len(named_fits) != 1:
            raise DetectError(
                f"weights file {shown!r} fits architectures of several worlds ({', '.join(f'{w.name}/{a}' for w, a in fits)}); give world in its reduced config"
            )
        fits = named_fits
    world, arch = fits[0]
    if wanted is not None and named_arch(world, wanted) != arch:
        known = [w for w in candidates if named_arch(w, wanted) is not None]
        said = (
            f"{known[0].name}/{named_arch(known[0], wanted)}"
            if known
            else "no architecture of " + (world.name if len(candidates) == 1 else "any registered world")
        )
        allowed = ", ".join([*world.arch_names, *(c for c, _ in world.trojai_archs)])
        raise Contradiction(
            f"reduced config of {shown!r} names arch {wanted!r} ({said}; {world.name} has {allowed}) but its weights fit {world.name}/{arch}: the folder contradicts itself",
            world,
            arch,
        )
    return world, arch


def _shapes(weights: Mapping[str, torch.Tensor]) -> dict[str, tuple[int, ...]]:
    return {k: tuple(v.shape) for k, v in weights.items()}


def _fits(world: worlds.World, arch: str, weights: Mapping[str, torch.Tensor]) -> bool:
    try:
        if world.algorithm == "opac2":
            from rlbackdoors.algos.opac2 import weight_dims

            weight_dims(weights)
            return True
        from rlbackdoors.models import build_model, renamed

        expected = _shapes(build_model(arch, world.name).state_dict())
        got = _shapes(renamed(weights))
        return expected == got
    except (ValueError, KeyError, TypeError, IndexError):
        return False


def build_agent(world: worlds.World, arch: str, weights: dict[str, torch.Tensor]):
    """An :class:`rlbackdoors.agent.Agent` from in-memory weights (no config, no folder)."""
    from rlbackdoors.agent import Agent

    if world.algorithm == "opac2":
        import dataclasses

        from rlbackdoors.algos.opac2 import OPAC2, weight_dims
        from rlbackdoors.config import default_opac2

        obs_dim, act_dim, depth, width, obs_norm = weight_dims(weights)
        cfg = dataclasses.replace(default_opac2(world.name), depth=depth, width=max(width, 1), obs_norm=obs_norm)
        policy = OPAC2(obs_dim, act_dim, cfg, torch.Generator().manual_seed(0))
        try:
            policy.load_weights(weights)
        except (KeyError, TypeError, ValueError, RuntimeError) as err:
            raise DetectError(f"weights do not fit an OPAC² agent of depth {depth}, width {width} ({first_line(err)})") from None
        return Agent(world, None, policy, None)
    from rlbackdoors.models import build_model, renamed

    model = build_model(arch, world.name)
    try:
        model.load_state_dict(renamed(weights))
    except RuntimeError as err:
        raise DetectError(f"weights do not fit {world.name}/{arch} ({first_line(err)})") from None
    model.eval()
    return Agent(world, None, model, None)


__all__ = ["Contradiction", "DetectError", "ModelHandle", "build_agent", "identify", "named_arch", "open_files", "open_model"]
