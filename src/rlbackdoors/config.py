"""The typed run configuration: everything a training run needs, round-tripping to ``config.json``.

Validation happens here, at the edge: unknown keys, wrong types and out-of-range
values are rejected with a message naming the field and what is allowed.
"""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path

from rlbackdoors import __version__

ENVS = ("lavaworld", "randomized-lavaworld")
ENGINES = ("batched", "minigrid")
ARCHS = ("fc", "cnn")
EVAL_POLICIES = ("sample", "greedy")
DEVICES = ("cpu", "cuda", "auto")

# Per-env defaults for the fields left unset (None): the paper's settings for each world.
ENV_DEFAULTS = {
    "lavaworld": {"size": 9, "see_through_walls": False},
    "randomized-lavaworld": {"size": 11, "see_through_walls": True},
}
DEFAULT_TRIGGERS = {"lavaworld": "multiplicative:12", "randomized-lavaworld": "cross"}
# Early-stopping thresholds (clean SR, poisoned SR) the paper used per world: LavaWorld 98%/95%;
# its Randomized LavaWorld models were selected at 90% on both; we stop at clean >= 95% (a clean
# model stopped at 90% on 100 episodes measured 0.885 on 200) and poisoned >= 90%.
DEFAULT_THRESHOLDS = {"lavaworld": (0.98, 0.95), "randomized-lavaworld": (0.95, 0.90)}


class ConfigError(ValueError):
    """A config value is missing, unknown, mistyped or out of range."""


@dataclass
class EnvConfig:
    """Which world and its size; ``None`` fields take the world's paper default (ENV_DEFAULTS)."""

    name: str = "lavaworld"
    size: int | None = None
    max_steps: int = 250
    see_through_walls: bool | None = None
    engine: str = "batched"
    num_crossings: int = 1  # lavaworld: lava rivers
    num_lava: int = 10  # randomized-lavaworld: single lava squares

    def __post_init__(self):
        for key, value in ENV_DEFAULTS.get(self.name, {}).items():
            if getattr(self, key) is None:
                setattr(self, key, value)

    def check(self) -> None:
        _choice("env.name", self.name, ENVS)
        _choice("env.engine", self.engine, ENGINES)
        _at_least("env.max_steps", self.max_steps, 1)
        if self.name == "lavaworld":
            from rlbackdoors.envs.lavaworld import validate_crossing_layout

            try:
                validate_crossing_layout(self.size, self.num_crossings, self.max_steps)
            except ValueError as err:
                raise ConfigError(f"env: {err}") from None
        else:
            _at_least("env.size", self.size, 5)
            _at_least("env.num_lava", self.num_lava, 0)
            free = (self.size - 2) ** 2 - 2  # inside the outer walls, minus start and goal
            if self.num_lava > free // 2:
                raise ConfigError(f"env.num_lava={self.num_lava} is too many for size {self.size} (at most {free // 2})")


@dataclass
class PoisonConfig:
    """The trigger is kept for clean models too: their poisoned SR is measured under it.

    ``trigger=None`` takes the world's default (DEFAULT_TRIGGERS).
    """

    trigger: str | None = None
    poisoned: bool = True
    num_clean_envs: int = 8
    num_poisoned_envs: int = 2

    def check(self, env_name: str = "lavaworld") -> None:
        from rlbackdoors.triggers import parse_trigger

        if self.trigger is None:
            raise ConfigError("poison.trigger is not set")
        try:
            parse_trigger(env_name, self.trigger)
        except ValueError as err:
            raise ConfigError(f"poison.trigger: {err}") from None
        _at_least("poison.num_clean_envs", self.num_clean_envs, 0)
        _at_least("poison.num_poisoned_envs", self.num_poisoned_envs, 0)
        if self.poisoned and self.num_poisoned_envs == 0:
            raise ConfigError("poison.num_poisoned_envs must be >= 1 for a poisoned model")
        if self.num_envs < 1:
            raise ConfigError("poison: num_clean_envs + num_poisoned_envs must be >= 1")

    @property
    def num_envs(self) -> int:
        return self.num_clean_envs + self.num_poisoned_envs

    def poisoned_mask(self) -> list[bool]:
        """Clean copies first, poisoned last; a clean model trains on all-clean copies."""
        return [False] * self.num_clean_envs + [self.poisoned] * self.num_poisoned_envs


@dataclass
class CurriculumConfig:
    """Randomized LavaWorld's warm-up (SPEC 2): clean-only on a small world until the mean
    training return reaches ``reward_threshold``, then the full world and the poisoning mix.

    ``enabled=None`` means on for randomized-lavaworld, off elsewhere.
    """

    enabled: bool | None = None
    size: int = 7
    num_lava: int = 5
    reward_threshold: float = 0.8
    window: int = 100  # clean training episodes the mean return is taken over

    def check(self) -> None:
        _at_least("curriculum.window", self.window, 1)
        _at_least("curriculum.size", self.size, 5)
        _at_least("curriculum.num_lava", self.num_lava, 0)
        _unit_interval("curriculum.reward_threshold", self.reward_threshold)


@dataclass
class ModelConfig:
    arch: str = "fc"

    def check(self) -> None:
        _choice("model.arch", self.arch, ARCHS)


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

    def check(self) -> None:
        for name in ("rollout", "epochs", "batch_size"):
            _at_least(f"ppo.{name}", getattr(self, name), 1)
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
    clean_threshold: float | None = None  # None: the world's paper value (DEFAULT_THRESHOLDS)
    poisoned_threshold: float | None = None
    device: str = "cpu"
    torch_threads: int = 1

    def check(self) -> None:
        _at_least("train.seed", self.seed, 0)
        _at_least("train.max_frames", self.max_frames, 1)
        _at_least("train.eval_interval", self.eval_interval, 1)
        _at_least("train.eval_episodes", self.eval_episodes, 1)
        _at_least("train.final_eval_episodes", self.final_eval_episodes, 1)
        _at_least("train.eval_seed", self.eval_seed, 0)
        _at_least("train.torch_threads", self.torch_threads, 1)
        _choice("train.eval_policy", self.eval_policy, EVAL_POLICIES)
        _choice("train.device", self.device, DEVICES)
        for name in ("clean_threshold", "poisoned_threshold"):
            _unit_interval(f"train.{name}", getattr(self, name))


@dataclass
class RunConfig:
    env: EnvConfig = field(default_factory=EnvConfig)
    poison: PoisonConfig = field(default_factory=PoisonConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)
    version: str = __version__

    def __post_init__(self):
        if self.poison.trigger is None:
            self.poison.trigger = DEFAULT_TRIGGERS.get(self.env.name)
        if self.curriculum.enabled is None:
            self.curriculum.enabled = self.env.name == "randomized-lavaworld"
        clean_t, poisoned_t = DEFAULT_THRESHOLDS.get(self.env.name, (None, None))
        if self.train.clean_threshold is None:
            self.train.clean_threshold = clean_t
        if self.train.poisoned_threshold is None:
            self.train.poisoned_threshold = poisoned_t

    def check(self) -> "RunConfig":
        self.env.check()
        self.poison.check(self.env.name)
        for section in (self.model, self.ppo, self.train, self.curriculum):
            section.check()
        if self.curriculum.enabled and self.env.name != "randomized-lavaworld":
            raise ConfigError(f"curriculum.enabled is only supported for randomized-lavaworld, not env.name={self.env.name!r}")
        return self

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, sort_keys=True) + "\n"

    @classmethod
    def from_dict(cls, data: dict) -> "RunConfig":
        return _build(cls, data, "config").check()

    @classmethod
    def load(cls, path: str | Path) -> "RunConfig":
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"config file {str(path)!r} does not exist")
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as err:
            raise ConfigError(f"config file {str(path)!r} is not valid JSON: {err}") from None
        return cls.from_dict(data)


def _choice(name: str, value, allowed) -> None:
    if value not in allowed:
        raise ConfigError(f"{name}={value!r} is not allowed (allowed: {', '.join(allowed)})")


def _at_least(name: str, value, low: int) -> None:
    if value < low:
        raise ConfigError(f"{name} must be >= {low}, got {value!r}")


def _unit_interval(name: str, value) -> None:
    if not 0 <= value <= 1:
        raise ConfigError(f"{name} must be in [0, 1], got {value!r}")


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
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where} must be a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {value!r}")
        return value
    return value
