"""What a TrojAI round's model folder says about its model: the class, and the env it was trained in.

Each RL round put these facts in other files (the table of docs/trojai.md, "Where each round put
its settings": a reduced config naming ``basicfc`` and a ``model.info.json`` in one, a
``config.json`` with the grid size only in another, the lava count only in the env string of the
clean examples), and a reader that knows only one of them plays a model in the wrong env without
a word (a 9x9 one-lava model in the world's 11x11 ten-lava default).

:func:`read_round` reads every one of them that a folder holds (as JSON / text, never
unpickled) and :meth:`RoundFiles.env` gives a world's env settings with, for each, the file and
key it came from: the first of :data:`ROUND_FILES` that names a setting wins, the env string
last. Both the importer (``zoo import-trojai``) and a detector's view of a model
(:mod:`rlbackdoors.detect.handle`, ``detect infer``) read settings here, so the two never
disagree on which env a model was trained in.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rlbackdoors import worlds
from rlbackdoors.worlds.base import canonical_class

# Strongest first: where a setting appears in several, the first wins.
ROUND_FILES = ("reduced-config.json", "config.json", "model.info.json", "args.json", "params.json")
ENV_STRING = "env-string.txt"  # in clean-example-data/: the gym id of the clean env
EXAMPLES_DIR = "clean-example-data"
MAX_BYTES = 4 << 20
# TrojAI's flat keys -> our env fields (values: an int, or a one-value list such as [1])
FLAT_KEYS = (
    ("grid_size", "size"),
    ("size", "size"),
    ("num_lava_squares", "num_lava"),
    ("max_steps", "max_steps"),
    ("max_episode_length", "max_steps"),
    ("test_max_steps", "max_steps"),  # the Jul 2023 round's model.info.json: the episode cut TrojAI evaluated with
)
# Files whose env keys sit in a sub-object (RLlib's params.json: env_config.cfg)
NESTED = {"params.json": ("env_config", "cfg")}
# MiniGrid's LavaCrossing ids: S = grid size, N = the world's lava count (rivers or squares)
GYM_ID = re.compile(r"MiniGrid-LavaCrossingS(\d+)N(\d+)-v\d+")


@dataclass(frozen=True)
class Setting:
    """One env setting and where it was read (``"config.json: grid_size"``)."""

    value: Any
    source: str


@dataclass
class RoundFiles:
    """The round files of one model folder, read as data (:func:`read_round`)."""

    configs: dict[str, dict] = field(default_factory=dict)  # file name -> JSON object, ROUND_FILES order
    env_string: str | None = None

    def own_config(self) -> dict | None:
        """The ``config.json`` that this package's ``train`` wrote (``format_version``, an ``env``
        naming a registered world, a ``poison`` section), else None: not a TrojAI file."""
        data = self.configs.get("config.json") or {}
        env, poison = data.get("env"), data.get("poison")
        if isinstance(data.get("format_version"), int) and isinstance(env, dict) and isinstance(poison, dict):
            if env.get("name") in worlds.names():
                return data
        return None

    def own_reduced(self) -> dict | None:
        """The ``reduced-config.json`` that this package wrote (``world`` and ``env`` keys), else None."""
        data = self.configs.get("reduced-config.json") or {}
        return data if isinstance(data.get("world"), str) and isinstance(data.get("env"), dict) else None

    def model_class(self) -> tuple[str | None, str | None]:
        """(TrojAI class, where it was read): ``model`` or ``arch`` of the first round file naming
        one; our own files name no TrojAI class."""
        for name in ROUND_FILES:
            if name == "config.json" and self.own_config() is not None or name == "reduced-config.json" and self.own_reduced() is not None:
                continue
            data = self.configs.get(name, {})
            for key in ("model", "arch"):
                if isinstance(data.get(key), str):
                    return data[key], f"{name}: {key}"
        return None, None

    def env(self, world: worlds.World) -> dict[str, Setting]:
        """``world``'s env settings these files give, each with its source (module doc).

        Our own files give their ``env`` section as it is; TrojAI's give :data:`FLAT_KEYS`, the
        world's own keys (:attr:`~rlbackdoors.worlds.World.trojai_env`) and the env string's grid
        size and lava count. ValueError names a value our worlds cannot take (a range of lava
        counts, ``random_length: true``)."""
        allowed = (*world.env_fields, "max_steps")
        found: dict[str, Setting] = {}

        def give(key: str, value: Any, source: str) -> None:
            if key in allowed and key not in found:
                found[key] = Setting(value, source)

        for name, section in (("config.json", self.own_config()), ("reduced-config.json", self.own_reduced())):  # train's config is the record
            if section is not None and section["env"].get("name", world.name) == world.name:
                for key, value in section["env"].items():
                    if key not in ("name", "engine"):
                        give(key, value, f"{name}: env.{key}")
        for name in ROUND_FILES:
            data = self.configs.get(name)
            if data is None or (name == "config.json" and self.own_config() is not None) or (name == "reduced-config.json" and self.own_reduced() is not None):
                continue
            if data.get("random_length") is True:
                raise ValueError(f"{name}: random_length is true; our worlds have fixed hallways")
            inner: Any = data
            for key in NESTED.get(name, ()):
                inner = inner.get(key) if isinstance(inner, dict) else None
            prefix = ".".join(NESTED.get(name, ()))
            for theirs, ours in FLAT_KEYS:
                if isinstance(inner, dict) and theirs in inner and ours in allowed and ours not in found:
                    give(
                        ours,
                        _one_number(inner[theirs], f"{name}: {prefix + '.' if prefix else ''}{theirs}"),
                        f"{name}: {prefix + '.' if prefix else ''}{theirs}",
                    )
            if world.trojai_env is not None:
                for key, value in (world.trojai_env(data) or {}).items():
                    give(key, value, f"{name}: {world.name} round keys")
        if self.env_string is not None:
            match = GYM_ID.fullmatch(self.env_string)
            if match is not None:
                source = f"{EXAMPLES_DIR}/{ENV_STRING}: {self.env_string}"
                give("size", int(match.group(1)), source)
                if world.trojai_env_string_count is not None:
                    give(world.trojai_env_string_count, int(match.group(2)), source)
        return found


def _one_number(value: Any, where: str) -> int:
    if isinstance(value, list) and len(value) == 1:
        value = value[0]
    if isinstance(value, list) and len(value) == 2 and value[0] == value[1]:
        value = value[0]
    if not isinstance(value, int) or isinstance(value, bool):
        raise ValueError(f"{where}={value!r} is not one number (our worlds take a fixed value; give it with a flag)")
    return value


def read_json(path: Path) -> dict:
    """One JSON object from ``path``, at most :data:`MAX_BYTES`; ValueError names the file."""
    if path.stat().st_size > MAX_BYTES:
        raise ValueError(f"{str(path)!r} is larger than {MAX_BYTES} bytes")
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as err:
        raise ValueError(f"{str(path)!r} is not JSON ({err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{str(path)!r} must hold a JSON object")
    return data


def read_env_string(path: Path) -> str | None:
    """The first line of an ``env-string.txt`` (a gym id), None when there is none."""
    if not path.is_file() or path.is_symlink() or path.stat().st_size > 4096:
        return None
    text = path.read_bytes().decode("utf-8", errors="replace").strip()
    return text.splitlines()[0].strip() if text else None


def read_round(folder: str | Path, names: tuple[str, ...] = ROUND_FILES, examples: str | Path | None = None) -> RoundFiles:
    """The round files ``names`` that ``folder`` holds, and the env string of ``examples`` (default
    ``folder/clean-example-data``). Links are not followed: a round folder is untrusted input."""
    folder = Path(folder)
    configs = {n: read_json(folder / n) for n in names if (folder / n).is_file() and not (folder / n).is_symlink()}
    where = Path(examples) if examples is not None else folder / EXAMPLES_DIR
    return RoundFiles(configs, read_env_string(where / ENV_STRING))


__all__ = ["ROUND_FILES", "RoundFiles", "Setting", "canonical_class", "read_json", "read_round"]
