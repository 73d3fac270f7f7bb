"""``rlbackdoors zoo import-trojai DIR --out ZOO``: a TrojAI RL round's model folders as a zoo.

TrojAI shipped each RL round as model folders (``id-XXXXXXXX/`` with ``model.pt``,
``ground_truth.csv`` and a ``config.json`` / ``reduced-config.json`` naming the model class).
The import indexes them in this package's zoo layout, so ``evaluate``, ``zoo report`` and the
detectors (``detect fit`` / ``detect score``) run on TrojAI's own models:

* **Reading, never running.** ``model.pt`` is read as data: ``torch.load(weights_only=True)``,
  or, for the rounds that pickled objects (a whole module, gymnasium spaces, a ``box.Box``), the
  inert reader (:mod:`rlbackdoors.torchfile`), accepted only when every global the file names
  belongs to a known TrojAI format (:func:`rlbackdoors.models.read_weights`). The JSON files are
  read as JSON. ``DIR`` is only read.
* **Which world and architecture.** The TrojAI class (from the file, ``reduced-config.json``,
  ``config.json`` or ``args.json``) names them through the registry
  (:attr:`rlbackdoors.worlds.World.trojai_archs`); a round whose config names no class but its
  env is recognised by the world (:attr:`~rlbackdoors.worlds.World.trojai_env`); ``--world``
  picks the world otherwise. An OPAC² world's network (depth, width, obs_norm) comes from the
  shapes, its tensors mapped to our keys by the world (``World.trojai_weights``). The env
  settings come from every file the round put them in (:mod:`rlbackdoors.trojai_round`:
  reduced-config, config, model.info, args, params, the env string), flags on top, and
  ``trojai.json`` says where each came from. A folder without ``ground_truth.csv`` (and no
  ``--label``) is imported unlabelled: no ground truth written, never counted as clean.
* **Our own training folders** (what ``rlbackdoors train`` wrote: a ``config.json`` with a
  ``format_version`` and an ``env.name`` of a registered world) import the same way, so a few
  models trained one by one (a world whose models take CPU-hours) become a dataset that
  ``detect cv`` scores: their world, env settings and trigger are the ones their config
  recorded, not guessed, and METADATA.csv names the trigger instead of ``unknown``.
* **What is written**, per model ``ZOO/models/id-X/``: ``model.pt`` (the flat state dict, saved
  as plain tensors), ``config.json`` (what :func:`rlbackdoors.load` reads), ``ground_truth.csv``
  (copied), ``metrics.json`` (clean SR and reward measured here in our world, ``--episodes``;
  the poisoned SR only under ``--trigger``, TrojAI's triggers are not ours to name),
  ``clean-example-data/``, ``trojai.json`` (the source folder, the class, the sha256 of every
  file read) and ``trojai/`` (TrojAI's own small JSON/CSV/text files, copied), then
  ``reduced-config.json`` last; ``ZOO/zoo.json`` and ``ZOO/METADATA.csv``.
* **All or nothing, atomic, idempotent.** Every model is read and checked before the first file
  is written: an unknown class, world or format is one ``rlbackdoors: error: ...`` line and
  nothing is written. Each model folder is built under a temp name and renamed into place; the
  zoo is locked while importing. Importing the same ``DIR`` again with the same options writes
  nothing for models already there (same source bytes) and adds new ones; other options, or a
  folder holding another model, are refused.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import shutil
import warnings
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import torch

from rlbackdoors import worlds
from rlbackdoors.io import FolderLock, LockedError, atomic_write_text, remove_tree, save_torch
from rlbackdoors.trojai_round import ROUND_FILES, RoundFiles, read_round
from rlbackdoors.validate import ConfigError
from rlbackdoors.zoo.spec import ZooError

IMPORT_FORMAT = 1
WEIGHT_FILES = ("model.pt", "base_model.pt")  # base_model.pt: the Jul 2023 branch's example folder
COPIED_SUFFIXES = (".json", ".csv", ".txt")
MAX_COPIED_BYTES = 4 << 20
ID_NAME = re.compile(r"^id-[0-9]{8}$")
TMP_DIR_SUFFIX = ".rlbimport"
UNKNOWN_TRIGGER = "unknown"


@dataclass
class SourceModel:
    """One TrojAI model folder, read and checked (nothing written yet)."""

    folder: Path
    weights_file: Path
    name: str  # our id-XXXXXXXX
    world: str
    arch: str
    model_class: str | None
    env: dict
    label: int | None  # None: the round shipped no ground_truth.csv (a test split, the Sep/Oct 2024 examples)
    state: dict[str, torch.Tensor]
    digest: dict[str, str]  # file name -> sha256 of every file read
    config: dict  # our config.json's content (checked)
    configs: dict[str, dict] = field(default_factory=dict)
    own_trigger: str | None = None  # the trigger our own config.json recorded (a folder train wrote)
    env_sources: dict[str, str] = field(default_factory=dict)  # env field -> the file and key it was read from
    source: str = "."  # the folder, relative to the round folder imported (no path of this machine)

    def provenance(self, options: dict) -> dict:
        return {
            "format": IMPORT_FORMAT,
            "source": self.source,
            "weights_file": self.weights_file.name,
            "model_class": self.model_class,
            "world": self.world,
            "arch": self.arch,
            "env": self.env,
            "env_sources": self.env_sources,
            "label": self.label,
            "sha256": self.digest,
            "options": options,
            "own_trigger": self.own_trigger,
        }


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def model_folders(source: Path) -> list[Path]:
    """TrojAI model folders under ``source``: ``source/models/*`` or ``source/*`` holding a
    weights file, or ``source`` itself when it holds one."""
    if not source.is_dir():
        raise ZooError(f"TrojAI folder {str(source)!r} does not exist")
    if any((source / name).is_file() for name in WEIGHT_FILES):
        return [source]
    root = source / "models" if (source / "models").is_dir() else source
    found = sorted(p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".") and any((p / n).is_file() for n in WEIGHT_FILES))
    if not found:
        raise ZooError(f"{str(source)!r} holds no TrojAI model folders (folders holding {' or '.join(WEIGHT_FILES)})")
    return found


def our_names(folders: list[Path]) -> list[str]:
    """TrojAI's ``id-XXXXXXXX`` names when every folder has one, else ids by sorted name."""
    names = [f.name for f in folders]
    if all(ID_NAME.match(n) for n in names) and len(set(names)) == len(names):
        return names
    return [f"id-{i:08d}" for i in range(len(folders))]


def _world_of_class(model_class: str) -> worlds.World | None:
    owners = [w for w in worlds.registered() if w.trojai_arch(model_class) is not None]
    return owners[0] if len(owners) == 1 else None


def env_settings(world: worlds.World, files: RoundFiles, overrides: dict, where: str) -> tuple[dict, dict[str, str]]:
    """(env fields of ``world`` that the round files give, ``overrides`` on top; where each came
    from): :meth:`rlbackdoors.trojai_round.RoundFiles.env`, the flags winning."""
    allowed = (*world.env_fields, "max_steps")
    overrides = {k: v for k, v in overrides.items() if v is not None}
    try:
        given = files.env(world)
    except ValueError as err:
        raise ZooError(f"{where}/{err}") from None
    env = {k: s.value for k, s in given.items()}
    sources = {k: s.source for k, s in given.items()}
    for key, value in overrides.items():
        if key not in allowed:
            raise ConfigError(f"--{key.replace('_', '-')} does not apply to {world.name}")
        env[key], sources[key] = value, f"--{key.replace('_', '-')}"
    return env, sources


def _round_env(world: worlds.World, configs: dict[str, dict], where: str) -> dict | None:
    """The env settings ``world`` reads from TrojAI's configs of its round
    (:attr:`~rlbackdoors.worlds.World.trojai_env`; reduced-config.json wins), None when none of
    them is of its round."""
    if world.trojai_env is None:
        return None
    found: dict | None = None
    for name in reversed(ROUND_FILES):
        if name not in configs:
            continue
        try:
            given = world.trojai_env(configs[name])
        except ValueError as err:
            raise ZooError(f"{where}/{name}: {err}") from None
        if given is not None:
            found = {**(found or {}), **given}
    return found


def _known_trigger(info: dict) -> str | None:
    """An imported model's trigger where one is known (``--trigger``, or the one train recorded)."""
    return (info.get("options") or {}).get("trigger") or info.get("own_trigger")


def _world_of_configs(configs: dict[str, dict], where: str) -> worlds.World | None:
    """The one world whose round TrojAI's configs describe (:attr:`World.trojai_env`), if any."""
    owners = [w for w in worlds.registered() if _round_env(w, configs, where) is not None]
    return owners[0] if len(owners) == 1 else None


def read_source(
    folder: Path, name: str, world_name: str | None, overrides: dict, label: int | None, trigger: str | None = None, arch: str | None = None
) -> SourceModel:
    """Read and check one TrojAI model folder (module doc); ZooError/ValueError name the problem."""
    from rlbackdoors.models import build_model, load_state, read_weights, resolve_arch
    from rlbackdoors.torchfile import read_torch_file

    weights_file = next(folder / n for n in WEIGHT_FILES if (folder / n).is_file())
    try:
        files = read_round(folder)
    except ValueError as err:
        raise ZooError(str(err)) from None
    configs = files.configs
    digest = {p.name: _sha256(p) for p in [weights_file, *(folder / n for n in configs)]}
    if files.env_string is not None:
        digest["clean-example-data/env-string.txt"] = _sha256(folder / "clean-example-data" / "env-string.txt")
    own = files.own_config()
    model_class, _ = files.model_class()  # our own files name no TrojAI class
    if model_class is None:  # a pickled module names its class itself
        try:
            file = read_torch_file(weights_file, "weights file")
            model_class = file.model_class()
        except ValueError:
            model_class = None
    by_config = _world_of_configs(configs, str(folder)) if model_class is None else None
    if world_name is not None:
        world = worlds.get(world_name)
    elif own is not None:  # a folder this package's train wrote: its config names the world
        world = worlds.get(own["env"]["name"])
    elif by_config is not None:  # a round whose config names its env, not a class
        world = by_config
    elif model_class is not None:
        found = _world_of_class(model_class)
        if found is None:
            known = ", ".join(f"{c} ({w.name})" for w in worlds.registered() for c, _ in w.trojai_archs)
            raise ZooError(f"{str(folder)!r}: TrojAI class {model_class!r} is not one we know (known: {known}); give --world and --arch")
        world = found
    else:
        raise ZooError(f"{str(folder)!r} names no model class ({', '.join(ROUND_FILES)}) and its weights file names none; give --world")
    if not world.trojai_archs:
        raise ZooError(f"{str(folder)!r}: {world.name} maps no TrojAI classes to its architectures (World.trojai_archs); it cannot be imported yet")
    state, file_class = read_weights(weights_file, world.name)
    model_class = file_class or model_class
    if model_class is None and len(world.trojai_archs) == 1 and _round_env(world, configs, str(folder)) is not None:
        model_class = world.trojai_archs[0][0]  # the round's one class, which its files do not name
    if model_class is not None:
        model_class = world.trojai_class(model_class) or model_class  # d969b25's "basicfc" is BasicFCModel
    if arch is not None and arch not in world.arch_names:
        raise ConfigError(f"--arch {arch} is not an architecture of {world.name} (allowed: {', '.join(world.arch_names)})")
    if world.algorithm == "opac2":  # one network family: depth, width and obs_norm from the shapes
        from rlbackdoors.agent import opac2_shape
        from rlbackdoors.folder import FolderError

        arch = arch or world.arch_names[0]
        try:
            section: dict = {"opac2": opac2_shape(state, weights_file)}
        except FolderError as err:
            raise ZooError(str(err)) from None
    else:
        if arch is None:
            arch = resolve_arch(world.name, state, model_class, weights_file)
        load_state(build_model(arch, world.name), state, weights_file)  # fits, by key, shape and value
        section = {"model": {"arch": arch}}
    truth = folder / "ground_truth.csv"
    if truth.is_file():
        digest[truth.name] = _sha256(truth)
        lines = truth.read_text(errors="replace").strip().splitlines()
        if not lines or lines[0].strip() not in ("0", "1"):
            raise ZooError(f"{str(truth)!r} must hold 1 (poisoned) or 0 (clean)")
        label = int(lines[0].strip())
    own_trigger = None
    if own is not None and own["env"]["name"] == world.name and trigger is None and isinstance(own["poison"].get("trigger"), str):
        trigger = own_trigger = own["poison"]["trigger"]  # what train recorded is known, not guessed
    env, sources = env_settings(world, files, overrides, str(folder))
    config = run_config(world, arch, env, label, trigger, str(folder), section)
    if world.algorithm == "opac2":
        from rlbackdoors.agent import opac2_policy
        from rlbackdoors.config import RunConfig
        from rlbackdoors.folder import FolderError

        try:
            opac2_policy(RunConfig.from_dict(config), state, weights_file)  # fits, by key, shape and value
        except FolderError as err:
            raise ZooError(str(err)) from None
    return SourceModel(folder, weights_file, name, world.name, arch, model_class, env, label, state, digest, config, configs, own_trigger, sources)


def run_config(world: worlds.World, arch: str, env: dict, label: int | None, trigger: str | None, where: str, network: dict | None = None) -> dict:
    """Our config.json of an imported model, checked. ``network``: the config's network section
    (default ``{"model": {"arch": arch}}``; an OPAC² world's is its ``opac2`` depth, width and
    obs_norm). Its trigger is ``trigger`` when given, else the world's default (or, when the env
    cannot take that, a placeholder the world names): the model's own is not known, and
    METADATA.csv says so."""
    from rlbackdoors.config import RunConfig

    candidates: list[str | None] = [trigger] if trigger is not None else [t for t in (world.default_trigger, *world.placeholder_triggers) if t]
    error: Exception | None = None
    for candidate in candidates or [None]:
        data = {
            "env": {"name": world.name, **env},
            **(network or {"model": {"arch": arch}}),
            "poison": {"poisoned": bool(label), "trigger": candidate},
            "train": {"seed": 0},
        }
        try:
            cfg = RunConfig.from_dict(data)
            _check_env(cfg)
            return json.loads(cfg.to_json())
        except (ConfigError, ValueError, RuntimeError) as err:
            error = err
    raise ConfigError(f"{where}: no config of {world.name} takes these settings ({error})")


def _check_env(cfg) -> None:
    """Build the config's env once with its trigger on: what the engines check (a pattern that
    does not fit the room or the lava count) fails here, before anything is written."""
    world = cfg.env.world
    if world.vector_entry_point is not None:
        from rlbackdoors.poison.mix import make_vector_env

        envs = make_vector_env(cfg.env, cfg.poison.trigger, [True])
    else:
        envs = cfg.env.make(cfg.poison.trigger)
    envs.close()


# ----- the zoo folder ----------------------------------------------------------------------------
def is_imported(path: str | Path) -> bool:
    """Whether ``path`` is a zoo that ``zoo import-trojai`` wrote."""
    meta = Path(path) / "zoo.json"
    try:
        data = json.loads(meta.read_bytes().decode("utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and isinstance(data.get("trojai"), dict)


def _zoo_meta(source: Path, options: dict) -> dict:
    from rlbackdoors.folder import stack_versions

    return {"format": IMPORT_FORMAT, "trojai": {"source": source.resolve().name, "options": options}, "versions": stack_versions()}


def _check_out(out: Path, source: Path, options: dict) -> bool:
    """True when ``out`` already holds this import (same source and options)."""
    if out.exists() and not out.is_dir():
        raise ZooError(f"{str(out)!r} exists and is not a folder")
    if (out / "zoo.json").is_file():
        if not is_imported(out):
            raise ZooError(f"{str(out)!r} is a zoo that was not imported from TrojAI; import into a new or empty folder")
        old = json.loads((out / "zoo.json").read_bytes().decode("utf-8"))["trojai"]
        if old.get("source") not in (source.resolve().name, str(source.resolve())):  # older imports kept the whole path
            raise ZooError(f"zoo {str(out)!r} was imported from {old.get('source')!r}; import {str(source)!r} into a new folder")
        for key in sorted(set(old.get("options", {})) | set(options)):
            if old.get("options", {}).get(key) != options.get(key):
                raise ConfigError(f"zoo {str(out)!r} was imported with other options ({key} differs); import into a new folder")
        return True
    if out.is_dir() and any(p.name != ".lock" for p in out.iterdir()):
        raise ZooError(f"{str(out)!r} is not empty and holds no zoo.json; import into a new or empty folder")
    return False


def _copy_trojai_files(folder: Path, target: Path) -> None:
    target.mkdir()
    for path in sorted(folder.iterdir()):
        if path.is_file() and not path.is_symlink() and path.suffix in COPIED_SUFFIXES and path.stat().st_size <= MAX_COPIED_BYTES:
            shutil.copyfile(path, target / path.name)


def _write_model(model: SourceModel, target: Path, options: dict) -> None:
    """Build the model folder under a temp name beside ``target``, then rename it into place."""
    from rlbackdoors.agent import load as load_agent
    from rlbackdoors.config import RunConfig
    from rlbackdoors.evaluate import evaluate
    from rlbackdoors.folder import ModelFolder, write_manifest
    from rlbackdoors.zoo.examples import write_examples
    from rlbackdoors.zoo.job import COMPLETE_MARK, reduced_config

    tmp = target.with_name(f".{target.name}.{os.getpid()}{TMP_DIR_SUFFIX}")
    remove_tree(tmp)
    tmp.mkdir(parents=True)
    try:
        world = worlds.get(model.world)
        trigger = options.get("trigger")
        cfg = RunConfig.from_dict(model.config)
        folder = ModelFolder(tmp)
        save_torch(tmp / "model.pt", {k: v.detach().cpu().contiguous().clone() for k, v in model.state.items()})
        folder.write_config(cfg)
        if model.label is not None:  # an unlabelled model stays so: detect fit/score refuse it by name
            folder.write_ground_truth(bool(model.label))
        metrics: dict = {
            "poisoned": None if model.label is None else bool(model.label),
            "converged": True,  # a model TrojAI shipped in its round's dataset
            "source": "trojai",
            "clean_sr": None,
            "poisoned_sr": None,
            "clean_reward": None,
            "poisoned_reward": None,
            "episodes": options["episodes"],
            "eval_policy": options["policy"] or cfg.train.eval_policy,
            "eval_seed": options["seed"],
        }
        atomic_write_text(tmp / "metrics.json", json.dumps(metrics, indent=2, sort_keys=True) + "\n")
        if options["episodes"]:
            agent = load_agent(tmp)
            close_k = (cfg.poison.close_k_min, cfg.poison.close_k_max) if world.close_to_trigger and trigger else None
            result = evaluate(agent, cfg.env, trigger, options["episodes"], options["seed"], metrics["eval_policy"], close_k)
            metrics.update({k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in result.to_dict().items()})
            atomic_write_text(tmp / "metrics.json", json.dumps(metrics, indent=2, sort_keys=True) + "\n")
        if options["examples"]:
            write_examples(tmp, cfg, episodes=options["examples"], seed=2_000_000, policy="sample")
        _copy_trojai_files(model.folder, tmp / "trojai")
        atomic_write_text(tmp / "trojai.json", json.dumps(model.provenance(options), indent=2, sort_keys=True) + "\n")
        reduced = reduced_config(tmp, json.loads((tmp / "config.json").read_bytes().decode("utf-8")))
        if model.model_class:
            reduced["trojai_class"] = model.model_class
        mark = json.dumps(reduced, indent=2, sort_keys=True) + "\n"
        write_manifest(tmp, {COMPLETE_MARK: mark.encode()})  # every file's sha256 (zoo verify), the mark's included
        atomic_write_text(tmp / COMPLETE_MARK, mark)
        os.replace(tmp, target)
    except BaseException:
        remove_tree(tmp)
        raise


def _same_model(target: Path, model: SourceModel) -> bool:
    try:
        old = json.loads((target / "trojai.json").read_bytes().decode("utf-8"))
    except (OSError, ValueError):
        return False
    same_source = old.get("source") in (model.source, str(model.folder.resolve()))  # older imports kept the whole path
    return same_source and old.get("sha256") == model.digest and (target / "reduced-config.json").is_file()


def import_trojai(
    source: str | Path,
    out: str | Path,
    world: str | None = None,
    arch: str | None = None,
    size: int | None = None,
    num_lava: int | None = None,
    max_steps: int | None = None,
    label: int | None = None,
    num_cubes: int | None = None,
    trigger: str | None = None,
    episodes: int = 100,
    examples: int = 5,
    seed: int = 1_000_000,
    policy: str | None = None,
) -> dict:
    """Import the TrojAI model folders of ``source`` into the zoo ``out`` (module doc); returns a
    summary: ``models``, ``written``, ``skipped``, and per model its world, arch and clean SR."""
    source, out = Path(source), Path(out)
    if world is not None:
        worlds.get(world)  # ValueError names the registered worlds
    if arch is not None and world is None:
        raise ConfigError("--arch needs --world (an architecture is a world's)")
    if trigger is not None:
        if world is None:
            raise ConfigError("--trigger needs --world (a trigger is read by its world)")
        worlds.parse_trigger(world, trigger)
    options = {
        "world": world,
        "arch": arch,
        "size": size,
        "num_lava": num_lava,
        "max_steps": max_steps,
        "num_cubes": num_cubes,
        "label": label,
        "trigger": trigger,
        "episodes": episodes,
        "examples": examples,
        "seed": seed,
        "policy": policy,
    }
    if out.resolve() == source.resolve() or source.resolve() in out.resolve().parents:
        raise ZooError(f"{str(out)!r} is inside the TrojAI folder; write the zoo elsewhere (the source is only read)")
    folders = model_folders(source)
    names = our_names(folders)
    overrides = {"size": size, "num_lava": num_lava, "max_steps": max_steps, "num_cubes": num_cubes}
    models = [read_source(f, n, world, overrides, label, trigger, arch) for f, n in zip(folders, names)]  # all checked first
    for model in models:  # where in the round, never a path of this machine (datasets are shared)
        model.source = model.folder.relative_to(source).as_posix() if model.folder != source else "."
    existed = _check_out(out, source, options)
    out.mkdir(parents=True, exist_ok=True)
    lock = FolderLock(out, "zoo")
    try:
        lock.acquire()
    except LockedError as err:
        raise ZooError(str(err)) from None
    written = skipped = 0
    try:
        if not existed:
            atomic_write_text(out / "zoo.json", json.dumps(_zoo_meta(source, options), indent=2, sort_keys=True) + "\n")
        models_dir = out / "models"
        models_dir.mkdir(exist_ok=True)
        for stale in models_dir.glob(f".*{TMP_DIR_SUFFIX}"):  # what a killed import left (we hold the lock)
            remove_tree(stale)
        for model in models:
            target = models_dir / model.name
            if target.exists():
                if not _same_model(target, model):
                    raise ZooError(f"{str(target)!r} holds another model than {str(model.folder)!r}; import into a new folder")
                skipped += 1
                continue
            _write_model(model, target, options)
            written += 1
        write_metadata(out)
    finally:
        lock.release()
    return {
        "models": len(models),
        "written": written,
        "skipped": skipped,
        "per_model": [{"name": m.name, "source": m.folder.name, "world": m.world, "arch": m.arch, "class": m.model_class, "label": m.label} for m in models],
    }


# ----- what an imported zoo holds ------------------------------------------------------------------
def _json_or_empty(path: Path) -> dict:
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def states(zoo: str | Path) -> list:
    """The imported models as :class:`rlbackdoors.zoo.index.ModelState` (status ``done``), one
    cell per world x arch, so the zoo's report and METADATA code read them as they read a
    trained zoo's."""
    from rlbackdoors.zoo.index import ModelState
    from rlbackdoors.zoo.plan import PlannedModel
    from rlbackdoors.zoo.spec import Cell, Group, TriggerFamily

    models_dir = Path(zoo) / "models"
    found = []
    for folder in sorted(p for p in models_dir.iterdir() if p.is_dir() and not p.name.startswith(".") and (p / "reduced-config.json").is_file()):
        info = _json_or_empty(folder / "trojai.json")
        config, metrics = _json_or_empty(folder / "config.json"), _json_or_empty(folder / "metrics.json")
        found.append((folder, info, config, metrics))
    cells: dict[tuple[str, str, str], Cell] = {}
    groups: dict[tuple[str, str, str, bool], Group] = {}

    # A model's cell: world x arch x trigger family (known for --trigger or our own folders).
    keys = [(str(i.get("world")), str(i.get("arch")), str(t).split(":")[0] if (t := _known_trigger(i)) else UNKNOWN_TRIGGER) for _, i, _, _ in found]
    sizes = Counter(keys)
    for world, arch, family in sizes:
        n = sizes[(world, arch, family)]
        cells[(world, arch, family)] = Cell(
            entry=len(cells), world=world, arch=arch, trigger=TriggerFamily(name=family), clean=n, poisoned=n, max_attempts=n, overrides={}
        )
    out: list[ModelState] = []
    for (folder, info, config, metrics), key in zip(found, keys):
        cell = cells[key]
        poisoned = bool(info.get("label"))
        group = groups.setdefault((*key, poisoned), Group(index=len(groups), cell=cell, poisoned=poisoned, id_offset=0))
        number = int(folder.name[3:]) if ID_NAME.match(folder.name) else len(out)
        out.append(ModelState(PlannedModel(number, group, 0), folder, "done", config, metrics))
    return out


# The network's shape in an OPAC² section is read off the weights (known); the rest of the section
# and the ppo and train sections are how a model was trained, which an import does not know.
SHAPE_KEYS = ("opac2.depth", "opac2.width", "opac2.obs_norm")


def _training_unknown(key: str) -> bool:
    return key.split(".")[0] in ("train", "ppo", "opac2") and key not in SHAPE_KEYS


# What a training run's metrics say about the run itself (not measured again at import).
TRAINING_METRICS = ("frames", "converged_at_frames", "wall_time_s", "cpu_time_s", "stop_reason", "trainer")


def _own_training(folder: Path) -> tuple[dict, dict]:
    """The training settings and metrics that this package's ``train`` recorded in the source folder
    (its config.json and metrics.json, copied to ``trojai/``), flattened; empty for a TrojAI model."""
    from rlbackdoors.zoo.spec import flatten

    try:
        config = read_round(folder / "trojai", ("config.json",)).own_config()
    except ValueError:  # not JSON we can read: not a file train wrote
        config = None
    if config is None:
        return {}, {}
    metrics = _json_or_empty(folder / "trojai" / "metrics.json")
    trained = {k: v for k, v in flatten(config).items() if _training_unknown(k)}
    return trained, {f"metrics.{k}": v for k, v in flatten(metrics).items() if k in TRAINING_METRICS}


def metadata_text(zoo: str | Path) -> str:
    """METADATA.csv of an imported zoo. A model's training settings (train, ppo, the OPAC² section
    but its network's shape) and its attempt are what our config.json had to hold to play it, not
    how it was trained: empty, unless the source folder is one this package's ``train`` wrote, whose
    recorded settings and run metrics (frames, wall time) are given instead."""
    from rlbackdoors.zoo.index import LEAD_COLUMNS, csv_text, metadata_rows

    rows = metadata_rows(states(zoo))
    for row in rows:
        folder = Path(zoo) / "models" / row["model_name"]
        own_settings, own_metrics = _own_training(folder)
        for key in [k for k in row if _training_unknown(k)]:
            row[key] = own_settings.get(key)
        row.update(own_metrics)
        row["attempt"] = ""  # no zoo attempt: a model shipped or trained elsewhere
        info = _json_or_empty(folder / "trojai.json")
        if row.get("poison.trigger") is not None and not _known_trigger(info):
            row["poison.trigger"] = UNKNOWN_TRIGGER  # the config's is the world's default, not the model's
        if info.get("label") is None:
            row["poisoned"] = ""  # no ground truth shipped: unknown, not clean
        row["trojai.source"] = info.get("source", "")
        row["trojai.model_class"] = info.get("model_class") or ""
        row["trojai.env_sources"] = "; ".join(f"{k}={v}" for k, v in sorted((info.get("env_sources") or {}).items()))
    return csv_text(rows, LEAD_COLUMNS)


def write_metadata(zoo: str | Path) -> Path:
    return atomic_write_text(Path(zoo) / "METADATA.csv", metadata_text(zoo))


def status(zoo: str | Path) -> str:
    """Models per world, arch and label, with their mean measured clean SR."""
    rows: dict[tuple[str, str, str], list[float]] = {}
    for s in states(zoo):
        label = s.model.group.label if (s.metrics or {}).get("poisoned") is not None else "unknown"
        key = (s.model.group.cell.world, s.model.group.cell.arch_label, label)
        value = (s.metrics or {}).get("clean_sr")
        rows.setdefault(key, []).append(float(value) if isinstance(value, (int, float)) else math.nan)
    head = ("world", "arch", "label", "models", "clean SR (mean, measured here)")
    body = [
        (
            w,
            a,
            label,
            str(len(v)),
            "–" if all(math.isnan(x) for x in v) else f"{sum(x for x in v if not math.isnan(x)) / sum(not math.isnan(x) for x in v):.3f}",
        )
        for (w, a, label), v in sorted(rows.items())
    ]
    table = [head, *body]
    widths = [max(len(r[i]) for r in table) for i in range(len(head))]
    lines = ["  ".join(v.ljust(w) for v, w in zip(r, widths)) for r in table]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return f"{Path(zoo)}: imported from TrojAI ({sum(len(v) for v in rows.values())} models)\n" + "\n".join(lines)


def report(zoo: str | Path) -> Path:
    """``ZOO/report/`` of an imported zoo: the same tables and plots as a trained zoo's (SRs as
    measured here at import; no training curves or frames), and METADATA.csv refreshed."""
    from rlbackdoors.zoo import report as zoo_report

    path = Path(zoo)
    found = states(path)
    write_metadata(path)
    out = path / "report"
    name = f"TrojAI models imported from {Path(str(_json_or_empty(path / 'zoo.json').get('trojai', {}).get('source', '?'))).name}"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN frames and wall times: nothing was trained here
        trained = [s for s in found if isinstance((s.metrics or {}).get("frames"), (int, float))]  # none, unless a folder says so
        text = zoo_report.write_report(out, name, found, trained)
    note = (
        "\n## About these models\n\nImported from TrojAI (`rlbackdoors zoo import-trojai`): every model is one TrojAI shipped, so all "
        "count as converged; the SRs and rewards were measured here, in our worlds, at import (metrics.json); TrojAI's triggers "
        "are not named, so poisoned SRs are measured only when the import was given `--trigger`. Nothing was trained: no frames, "
        "wall times or training curves.\n"
    )
    head, sep, tail = text.partition("## Frames and wall time to converge")
    tail = tail.replace("(no converged model yet)", "(nothing was trained here)", 1)
    atomic_write_text(out / "report.md", head + sep + tail + note)
    return out


__all__ = ["import_trojai", "is_imported", "model_folders", "read_source", "report", "states", "status", "write_metadata"]
