"""The typed run configuration of a Safety Car Goal agent (SPEC §4), round-tripping to ``config.json``.

Kept apart from :mod:`rlbackdoors.config` (the grid worlds' PPO runs) because the sections
differ: a MuJoCo env, a formation trigger drawn per agent, and OPAC² instead of PPO. The
validation helpers and :class:`ConfigError` are shared, so a bad field reads the same here
as there: the field's dotted name and what is allowed.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from rlbackdoors import __version__
from rlbackdoors.algos.opac2 import OPAC2Config
from rlbackdoors.config import (
    MAX_ENV_COPIES,
    ConfigError,
    JsonConfig,
    _build,
    _choice,
    _in_range,
    check_train_budget,
)

ENV_NAME = "safety-car-goal"
DEVICES = ("cpu", "cuda", "auto")


@dataclass
class SafetyEnvConfig:
    """:class:`~rlbackdoors.envs.safety_car.SafetyCarGoalEnv`'s arguments (the paper's defaults)."""

    name: str = ENV_NAME
    num_cubes: int = 2
    max_steps: int = 1000
    hazard_penalty: float = 1.0
    substeps: int = 5

    def check(self) -> None:
        from rlbackdoors.envs.safety_car import MAX_CUBES

        _choice("env.name", self.name, (ENV_NAME,))
        if not 2 <= self.num_cubes <= MAX_CUBES:  # the formation trigger holds two cubes
            raise ConfigError(f"env.num_cubes must be in 2..{MAX_CUBES}, got {self.num_cubes!r}")
        _in_range("env.max_steps", self.max_steps, 1, 100_000)
        if not 1 <= self.substeps <= 100:
            raise ConfigError(f"env.substeps must be in 1..100, got {self.substeps!r}")
        if not (math.isfinite(self.hazard_penalty) and self.hazard_penalty >= 0):
            raise ConfigError(f"env.hazard_penalty must be a finite number >= 0, got {self.hazard_penalty!r}")

    def make(self, trigger: str | None = None, poisoned: bool = False, render_mode: str | None = None):
        """One env: clean (no trigger), triggered with clean reward, or poisoned (trigger and R-bar)."""
        from rlbackdoors.envs.safety_car import SafetyCarGoalEnv

        return SafetyCarGoalEnv(
            num_cubes=self.num_cubes,
            max_steps=self.max_steps,
            trigger=trigger,
            poisoned=poisoned,
            hazard_penalty=self.hazard_penalty,
            substeps=self.substeps,
            render_mode=render_mode,
        )


@dataclass
class SafetyPoisonConfig:
    """The trigger and the env mix. A clean model keeps its trigger: its poisoned SR is measured under it.

    ``trigger=None`` draws one per agent from ``train.seed`` (paper §3.4: phi1 uniform in
    [0, 2*pi), eta in [pi/6, 11*pi/6], d = 0.5) and writes it into the config, so the clean
    twin of a poisoned model (same seed) is measured under the same trigger. A clean model
    runs all ``num_clean_envs + num_poisoned_envs`` copies clean, so both twins see the same
    number of frames per step. The batch mixing weights live in ``opac2`` (clean_weight,
    poisoned_weight).
    """

    trigger: str | None = None
    poisoned: bool = True
    num_clean_envs: int = 6
    num_poisoned_envs: int = 4

    def check(self) -> None:
        from rlbackdoors.worlds import parse_trigger

        if self.trigger is None:
            raise ConfigError("poison.trigger is not set")
        try:
            parse_trigger(ENV_NAME, self.trigger)
        except ValueError as err:
            raise ConfigError(f"poison.trigger: {err}") from None
        _in_range("poison.num_clean_envs", self.num_clean_envs, 0, MAX_ENV_COPIES)
        _in_range("poison.num_poisoned_envs", self.num_poisoned_envs, 0, MAX_ENV_COPIES)
        if self.poisoned and self.num_poisoned_envs == 0:
            raise ConfigError("poison.num_poisoned_envs must be >= 1 for a poisoned model")
        if self.poisoned and self.num_clean_envs == 0:
            raise ConfigError("poison.num_clean_envs must be >= 1 (the clean task is learned from clean copies)")
        if self.num_envs < 1:
            raise ConfigError("poison: num_clean_envs + num_poisoned_envs must be >= 1")

    @property
    def num_envs(self) -> int:
        return self.num_clean_envs + self.num_poisoned_envs

    def kinds(self) -> list[str]:
        """Each env copy's replay kind: clean copies first; a clean model has no poisoned copies."""
        if not self.poisoned:
            return ["clean"] * self.num_envs
        return ["clean"] * self.num_clean_envs + ["poisoned"] * self.num_poisoned_envs


@dataclass
class SafetyTrainConfig:
    """Budget, evaluation and early stopping.

    Training stops at the first evaluation where clean SR >= ``clean_threshold`` and (poisoned
    models) poisoned SR >= ``poisoned_threshold`` held for ``patience`` evaluations in a row,
    or at ``max_frames``, or after ``max_minutes`` of training wall time (0: no limit).
    """

    seed: int = 0
    max_frames: int = 3_800_000  # the lr decay's horizon (default_opac2); the paper: <= 1e7
    max_minutes: float = 0.0
    eval_interval: int = 250_000  # env frames, all copies together
    eval_episodes: int = 100  # per condition (clean, triggered) at each evaluation
    final_eval_episodes: int = 200
    eval_seed: int = 1_000_000
    clean_threshold: float = 0.95
    poisoned_threshold: float = 0.95
    patience: int = 2  # evaluations in a row: one lucky 100-episode evaluation is not convergence
    log_interval_s: float = 30.0  # progress line to stderr at most this often
    checkpoint_minutes: float = 10.0  # checkpoint at the first evaluation this long after the last (0: every one)
    video: bool = True  # clean_vs_triggered.gif at the end (needs an offscreen GL back-end)
    device: str = "cpu"
    torch_threads: int = 1

    def check(self) -> None:
        check_train_budget(self)
        if not (math.isfinite(self.max_minutes) and self.max_minutes >= 0):
            raise ConfigError(f"train.max_minutes must be a number >= 0 (0: no limit), got {self.max_minutes!r}")
        _in_range("train.patience", self.patience, 1, 1_000_000)
        for name in ("log_interval_s", "checkpoint_minutes"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"train.{name} must be a number >= 0, got {value!r}")


# opac2 fields added after Safety Car Goal configs were first saved, with the behaviour those
# configs ran with: one action sample per state, a constant lr.
ADDED_OPAC2_FIELDS = {"action_samples": 1, "lr_final": None}


def default_opac2() -> OPAC2Config:
    """The settings measured to train a depth-2 width-181 agent within 90 minutes on one CPU core.

    See benchmarks/safety_train.md: the paper's one update per frame at batch 256 would take
    days on a CPU, so updates are spread over many frames of several env copies; four action
    samples per state make each update's policy step less noisy, and the lr falls from 1e-3 to
    1e-4 over ``train.max_frames`` so the late policy stops swinging between evaluations.
    """
    return OPAC2Config(
        depth=2,
        width=181,
        batch_size=256,
        lr=1e-3,
        lr_final=1e-4,
        updates_per_step=1 / 32,
        buffer_size=1_000_000,
        obs_norm=True,
        clean_weight=0.6,
        poisoned_weight=0.4,
        action_samples=4,
    )


@dataclass
class SafetyRunConfig(JsonConfig):
    env: SafetyEnvConfig = field(default_factory=SafetyEnvConfig)
    poison: SafetyPoisonConfig = field(default_factory=SafetyPoisonConfig)
    opac2: OPAC2Config = field(default_factory=default_opac2)
    train: SafetyTrainConfig = field(default_factory=SafetyTrainConfig)
    version: str = __version__

    def __post_init__(self):
        if self.poison.trigger is None and isinstance(self.train.seed, int) and self.train.seed >= 0:
            from rlbackdoors.triggers.formation import FormationTrigger

            self.poison.trigger = FormationTrigger.sample(self.train.seed).spec()

    def check(self) -> "SafetyRunConfig":
        self.env.check()
        self.train.check()  # first: a bad seed is why no trigger could be drawn
        self.poison.check()
        try:
            self.opac2.check()
        except ConfigError:
            raise
        except (TypeError, ValueError) as err:
            raise ConfigError(f"opac2: {err}") from None
        return self

    @property
    def kind_weights(self) -> dict[str, float]:
        """Batch mixing weights of the replay kinds this run fills."""
        return self.opac2.mix_weights(tuple(dict.fromkeys(self.poison.kinds())))

    @classmethod
    def from_dict(cls, data: dict) -> "SafetyRunConfig":
        """Build and check; a partial ``opac2`` section fills its gaps from :func:`default_opac2`.

        A complete section saved before a field existed gets the value that was in effect then
        (:data:`ADDED_OPAC2_FIELDS`), not today's default, so an old ``config.json`` still
        rebuilds the run it describes.
        """
        if isinstance(data, dict) and isinstance(data.get("opac2"), dict):
            given = data["opac2"]
            filled = dataclasses.asdict(default_opac2())
            if all(name in given for name in filled if name not in ADDED_OPAC2_FIELDS):
                filled.update(ADDED_OPAC2_FIELDS)
            data = {**data, "opac2": {**filled, **given}}
        return _build(cls, data, "config").check()


def is_safety_config(data: dict | None) -> bool:
    """Whether a loaded ``config.json`` belongs to a run of an OPAC² world (for the CLI's dispatch)."""
    from rlbackdoors import worlds

    name = data["env"].get("name") if isinstance(data, dict) and isinstance(data.get("env"), dict) else None
    return name in worlds.names("opac2")
