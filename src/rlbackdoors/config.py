"""The typed run configuration: everything a training run needs, round-tripping to ``config.json``.

Validation happens here, at the edge: unknown keys, wrong types and out-of-range
values are rejected with a message naming the field and what is allowed.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

from rlbackdoors import __version__

from rlbackdoors import worlds
from rlbackdoors.validate import (  # noqa: F401  (re-exported: the config's validation vocabulary)
    MAX_ENV_COPIES,
    MAX_EPISODES,
    MAX_FRAMES,
    MAX_SEED,
    ConfigError,
    _at_least,
    _choice,
    _in_range,
    _unit_interval,
    check_seed,
)

ENVS = worlds.names("ppo")  # the grid worlds, trained with PPO by this config (OPAC²: safety_config)
ENGINES = ("batched", "minigrid")
# Architecture names per world (the registry holds the classes); the first is the default.
ARCHS_BY_ENV = {w.name: w.arch_names for w in worlds.registered("ppo")}
ARCHS = tuple(dict.fromkeys(a for archs in ARCHS_BY_ENV.values() for a in archs))
EVAL_POLICIES = ("sample", "greedy")
DEVICES = ("cpu", "cuda", "auto")


@dataclass
class EnvConfig:
    """Which world and its size; ``None`` fields take the world's paper default (ENV_DEFAULTS)."""

    name: str = worlds.DEFAULT_WORLD
    size: int | None = None
    max_steps: int = 250
    see_through_walls: bool | None = None
    engine: str = "batched"
    num_crossings: int = 1  # LavaWorld: lava rivers
    num_lava: int = 10  # Randomized LavaWorld: single lava squares

    def __post_init__(self):
        if self.name in ENVS:
            for key, value in worlds.get(self.name).env_defaults.items():
                if getattr(self, key) is None:
                    setattr(self, key, value)

    @property
    def world(self) -> worlds.World:
        return worlds.get(self.name)

    def check(self) -> None:
        _choice("env.name", self.name, ENVS)
        _choice("env.engine", self.engine, ENGINES)
        _in_range("env.max_steps", self.max_steps, 1, 100_000)
        _in_range("env.size", self.size, 5, 64)  # every world: a typo'd size must not allocate a huge grid
        try:
            check_env = self.world.check_env
            assert check_env is not None  # every PPO world (env.name is one: checked above) has one
            check_env(self)
        except ConfigError:
            raise
        except ValueError as err:
            raise ConfigError(f"env: {err}") from None


@dataclass
class PoisonConfig:
    """The trigger is kept for clean models too: their poisoned SR is measured under it.

    ``trigger=None`` takes the world's default trigger.
    """

    trigger: str | None = None
    poisoned: bool = True
    num_clean_envs: int | None = None  # None: the world's mix
    num_close_envs: int | None = None  # close-to-trigger copies (Colorful Memory only)
    num_poisoned_envs: int | None = None
    close_k_min: int = 1  # a close-to-trigger layout recolours k squares, k uniform in [min, max]
    close_k_max: int = 3

    def fill_defaults(self, env_name: str) -> None:
        mix = worlds.get(env_name).mix if env_name in ENVS else (8, 0, 2)
        for key, value in zip(("num_clean_envs", "num_close_envs", "num_poisoned_envs"), mix):
            if getattr(self, key) is None:
                setattr(self, key, value)

    def check(self, env_name: str = worlds.DEFAULT_WORLD) -> None:
        from rlbackdoors.worlds import parse_trigger

        self.fill_defaults(env_name)
        if self.trigger is None:
            raise ConfigError("poison.trigger is not set")
        try:
            parse_trigger(env_name, self.trigger)
        except ValueError as err:
            raise ConfigError(f"poison.trigger: {err}") from None
        for name in ("num_clean_envs", "num_close_envs", "num_poisoned_envs"):
            _in_range(f"poison.{name}", getattr(self, name), 0, MAX_ENV_COPIES)
        world = worlds.get(env_name)
        if self.num_close_envs and not world.close_to_trigger:
            close_worlds = ", ".join(w.name for w in worlds.registered() if w.close_to_trigger)
            raise ConfigError(f"poison.num_close_envs must be 0 for env.name={env_name!r} (close-to-trigger envs exist for {close_worlds} only)")
        if world.close_to_trigger:
            from rlbackdoors.triggers.wall_colors import check_close_k

            try:
                check_close_k((self.close_k_min, self.close_k_max), parse_trigger(env_name, self.trigger).num_squares)
            except ValueError as err:
                raise ConfigError(f"poison.close_k_min/close_k_max: {err}") from None
        if self.poisoned and self.num_poisoned_envs == 0:
            raise ConfigError("poison.num_poisoned_envs must be >= 1 for a poisoned model")
        if self.num_envs < 1:
            raise ConfigError("poison: num_clean_envs + num_poisoned_envs must be >= 1")

    def counts(self) -> tuple[int, int, int]:
        """(clean, close-to-trigger, poisoned) copies; unset ones as in the 8:2 mix."""
        clean, close, poisoned = (d if v is None else v for v, d in zip((self.num_clean_envs, self.num_close_envs, self.num_poisoned_envs), (8, 0, 2)))
        return clean, close, poisoned

    @property
    def num_envs(self) -> int:
        return sum(self.counts())

    def poisoned_mask(self) -> list[bool]:
        """Clean copies first, then close-to-trigger, poisoned last; a clean model trains on
        clean copies where the poisoned ones would be."""
        clean, close, poisoned = self.counts()
        return [False] * (clean + close) + [self.poisoned] * poisoned

    def close_mask(self) -> list[bool]:
        clean, close, poisoned = self.counts()
        return [False] * clean + [True] * close + [False] * poisoned


@dataclass
class CurriculumConfig:
    """Randomized LavaWorld's warm-up (SPEC 2): clean-only on a small world until the mean
    training return reaches ``reward_threshold``, then the full world and the poisoning mix.

    ``enabled=None`` means the world's default (World.curriculum).
    """

    enabled: bool | None = None
    size: int = 7
    num_lava: int = 5
    reward_threshold: float = 0.8
    window: int = 100  # clean training episodes the mean return is taken over

    def check(self) -> None:
        _in_range("curriculum.window", self.window, 1, MAX_EPISODES)
        _in_range("curriculum.size", self.size, 5, 64)
        _at_least("curriculum.num_lava", self.num_lava, 0)
        _unit_interval("curriculum.reward_threshold", self.reward_threshold)


@dataclass
class ModelConfig:
    arch: str | None = None  # None: the world's first architecture (ARCHS_BY_ENV)

    def check(self, env_name: str = worlds.DEFAULT_WORLD) -> None:
        _choice("model.arch", self.arch, ARCHS_BY_ENV.get(env_name, ARCHS))


@dataclass
class PPOConfig:
    """The paper's LavaWorld appendix table (torch-ac PPO)."""

    rollout: int = 128
    epochs: int = 4
    batch_size: int = 256
    lr: float = 1e-3
    clip: float = 0.2
    value_coef: float = 0.5
    entropy_coef: float = 0.01
    gamma: float = 0.99
    gae_lambda: float = 0.95
    max_grad_norm: float = 0.4
    adam_eps: float = 1e-8
    recurrence: int = 1  # steps of truncated BPTT for recurrent models (torch-ac's ``recurrence``)

    def check(self) -> None:
        for name in ("rollout", "epochs", "batch_size", "recurrence"):
            _in_range(f"ppo.{name}", getattr(self, name), 1, 1_000_000)
        if self.rollout % self.recurrence:
            raise ConfigError(f"ppo.rollout={self.rollout} must be a multiple of ppo.recurrence={self.recurrence}")
        if self.batch_size % self.recurrence:
            raise ConfigError(f"ppo.batch_size={self.batch_size} must be a multiple of ppo.recurrence={self.recurrence}")
        for name in ("lr", "clip", "max_grad_norm", "adam_eps"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"ppo.{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("gamma", "gae_lambda"):
            _unit_interval(f"ppo.{name}", getattr(self, name))
        for name in ("value_coef", "entropy_coef"):
            if getattr(self, name) < 0:
                raise ConfigError(f"ppo.{name} must be >= 0, got {getattr(self, name)!r}")


@dataclass
class TrainConfig:
    seed: int = 0
    max_frames: int = 5_000_000
    eval_interval: int = 100_000
    eval_episodes: int = 100
    final_eval_episodes: int = 200
    eval_seed: int = 1_000_000
    eval_policy: str = "sample"
    clean_threshold: float | None = None  # None: the world's paper value (its World.thresholds)
    poisoned_threshold: float | None = None
    patience: int | None = None  # None: the world's default (World.patience; 0 = off)
    patience_reward: float = 0.9
    device: str = "cpu"
    torch_threads: int = 1

    def check(self) -> None:
        check_train_budget(self)
        _in_range("train.patience", self.patience, 0, 1_000_000)
        _choice("train.eval_policy", self.eval_policy, EVAL_POLICIES)


def check_train_budget(tc) -> None:
    """The ``train`` fields both run configs share: seeds, frame and episode budgets, threads,
    device and thresholds."""
    check_seed("train.seed", tc.seed)
    _in_range("train.max_frames", tc.max_frames, 1, MAX_FRAMES)
    _in_range("train.eval_interval", tc.eval_interval, 1, MAX_FRAMES)
    _in_range("train.eval_episodes", tc.eval_episodes, 1, MAX_EPISODES)
    _in_range("train.final_eval_episodes", tc.final_eval_episodes, 1, MAX_EPISODES)
    check_seed("train.eval_seed", tc.eval_seed)
    _in_range("train.torch_threads", tc.torch_threads, 1, 1024)
    _choice("train.device", tc.device, DEVICES)
    for name in ("clean_threshold", "poisoned_threshold"):
        _unit_interval(f"train.{name}", getattr(tc, name))


class JsonConfig:
    """``config.json`` I/O shared by the run configs (dataclasses with ``from_dict``)."""

    if TYPE_CHECKING:  # what the subclasses define; nothing is defined at run time
        __dataclass_fields__: ClassVar[dict[str, Any]]

        @classmethod
        def from_dict(cls, data: dict) -> JsonConfig: ...

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n"

    @classmethod
    def load(cls, path: str | Path):
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"config file {str(path)!r} does not exist")
        try:
            data = json.loads(path.read_bytes().decode("utf-8"))
        except (ValueError, RecursionError) as err:  # bad UTF-8 or JSON, absurd nesting or numbers
            raise ConfigError(f"config file {str(path)!r} is not valid JSON: {' '.join(str(err).split())[:200]}") from None
        except OSError as err:
            raise ConfigError(f"config file {str(path)!r} cannot be read: {err.strerror or err}") from None
        return cls.from_dict(data)


@dataclass
class RunConfig(JsonConfig):
    env: EnvConfig = field(default_factory=EnvConfig)
    poison: PoisonConfig = field(default_factory=PoisonConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    ppo: PPOConfig | None = None  # None: the world's defaults (default_ppo)
    train: TrainConfig = field(default_factory=TrainConfig)
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)
    version: str = __version__

    def __post_init__(self):
        name = self.env.name
        world = worlds.get(name) if name in ENVS else None
        if world is not None:
            if self.poison.trigger is None:
                self.poison.trigger = world.default_trigger
            if world.settle_trigger is not None:  # e.g. a bare kind: drawn once, from the seed
                try:
                    self.poison.trigger = world.settle_trigger(self.poison.trigger, self.train.seed, self.env.size)
                except (ValueError, TypeError):
                    pass  # a bad env.size or seed: check() reports it by name
        self.poison.fill_defaults(name)
        if self.model.arch is None:
            self.model.arch = ARCHS_BY_ENV.get(name, ARCHS)[0]
        if self.ppo is None:
            self.ppo = default_ppo(name)
        if self.train.patience is None:
            self.train.patience = world.patience if world else 0
        if self.curriculum.enabled is None:
            self.curriculum.enabled = bool(world and world.curriculum)
        clean_t, poisoned_t = world.thresholds if world else (None, None)
        if self.train.clean_threshold is None:
            self.train.clean_threshold = clean_t
        if self.train.poisoned_threshold is None:
            self.train.poisoned_threshold = poisoned_t

    def check(self) -> "RunConfig":
        self.env.check()
        self.poison.check(self.env.name)
        self.model.check(self.env.name)
        assert self.ppo is not None  # __post_init__ fills it in
        for section in (self.ppo, self.train, self.curriculum):
            section.check()
        assert self.model.arch is not None  # __post_init__ fills it in
        recurrent = self.model.arch.startswith("cnn-gru")
        if self.ppo.recurrence > 1 and not recurrent:
            raise ConfigError(f"ppo.recurrence={self.ppo.recurrence} needs a recurrent model.arch (cnn-gru-*), not {self.model.arch!r}")
        if self.curriculum.enabled and not self.env.world.curriculum:
            supported = ", ".join(w.name for w in worlds.registered() if w.curriculum)
            raise ConfigError(f"curriculum.enabled is only supported for {supported}, not env.name={self.env.name!r}")
        return self

    @classmethod
    def from_dict(cls, data: dict) -> "RunConfig":
        env = data.get("env") if isinstance(data, dict) else None
        name = env.get("name") if isinstance(env, dict) else None
        if isinstance(data.get("ppo") if isinstance(data, dict) else None, dict) and name in ENVS:
            # a partial ppo section fills in from the world's defaults, not another world's
            data = {**data, "ppo": {**dataclasses.asdict(default_ppo(name)), **data["ppo"]}}
        return _build(cls, data, "config").check()


def default_ppo(env_name: str) -> PPOConfig:
    """The world's PPO hyper-parameters (LavaWorld's table unless the world says otherwise)."""
    return PPOConfig(**(worlds.get(env_name).ppo if env_name in ENVS else {}))


def _build(cls, data, where: str):
    """Recursively build dataclass ``cls`` from ``data``, checking keys and scalar types."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where} must be a JSON object, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key {unknown[0]!r} (allowed: {', '.join(fields)})")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in data.items():
        kwargs[name] = _coerce(hints[name], value, f"{where}.{name}" if where != "config" else name)
    return cls(**kwargs)


def _coerce(hint, value, where: str):
    if dataclasses.is_dataclass(hint):
        return _build(hint, value, where)
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        options = [h for h in typing.get_args(hint) if h is not type(None)]
        if value is None:
            return None
        return _coerce(options[0], value, where)
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not (isinstance(value, int) or (isinstance(value, float) and value.is_integer())):
            raise ConfigError(f"{where} must be an integer, got {value!r}")
        return int(value)
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(f"{where} must be a finite number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {value!r}")
        return value
    return value
