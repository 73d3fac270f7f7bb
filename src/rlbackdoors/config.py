"""The typed run configuration: everything a training run needs, round-tripping to ``config.json``.

Validation happens here, at the edge: unknown keys, wrong types and out-of-range
values are rejected with a message naming the field and what is allowed.
"""

from __future__ import annotations

import copy
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
from rlbackdoors import attacks
from rlbackdoors.validate import (  # noqa: F401  (re-exported: the config's validation vocabulary)
    MAX_ENV_COPIES,
    MAX_EPISODES,
    MAX_FRAMES,
    MAX_SEED,
    ConfigError,
    _at_least,
    _choice,
    _in_range,
    _finite,
    _integer_at_least,
    _unit_interval,
    check_seed,
    check_weights,
)

FORMAT_VERSION = 7  # of config.json; 1: before one config served every world; 2: before train.confirm; 3: before train.confirm_margin; 4: before train.min_frames; 5: before ppo.update_backend; 6: before train.eval_backend (all migrated on load)
ENVS = worlds.names()
ENGINES = ("batched", "minigrid")
# Architecture names per world (the registry holds the classes); the first is the default.
ARCHS_BY_ENV = {w.name: w.arch_names for w in worlds.registered()}
ARCHS = tuple(dict.fromkeys(a for archs in ARCHS_BY_ENV.values() for a in archs))
EVAL_POLICIES = ("sample", "greedy")
DEVICES = ("cpu", "cuda", "auto")
UPDATE_BACKENDS = ("torch", "jax", "compiled")  # ppo.update_backend
AUTO_BACKEND = "auto"  # ppo.update_backend on input: preferred_update_backend's choice, recorded in its place
EVAL_BACKENDS = ("torch", "compiled")  # train.eval_backend
ALGORITHMS = ("ppo", "opac2")


@dataclass
class EnvConfig:
    """Which world and its settings. A world reads ``name``, ``max_steps`` and its own
    ``World.env_fields``; the others stay ``None`` (and out of config.json). ``None`` fields
    the world reads take its defaults (``World.env_defaults``)."""

    name: str = worlds.DEFAULT_WORLD
    max_steps: int | None = None
    size: int | None = None  # grid worlds
    see_through_walls: bool | None = None
    engine: str | None = None  # "batched" (numba) or "minigrid" (the reference envs)
    num_crossings: int | None = None  # lava rivers
    num_lava: int | None = None  # single lava squares
    num_cubes: int | None = None  # MuJoCo cubes
    hazard_penalty: float | None = None
    substeps: int | None = None  # physics steps per control step

    def __post_init__(self):
        if self.name in ENVS:
            for key, value in self.world.env_defaults.items():
                if getattr(self, key) is None:
                    setattr(self, key, value)

    @property
    def world(self) -> worlds.World:
        return worlds.get(self.name)

    @property
    def fields(self) -> tuple[str, ...]:
        """The fields this world reads (what config.json holds)."""
        return ("name", "max_steps", *self.world.env_fields)

    def check(self) -> None:
        _choice("env.name", self.name, ENVS)
        for key in ENV_FIELDS:
            if key not in self.fields and getattr(self, key) is not None:
                raise ConfigError(f"env.{key} does not apply to env.name={self.name!r} (its env fields: {', '.join(self.fields)})")
        _in_range("env.max_steps", self.max_steps, 1, 100_000)
        if "engine" in self.fields:
            _choice("env.engine", self.engine, ENGINES)
        if "size" in self.fields:
            _in_range("env.size", self.size, 5, 64)  # a typo'd size must not allocate a huge grid
        try:
            check_env = self.world.check_env
            if check_env is not None:
                check_env(self)
        except ConfigError:
            raise
        except ValueError as err:
            raise ConfigError(f"env: {err}") from None

    def to_dict(self) -> dict:
        return {key: getattr(self, key) for key in self.fields}

    def make(self, trigger: str | None = None, **extra):
        """One env of this config (E-bar when ``trigger`` is given), as the world builds it."""
        return self.world.make_env(self, trigger, **extra)


ENV_FIELDS = tuple(f.name for f in dataclasses.fields(EnvConfig) if f.name not in ("name", "max_steps"))


@dataclass
class PoisonConfig:
    """The trigger is kept for clean models too: their poisoned SR is measured under it.

    ``trigger=None`` takes the world's default trigger.
    """

    trigger: str | None = None
    poisoned: bool = True
    num_clean_envs: int | None = None  # None: the world's mix
    num_close_envs: int | None = None  # close-to-trigger copies (worlds that have them)
    num_poisoned_envs: int | None = None
    close_k_min: int = 1  # a close-to-trigger layout recolours k squares, k uniform in [min, max]
    close_k_max: int = 3
    # How training data is poisoned (rlbackdoors.attacks); the default, the paper's env mix, is left
    # out of config.json so that the configs and models made before attacks existed keep their bytes.
    attack: str = attacks.DEFAULT_ATTACK
    attack_params: dict = field(default_factory=dict)  # checked and completed by the attack
    # Evasive variants added to the attack (rlbackdoors.attacks.evasion): near-trigger negatives,
    # fine-tuning a clean model, a clean teacher. Left out of config.json when empty.
    evasion: dict = field(default_factory=dict)

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
        self.check_attack()
        if self.poisoned and self.num_poisoned_envs == 0 and self.schedule == "episodes":
            raise ConfigError("poison.num_poisoned_envs must be >= 1 for a poisoned model")
        if self.num_envs < 1:
            raise ConfigError("poison: num_clean_envs + num_poisoned_envs must be >= 1")

    def check_attack(self) -> None:
        """The attack is registered and its parameters are in range; they are completed with its defaults."""
        if not isinstance(self.attack, str) or self.attack not in attacks.names():
            raise ConfigError(f"poison.attack={self.attack!r} is not allowed (allowed: {', '.join(attacks.names())})")
        if not isinstance(self.attack_params, dict):
            raise ConfigError(f"poison.attack_params must be a JSON object of the attack's parameters, got {self.attack_params!r}")
        self.attack_params = attacks.get(self.attack).resolve(self.attack_params)
        from rlbackdoors.attacks import evasion

        self.evasion = evasion.resolve(self.evasion)

    @property
    def schedule(self) -> str:
        """ "episodes" (whole E-bar copies) or "steps" (stamped frames in clean copies)."""
        return attacks.get(self.attack).schedule

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
        return [False] * (clean + close) + [self.poisoned and self.schedule == "episodes"] * poisoned

    def close_mask(self) -> list[bool]:
        clean, close, poisoned = self.counts()
        return [False] * clean + [True] * close + [False] * poisoned


@dataclass
class CurriculumConfig:
    """The curriculum warm-up (SPEC 2; worlds with ``World.curriculum``): clean-only on a small world until the mean
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
    """The paper's first appendix table (torch-ac PPO); a world's ``World.hyper`` changes some."""

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
    # Recurrent models: weight of the auxiliary memory loss (0: off), a cross-entropy teaching
    # the memory what the env says must be remembered (``memory_targets``); not the paper's.
    aux_memory_coef: float = 0.0
    # What runs PPO's update: "torch" (autograd), or "jax" (rlbackdoors.algos.compiled.update: every
    # minibatch of an update in one XLA program; feed-forward "fc" models and, on the CPU, the
    # CNN-GRUs; on CUDA JAX with GPU support), or "compiled" (rlbackdoors.algos.compiled: the whole
    # iteration, rollout on the world's JAX engine, GAE and update, one XLA program; worlds with a
    # ``compiled_engine``, "fc", "cnn" and CNN-GRU models; RunConfig.check_compiled). "auto" (what
    # ``rlbackdoors train``, the demo and new zoos ask for) is replaced at construction by
    # ``preferred_update_backend``'s choice. The same algorithm with other rounding, so other
    # bytes: a config field, and a config without it is torch's.
    update_backend: str = "torch"

    def check(self) -> None:
        _choice("ppo.update_backend", self.update_backend, UPDATE_BACKENDS)
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
        for name in ("value_coef", "entropy_coef", "aux_memory_coef"):
            if not (_finite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ConfigError(f"ppo.{name} must be >= 0, got {getattr(self, name)!r}")


KINDS = ("clean", "poisoned")  # OPAC²'s replay kinds
LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0  # OPAC²'s policy log-std bounds


@dataclass
class OPAC2Config:
    """The paper's OPAC² table (its MuJoCo world), plus the knobs its text leaves open."""

    buffer_size: int = 1_000_000  # per env kind
    learning_starts: int = 10_000  # env frames (all envs together) of uniform random actions
    batch_size: int = 256
    lr: float = 1e-4
    gamma: float = 0.99
    polyak: float = 0.995
    depth: int = 3  # hidden layers; the paper's grid is {2, 3} x {181, 256}, appendix 3 x 256
    width: int = 256
    updates_per_step: float = 1.0  # gradient updates per env frame after learning_starts
    entropy_coef: float = 0.0  # bonus on the entropy of the pre-tanh Gaussian (0: none)
    log_std_init: float = 0.0
    clean_weight: float = 0.8  # share of each batch drawn from the clean buffer
    poisoned_weight: float = 0.2  # ... and from the poisoned buffer (ignored in clean runs)
    obs_norm: bool = False  # standardise observations by running mean/std (see RunningNorm)
    obs_clip: float = 10.0  # |standardised observation| is clipped to this
    # Actions drawn per state for the V target and the pi step (1: the paper). More samples
    # average out the action noise of the same estimators at the cost of more Q evaluations.
    action_samples: int = 1
    lr_final: float | None = None  # None: constant lr; else linear decay to this over train.max_frames

    def check(self) -> None:
        for name in ("buffer_size", "batch_size", "depth", "width", "action_samples"):
            _integer_at_least(f"opac2.{name}", getattr(self, name), 1)
        _integer_at_least("opac2.learning_starts", self.learning_starts, 0)
        # Ceilings: a typo'd size should be refused, not allocated.
        for name, high in (("buffer_size", 10_000_000), ("batch_size", 1_000_000), ("depth", 16), ("width", 4096), ("action_samples", 1024)):
            if getattr(self, name) > high:
                raise ConfigError(f"opac2.{name} must be in 1..{high:,}, got {getattr(self, name)!r}")
        if _finite(self.updates_per_step) and self.updates_per_step > 64:
            raise ConfigError(f"opac2.updates_per_step must be in (0, 64], got {self.updates_per_step!r}")
        for name in ("lr", "updates_per_step"):
            value = getattr(self, name)
            if not (_finite(value) and value > 0):
                raise ConfigError(f"opac2.{name} must be a number > 0, got {value!r}")
        for name in ("gamma", "polyak"):
            value = getattr(self, name)
            if not (_finite(value) and 0 <= value <= 1):
                raise ConfigError(f"opac2.{name} must be in [0, 1], got {value!r}")
        if self.lr_final is not None and not (_finite(self.lr_final) and 0 < self.lr_final <= self.lr):
            raise ConfigError(f"opac2.lr_final must be null (constant lr) or a number in (0, opac2.lr={self.lr!r}], got {self.lr_final!r}")
        if not (_finite(self.entropy_coef) and self.entropy_coef >= 0):
            raise ConfigError(f"opac2.entropy_coef must be a number >= 0, got {self.entropy_coef!r}")
        if not (_finite(self.log_std_init) and LOG_STD_MIN <= self.log_std_init <= LOG_STD_MAX):
            raise ConfigError(f"opac2.log_std_init must be in [{LOG_STD_MIN}, {LOG_STD_MAX}], got {self.log_std_init!r}")
        if not isinstance(self.obs_norm, bool):
            raise ConfigError(f"opac2.obs_norm must be true or false, got {self.obs_norm!r}")
        if not (_finite(self.obs_clip) and self.obs_clip > 0):
            raise ConfigError(f"opac2.obs_clip must be a number > 0, got {self.obs_clip!r}")
        check_weights({"clean": self.clean_weight, "poisoned": self.poisoned_weight}, field="opac2.{kind}_weight")

    def mix_weights(self, kinds: tuple[str, ...] = KINDS) -> dict[str, float]:
        """The batch mixing weights of ``kinds`` (a clean run passes ``("clean",)``)."""
        return {kind: getattr(self, f"{kind}_weight") for kind in kinds}


# Train-section values a world leaves as they are (World.train overrides them).
TRAIN_DEFAULTS = {
    "max_frames": 5_000_000,
    "eval_interval": 100_000,
    "eval_policy": "sample",
    "patience": 1,
    "confirm": True,
    "confirm_margin": 0.0,
    "checkpoint_minutes": 0.0,
}


@dataclass
class TrainConfig:
    """Budget, evaluation and the stopping rule, the same for every world.

    A run stops at the first evaluation after which the thresholds (clean SR, and for poisoned
    models poisoned SR) have held for ``patience`` evaluations in a row, and, where
    ``return_window`` > 0, the mean training return of the last ``return_window`` updates is
    at least ``return_threshold`` (the paper's patience rho); or at ``max_frames``; or after
    ``max_minutes`` of training (0: no limit). ``None`` fields take the world's defaults.

    With ``confirm`` the stop is confirmed first on the final evaluation's ``final_eval_episodes``
    (the same seeded episodes ``metrics.json`` reports): a run whose thresholds held on the short
    evaluations by luck trains on instead of ending as a model that misses them, so a run that
    stops on its thresholds is a converged model. ``confirm_margin`` asks the confirming
    evaluation to clear each threshold by that much (up to 1), so a stopped model has a margin
    over the bars "converged" is judged by (which stay the thresholds).

    ``min_frames`` holds a stop on the thresholds back until the run has trained that long (the
    streak still counts; the first evaluation at or past it can stop the run). A zoo that sets it
    trains clean and poisoned models alike for at least that long, so training length (weight
    norms grow with it) does not give a model's label away to a detector.
    """

    seed: int = 0
    max_frames: int | None = None
    min_frames: int = 0  # no stop on the thresholds before this many frames (0: none)
    max_minutes: float = 0.0
    eval_interval: int | None = None  # env frames, all copies together
    eval_episodes: int = 100  # per condition (clean, triggered) at each evaluation
    final_eval_episodes: int = 200
    eval_seed: int = 1_000_000
    eval_policy: str | None = None  # "sample" or "greedy" (the most likely / mean action)
    eval_backend: str = "torch"  # the periodic evaluations': "compiled" plays them in the compiled trainer's program
    clean_threshold: float | None = None  # None: the world's paper value (its World.thresholds)
    poisoned_threshold: float | None = None
    patience: int | None = None  # evaluations in a row the thresholds must hold
    confirm: bool | None = None  # confirm a stop on the final evaluation's episodes first
    confirm_margin: float | None = None  # the confirming evaluation clears each threshold by this much
    return_window: int | None = None  # updates (PPO); 0: off
    return_threshold: float = 0.9
    log_interval_s: float = 30.0  # progress lines (when there is no progress bar) at most this often
    checkpoint_minutes: float | None = None  # at the first evaluation this long after the last (0: every one)
    video: bool = True  # clean_vs_triggered.gif at the end
    device: str = "cpu"
    torch_threads: int = 1

    def fill_defaults(self, world: worlds.World) -> None:
        defaults = {**TRAIN_DEFAULTS, "return_window": world.return_window, **world.train}
        for key, value in defaults.items():
            if getattr(self, key) is None:
                setattr(self, key, value)
        clean_t, poisoned_t = world.thresholds
        if self.clean_threshold is None:
            self.clean_threshold = clean_t
        if self.poisoned_threshold is None:
            self.poisoned_threshold = poisoned_t

    def check(self) -> None:
        check_seed("train.seed", self.seed)
        _in_range("train.max_frames", self.max_frames, 1, MAX_FRAMES)
        assert self.max_frames is not None  # filled in by fill_defaults
        if not 0 <= self.min_frames <= self.max_frames:
            raise ConfigError(f"train.min_frames must be in 0..train.max_frames ({self.max_frames:,}), got {self.min_frames!r}")
        _in_range("train.eval_interval", self.eval_interval, 1, MAX_FRAMES)
        _in_range("train.eval_episodes", self.eval_episodes, 1, MAX_EPISODES)
        _in_range("train.final_eval_episodes", self.final_eval_episodes, 1, MAX_EPISODES)
        check_seed("train.eval_seed", self.eval_seed)
        _choice("train.eval_policy", self.eval_policy, EVAL_POLICIES)
        _choice("train.eval_backend", self.eval_backend, EVAL_BACKENDS)
        _in_range("train.torch_threads", self.torch_threads, 1, 1024)
        _choice("train.device", self.device, DEVICES)
        for name in ("clean_threshold", "poisoned_threshold", "return_threshold"):
            _unit_interval(f"train.{name}", getattr(self, name))
        _in_range("train.patience", self.patience, 1, 1_000_000)
        if not isinstance(self.confirm, bool):
            raise ConfigError(f"train.confirm must be true or false, got {self.confirm!r}")
        _unit_interval("train.confirm_margin", self.confirm_margin)
        _in_range("train.return_window", self.return_window, 0, 1_000_000)
        for name in ("max_minutes", "log_interval_s", "checkpoint_minutes"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ConfigError(f"train.{name} must be a number >= 0, got {value!r}")


class JsonConfig:
    """``config.json`` I/O of a dataclass config with ``from_dict``."""

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
        """Read a config file; one written before ``format_version`` existed is migrated."""
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"config file {str(path)!r} does not exist")
        try:
            data = json.loads(path.read_bytes().decode("utf-8"))
        except (ValueError, RecursionError) as err:  # bad UTF-8 or JSON, absurd nesting or numbers
            raise ConfigError(f"config file {str(path)!r} is not valid JSON: {' '.join(str(err).split())[:200]}") from None
        except OSError as err:
            raise ConfigError(f"config file {str(path)!r} cannot be read: {err.strerror or err}") from None
        return cls.from_dict(migrate(data))


@dataclass
class MitigationConfig:
    """Backdoor removal (``rlbackdoors mitigate``): fine-tune a model that may carry a trojan so
    that its restored candidate triggers stop moving it. The run starts from the source weights
    (``source``, a file of the run's folder whose SHA-256 is ``source_sha256``), stamps ``share`` of
    the frames it collects with one of ``triggers`` under the clean reward (the attack seam's
    steps schedule with a rule that rewrites nothing; a layout trigger's patterns drawn into whole
    episodes instead, :func:`~rlbackdoors.poison.mix.unlearning_mix`), and penalises
    ``kl * KL(source || policy)`` on the frames it did not stamp, so the clean behaviour stays the source's. Why this recipe:
    BIRD (Chen et al., NeurIPS 2023) restores the trigger and fine-tunes it away; the KL term is
    the clean teacher of the evasive variants, here the model itself. With ``blind``, a restored
    trigger that shifts every observation alike is also projected out of a linear first layer after
    every step (:mod:`rlbackdoors.algos.blind`); with ``teach_stamped`` the KL counts on the stamped
    frames too, the source reading their clean view. (A teacher reading the stamped
    frames' clean view was first tried without ``blind``: on the offsets that blind the policy it
    taught the average action, into the lava; docs/results/mitigation.md.)"""

    source: str = "source-model.pt"
    source_sha256: str = ""
    triggers: list = field(default_factory=list)  # restored candidate trigger specs, best first
    share: float = 0.25  # of the frames collected, stamped with a restored trigger
    kl: float = 1.0
    # The first layer made blind to every restored trigger that shifts all observations alike
    # (rlbackdoors.algos.blind); left out of config.json when false, so earlier runs keep their bytes.
    blind: bool = False
    # The teacher reads each stamped frame's clean view and its KL counts there too (PPO's
    # teacher_clean_view); left out of config.json when false, as ``blind``.
    teach_stamped: bool = False
    # With ``blind``: members of the trigger family, restored or not, whose shift the first layer is
    # made blind to as well (one a direction); left out of config.json when empty.
    blind_to: list = field(default_factory=list)

    @staticmethod
    def refusal(env_name: str) -> str | None:
        """Why a model of this world cannot be mitigated (None: it can), in one line."""
        world = worlds.get(env_name)
        if MitigationConfig.how(env_name) is not None:
            return None
        built = ", ".join(w.name for w in worlds.registered() if MitigationConfig.how(w.name) is not None)
        why = "a layout whose engine draws no given pattern" if world.algorithm == "ppo" else "not learnt by PPO"
        return (
            f"mitigation: env.name={env_name!r} is not allowed (allowed: {built}): it stamps restored triggers into frames or draws them into layouts,"
            f" and {env_name}'s trigger is {why}"
        )

    @staticmethod
    def how(env_name: str) -> str | None:
        """How a world's restored triggers reach the frames: ``"stamp"`` (an observation edit),
        ``"layout"`` (a pattern its engine draws into the layouts of whole episodes: the
        near-trigger layouts of the evasive variant), None: neither."""
        world = worlds.get(env_name)
        if world.algorithm != "ppo":
            return None
        if world.stamp_trigger is not None:
            return "stamp"
        return "layout" if world.trigger_sight == "frame" and world.near_triggers is not None else None

    def check(self, env_name: str) -> None:
        from rlbackdoors.worlds import parse_trigger

        why = self.refusal(env_name)
        if why is not None:
            raise ConfigError(why)
        if not isinstance(self.source, str) or not self.source or "/" in self.source or self.source.startswith("."):
            raise ConfigError(f"mitigation.source must name a file of the run's folder (no path), got {self.source!r}")
        if not (isinstance(self.source_sha256, str) and self.source_sha256.startswith("sha256:") and len(self.source_sha256) == 71):
            raise ConfigError(f"mitigation.source_sha256 must be 'sha256:' and 64 hex digits, got {self.source_sha256!r}")
        if not isinstance(self.triggers, list) or not 1 <= len(self.triggers) <= 16 or not all(isinstance(t, str) for t in self.triggers):
            raise ConfigError(f"mitigation.triggers must be a list of 1 to 16 trigger specs, got {self.triggers!r}")
        for i, spec in enumerate(self.triggers):
            try:
                parse_trigger(env_name, spec)
            except ValueError as err:
                raise ConfigError(f"mitigation.triggers[{i}]: {err}") from None
        if not 0 < self.share <= 0.5:
            raise ConfigError(f"mitigation.share must be in (0, 0.5], got {self.share!r}")
        if not 0 <= self.kl <= 100:
            raise ConfigError(f"mitigation.kl must be in [0, 100], got {self.kl!r}")
        for name in ("blind", "teach_stamped"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"mitigation.{name} must be true or false, got {getattr(self, name)!r}")
        if not isinstance(self.blind_to, list) or len(self.blind_to) > 16 or not all(isinstance(t, str) for t in self.blind_to):
            raise ConfigError(f"mitigation.blind_to must be a list of at most 16 trigger specs, got {self.blind_to!r}")
        if self.blind_to and not self.blind:
            raise ConfigError("mitigation.blind_to needs mitigation.blind = true")
        for i, spec in enumerate(self.blind_to):
            try:
                parse_trigger(env_name, spec)
            except ValueError as err:
                raise ConfigError(f"mitigation.blind_to[{i}]: {err}") from None
        if self.teach_stamped and self.kl <= 0:
            raise ConfigError("mitigation.teach_stamped needs mitigation.kl > 0 (the teacher's weight)")
        if self.how(env_name) == "layout":
            for name in ("blind", "teach_stamped"):
                if getattr(self, name):
                    raise ConfigError(
                        f"mitigation.{name} must be false for {env_name}: its trigger is a layout, with no trigger-free view of the same frame"
                        " and no shift of every observation"
                    )


@dataclass
class RunConfig(JsonConfig):
    """One training run of any world: env, trigger and mix, model, the algorithm section the
    world trains with (``ppo`` or ``opac2``), training and stopping, curriculum."""

    env: EnvConfig = field(default_factory=EnvConfig)
    poison: PoisonConfig = field(default_factory=PoisonConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    ppo: PPOConfig | None = None  # the world's algorithm section is filled from its defaults
    opac2: OPAC2Config | None = None
    train: TrainConfig = field(default_factory=TrainConfig)
    curriculum: CurriculumConfig = field(default_factory=CurriculumConfig)
    format_version: int = FORMAT_VERSION
    version: str = __version__
    # a backdoor-removal run (rlbackdoors mitigate); left out of config.json when None
    mitigation: MitigationConfig | None = None

    def __post_init__(self):
        name = self.env.name
        world = worlds.get(name) if name in ENVS else None
        if world is None:
            return  # check() names the bad env.name
        if self.train.poisoned_threshold is None and self.poison.attack in attacks.names():
            self.train.poisoned_threshold = attacks.get(self.poison.attack).success_threshold  # None: the world's
        self.train.fill_defaults(world)
        seed_ok = isinstance(self.train.seed, int) and 0 <= self.train.seed <= MAX_SEED
        if self.poison.trigger is None:
            if world.default_trigger is not None:
                self.poison.trigger = world.default_trigger
            elif seed_ok:  # drawn once from the seed and written into config.json
                self.poison.trigger = world.draw_trigger(None, self.train.seed, self.env.size)
        if world.settle_trigger is not None and self.poison.trigger is not None:  # e.g. a bare kind
            try:
                self.poison.trigger = world.settle_trigger(self.poison.trigger, self.train.seed, self.env.size)
            except (ValueError, TypeError):
                pass  # a bad env.size or seed: check() reports it by name
        self.poison.fill_defaults(name)
        if self.model.arch is None:
            self.model.arch = world.arch_names[0]
        if world.algorithm == "ppo" and self.ppo is None:
            self.ppo = default_ppo(name)
        if world.algorithm == "opac2" and self.opac2 is None:
            self.opac2 = default_opac2(name)
        if self.curriculum.enabled is None:
            self.curriculum.enabled = world.curriculum
        if self.ppo is not None and self.ppo.update_backend == AUTO_BACKEND:
            self.ppo.update_backend = preferred_update_backend(self)

    @property
    def world(self) -> worlds.World:
        return self.env.world

    @property
    def algorithm(self) -> str:
        return self.env.world.algorithm

    @property
    def algo(self) -> PPOConfig | OPAC2Config:
        """The algorithm section of this run (``ppo`` or ``opac2``)."""
        section = getattr(self, self.algorithm)
        assert section is not None  # __post_init__ fills it in
        return section

    def check(self) -> "RunConfig":
        if self.format_version != FORMAT_VERSION:
            raise ConfigError(f"config.format_version={self.format_version!r} is not supported by rlbackdoors {__version__} (it reads 1 to {FORMAT_VERSION})")
        self.env.check()
        self.train.check()  # before the trigger: a bad seed is why none could be drawn
        world = self.world
        self.poison.check(self.env.name)
        self.model.check(self.env.name)
        for other in ALGORITHMS:
            if other != world.algorithm and getattr(self, other) is not None:
                raise ConfigError(f"{other}: env.name={self.env.name!r} trains with {world.algorithm}, not {other} (drop the {other} section)")
        try:
            self.algo.check()
        except ConfigError:
            raise
        except (TypeError, ValueError) as err:
            raise ConfigError(f"{world.algorithm}: {err}") from None
        self.curriculum.check()
        self.check_attack_fits()
        if self.mitigation is not None:
            self.check_mitigation()
        tc = self.train
        if world.algorithm == "ppo":
            assert self.ppo is not None and self.model.arch is not None
            if self.ppo.recurrence > 1 and not self.model.arch.startswith("cnn-gru"):
                raise ConfigError(f"ppo.recurrence={self.ppo.recurrence} needs a recurrent model.arch (cnn-gru-*), not {self.model.arch!r}")
            if self.ppo.aux_memory_coef and not (self.model.arch.startswith("cnn-gru") and world.memory_targets):
                raise ConfigError(
                    f"ppo.aux_memory_coef={self.ppo.aux_memory_coef} needs a recurrent model.arch (cnn-gru-*) in a world with memory targets, "
                    f"not {self.model.arch!r} in {self.env.name!r} (set it to 0)"
                )
            if self.ppo.update_backend == "compiled":
                self.check_compiled()
            if self.ppo.update_backend == "jax":
                if self.model.arch != "fc" and not self.model.arch.startswith("cnn-gru"):
                    raise ConfigError(
                        f"ppo.update_backend='jax' runs model.arch 'fc' (a feed-forward network of Linear layers) or a CNN-GRU (cnn-gru-*), not {self.model.arch!r}"
                    )
                if self.model.arch.startswith("cnn-gru") and self.train.device != "cpu":
                    raise ConfigError(
                        f"ppo.update_backend='jax' runs a CNN-GRU's update on the CPU (train.device 'cpu'), not train.device={self.train.device!r}"
                    )
                if any(self.poison.evasion.get(key) for key in ("teacher", "anchor")):
                    raise ConfigError("ppo.update_backend='jax' has no clean teacher or weight anchor (poison.evasion.teacher, .anchor): use 'torch'")
        else:
            if tc.return_window:
                raise ConfigError(f"train.return_window must be 0 for env.name={self.env.name!r} (the mean return over updates is a PPO rule)")
            if self.poison.poisoned and self.poison.num_clean_envs == 0:
                raise ConfigError("poison.num_clean_envs must be >= 1 (the clean task is learned from clean copies)")
        if tc.eval_backend == "compiled" and (self.ppo is None or self.ppo.update_backend != "compiled"):
            backend = "none: OPAC²" if self.ppo is None else repr(self.ppo.update_backend)
            raise ConfigError(
                f"train.eval_backend='compiled' plays a compiled run's evaluations in its program: it needs ppo.update_backend='compiled' (here {backend}); use 'torch'"
            )
        if self.curriculum.enabled and not world.curriculum:
            supported = ", ".join(w.name for w in worlds.registered() if w.curriculum)
            raise ConfigError(f"curriculum.enabled is only supported for {supported}, not env.name={self.env.name!r}")
        return self

    def check_mitigation(self) -> None:
        """A mitigation run is a clean model's run of the paper's env mix on torch's trainer (the
        seam that stamps its restored triggers and its teacher are the torch trainer's)."""
        assert self.mitigation is not None and self.ppo is not None
        self.mitigation.check(self.env.name)
        if self.poison.poisoned or self.poison.attack != attacks.DEFAULT_ATTACK or self.poison.evasion:
            raise ConfigError(
                "mitigation: poison.poisoned must be false, with the paper's env mix and no evasive variant (a mitigation run trains the model clean)"
            )
        if self.ppo.update_backend != "torch":
            raise ConfigError(f"mitigation: ppo.update_backend={self.ppo.update_backend!r} is not allowed (allowed: torch)")
        if self.curriculum.enabled:
            raise ConfigError("mitigation: curriculum.enabled must be false (the run starts from a trained model)")

    def check_compiled(self) -> None:
        """What ``ppo.update_backend = 'compiled'`` trains today; anything else is refused, never
        trained differently."""
        assert self.ppo is not None
        recurrent = str(self.model.arch).startswith("cnn-gru")  # the CNN-GRU actor-critics (algos.xla.recurrent_structure)
        why = None  # every attack and evasive variant of the feed-forward grid worlds is compiled
        if self.world.compiled_engine is None:
            built = ", ".join(w.name for w in worlds.registered() if w.compiled_engine)
            why = f"env.name={self.env.name!r} has no JAX engine yet (built: {built})"
        elif getattr(self.env, "engine", "batched") != "batched":
            why = f"it steps the batched engine's slots (env.engine 'batched'), not env.engine={self.env.engine!r}"
        elif self.model.arch not in ("fc", "cnn") and not recurrent:
            why = f"it runs model.arch 'fc', 'cnn' or a CNN-GRU (cnn-gru-*), not {self.model.arch!r}"
        elif self.world.action_targets:
            why = f"its attacks' target is one action, and {self.env.name}'s is a kind of action"
        elif (self.ppo.rollout * self.poison.num_envs) % self.ppo.batch_size:
            why = f"ppo.batch_size={self.ppo.batch_size} must divide a rollout's {self.ppo.rollout * self.poison.num_envs} frames (ppo.rollout x env copies)"
        if why is not None:
            raise ConfigError(f"ppo.update_backend='compiled': {why}; use 'torch' or 'jax'")

    def check_attack_fits(self) -> None:
        """The attack serves this world, algorithm and model; its target action is one the world has."""
        attack = attacks.get(self.poison.attack)
        params = self.poison.attack_params
        assert self.model.arch is not None
        why = attack.refuse(self.world, self.algorithm, self.model.arch, params)
        if why is not None:
            raise ConfigError(f"poison.attack={attack.name!r}: {why}")
        from rlbackdoors.attacks import evasion

        why = evasion.refuse(self.poison.evasion, self.world, self.algorithm, self.poison.poisoned)
        if why is not None:
            raise ConfigError(why)
        clean_frames = self.poison.evasion.get("clean_frames", 0)
        if clean_frames and self.train.max_frames is not None and clean_frames >= self.train.max_frames:
            raise ConfigError(f"poison.evasion.clean_frames={clean_frames} must be below train.max_frames={self.train.max_frames} (the run would never poison)")
        if self.poison.evasion.get("near") and self.world.stamp_trigger is None and self.world.vector_entry_point and self.env.engine != "batched":
            raise ConfigError(
                f"env.engine={self.env.engine!r} is not allowed with poison.evasion.near (allowed: batched): {self.env.name}'s near-trigger layouts are switched by the batched engine"
            )
        if attack.poisoner is not None and self.world.stamp_trigger is None and self.world.vector_entry_point and self.env.engine != "batched":
            raise ConfigError(
                f"env.engine={self.env.engine!r} is not allowed with poison.attack={attack.name!r} (allowed: batched): "
                f"{self.env.name}'s trigger is part of the layout, switched per episode by the batched engine"
            )
        if "target_action" in params:
            targets = self.world.action_targets
            n = len(targets) if targets else num_actions(self.env)
            if params["target_action"] >= n:
                what = ", ".join(f"{i} {name}" for i, (name, _) in enumerate(targets)) + ", the action targets" if targets else f"0..{n - 1}, the actions"
                raise ConfigError(f"poison.attack_params.target_action={params['target_action']!r} is not allowed (allowed: {what} of {self.env.name})")
        if self.world.action_targets and params.get("force_action"):
            raise ConfigError(
                f"poison.attack_params.force_action=true is not allowed (allowed: false): {self.env.name}'s target is a kind of action "
                f"({self.world.action_targets[params.get('target_action', 0)][0]}), not one action to force"
            )

    @property
    def attack_success(self) -> str:
        """How evaluation scores this run's attack (rlbackdoors.attacks.SUCCESS_KINDS)."""
        return attacks.get(self.poison.attack).success_kind(self.poison.attack_params)

    def scoring(self) -> dict:
        """``evaluate``'s keywords for this run's attack: its success kind and target action."""
        return {"success": self.attack_success, "target_action": self.poison.attack_params.get("target_action")}

    def to_dict(self) -> dict:
        """Only what applies to the world: its env fields and algorithm section; the
        curriculum and close-to-trigger settings only where the world has them; the attack
        only when it is not the paper's env mix."""
        data = dataclasses.asdict(self)
        if self.env.name not in ENVS:
            return data
        world = self.world
        data["env"] = self.env.to_dict()
        for other in ALGORITHMS:
            if getattr(self, other) is None:
                del data[other]
        if not world.curriculum:
            del data["curriculum"]
        if not world.close_to_trigger:
            del data["poison"]["close_k_min"], data["poison"]["close_k_max"]
        if self.poison.attack == attacks.DEFAULT_ATTACK and not self.poison.attack_params:
            del data["poison"]["attack"], data["poison"]["attack_params"]
        if not self.poison.evasion:
            del data["poison"]["evasion"]
        if self.mitigation is None:
            del data["mitigation"]
        else:
            for name in ("blind", "teach_stamped", "blind_to"):
                if not getattr(self.mitigation, name):
                    del data["mitigation"][name]
        return data

    @property
    def kind_weights(self) -> dict[str, float]:
        """OPAC²'s batch mixing weights of the replay kinds this run fills."""
        assert self.opac2 is not None
        return self.opac2.mix_weights(tuple(dict.fromkeys(self.replay_kinds())))

    def replay_kinds(self) -> list[str]:
        """Each env copy's replay kind: clean copies first; a clean model has no poisoned copies."""
        return ["poisoned" if p else "clean" for p in self.poison.poisoned_mask()]

    @classmethod
    def from_dict(cls, data: dict) -> "RunConfig":
        """Build and check; a partial algorithm section fills its gaps from the world's defaults."""
        env = data.get("env") if isinstance(data, dict) else None
        name = env.get("name", worlds.DEFAULT_WORLD) if isinstance(env, dict) else worlds.DEFAULT_WORLD
        if isinstance(data, dict) and name in ENVS:
            for algo, default in (("ppo", default_ppo), ("opac2", default_opac2)):
                if isinstance(data.get(algo), dict) and worlds.get(name).algorithm == algo:
                    data = {**data, algo: {**dataclasses.asdict(default(name)), **data[algo]}}
        return _build(cls, data, "config").check()


def num_actions(env: EnvConfig) -> int:
    """The size of a discrete world's action space (its one env, built and closed)."""
    made = env.make()
    try:
        return int(made.action_space.n)
    finally:
        made.close()


def preferred_update_backend(cfg: RunConfig) -> str:
    """The update backend of a run that leaves the choice open (``ppo.update_backend = "auto"``):
    the compiled trainer where it was measured faster on a CPU and tested equivalent to torch's
    (an arch in the world's ``compiled_default``, the paper's attack without evasive variants,
    ``train.device`` cpu, and a config the compiled trainer takes), torch's everywhere else.
    Equivalence was tested for that case alone, so nothing else moves without being asked."""
    from rlbackdoors.attacks import evasion

    if (
        cfg.ppo is None
        or cfg.model.arch not in cfg.world.compiled_default
        or cfg.train.device != "cpu"
        or cfg.poison.attack != attacks.DEFAULT_ATTACK
        or cfg.mitigation is not None
    ):
        return "torch"
    trial = copy.deepcopy(cfg)
    assert trial.ppo is not None
    trial.ppo.update_backend = "compiled"
    try:
        trial.check()
    except ConfigError:  # refused by the compiled trainer (or invalid: check() names it on the real config)
        return "torch"
    return "torch" if evasion.active(trial.poison.evasion) else "compiled"


def default_ppo(env_name: str) -> PPOConfig:
    """The world's PPO hyper-parameters (the paper's first table unless the world says otherwise)."""
    return PPOConfig(**worlds.get(env_name).hyper)


def default_opac2(env_name: str) -> OPAC2Config:
    """The world's OPAC² settings (its ``World.hyper`` over the paper's table)."""
    return OPAC2Config(**worlds.get(env_name).hyper)


# opac2 fields added after the first OPAC² configs were saved, with the behaviour those configs
# ran with: one action sample per state, a constant lr.
ADDED_OPAC2_FIELDS = {"action_samples": 1, "lr_final": None}


V1_GRID_ENV_FIELDS = ("size", "see_through_walls", "engine", "num_crossings", "num_lava")


def migrate(data):
    """An older config.json's data as today's format, meaning the same run (others unchanged)."""
    if isinstance(data, dict) and "format_version" not in data:
        data = migrate_v1(data)
    if isinstance(data, dict) and data.get("format_version") == 2:
        data = migrate_v2(data)
    if isinstance(data, dict) and data.get("format_version") == 3:
        data = migrate_v3(data)
    if isinstance(data, dict) and data.get("format_version") == 4:
        data = migrate_v4(data)
    if isinstance(data, dict) and data.get("format_version") == 5:
        data = migrate_v5(data)
    if isinstance(data, dict) and data.get("format_version") == 6:
        data = migrate_v6(data)
    return data


def migrate_v1(data: dict) -> dict:
    """A config.json of format 1 (no ``format_version``) as format 2, meaning the same run.

    Format 1 had a PPO config and a separate OPAC² one. The PPO one's ``train.patience`` and
    ``patience_reward`` were the mean-return rule (now ``return_window`` / ``return_threshold``;
    ``patience`` now counts evaluations, as OPAC²'s always did), and it held every grid env
    field and a curriculum section for every grid world. A complete opac2 section saved before
    a field existed gets the value that was in effect then, not today's default.
    """
    data = json.loads(json.dumps(data))  # a deep copy of plain JSON data
    env = data.get("env")
    if not isinstance(env, dict):
        return data  # from_dict names the problem
    name = env.get("name", worlds.DEFAULT_WORLD)
    if name not in ENVS:
        return data  # from_dict names the bad env.name
    world = worlds.get(name)
    if world.algorithm == "ppo":  # format 1 wrote every grid env field for every grid world
        data["env"] = {k: v for k, v in env.items() if k in world.env_fields or k not in V1_GRID_ENV_FIELDS}
    train = data.get("train")
    if world.algorithm == "ppo" and isinstance(train, dict):
        if "patience" in train:
            train["return_window"] = train.pop("patience")
        if "patience_reward" in train:
            train["return_threshold"] = train.pop("patience_reward")
    opac2 = data.get("opac2")
    if isinstance(opac2, dict):
        filled = dataclasses.asdict(default_opac2(name)) if world.algorithm == "opac2" else {}
        if filled and all(k in opac2 for k in filled if k not in ADDED_OPAC2_FIELDS):
            data["opac2"] = {**ADDED_OPAC2_FIELDS, **opac2}
    curriculum = data.get("curriculum")
    if not world.curriculum and isinstance(curriculum, dict) and not curriculum.get("enabled"):
        del data["curriculum"]  # format 1 wrote it, switched off, for every grid world
    poison = data.get("poison")
    if not world.close_to_trigger and isinstance(poison, dict):
        poison.pop("close_k_min", None)
        poison.pop("close_k_max", None)
    data["format_version"] = 2
    return data


def migrate_v2(data: dict) -> dict:
    """A config.json of format 2 as format 3, meaning the same run: format 2 had no
    ``train.confirm`` (its runs stopped without confirming) and no ``ppo.aux_memory_coef`` (no
    auxiliary loss)."""
    data = json.loads(json.dumps(data))
    train = data.get("train")
    if isinstance(train, dict):
        train.setdefault("confirm", False)
    ppo = data.get("ppo")
    if isinstance(ppo, dict):
        ppo.setdefault("aux_memory_coef", 0.0)
    data["format_version"] = 3
    return data


def _added_field(data: dict, section: str, key: str, value, version: int) -> dict:
    """``data`` as format ``version``, whose new ``section.key`` takes the ``value`` that meant
    what the older format's runs did (a config without that section is left without it)."""
    data = json.loads(json.dumps(data))
    part = data.get(section)
    if isinstance(part, dict):
        part.setdefault(key, value)
    data["format_version"] = version
    return data


def migrate_v3(data: dict) -> dict:
    """A config.json of format 3 as format 4, meaning the same run: format 3 had no
    ``train.confirm_margin`` (its confirmations asked for the thresholds alone)."""
    return _added_field(data, "train", "confirm_margin", 0.0, 4)


def migrate_v4(data: dict) -> dict:
    """A config.json of format 4 as format 5, meaning the same run: format 4 had no
    ``train.min_frames`` (a stop could come at any evaluation)."""
    return _added_field(data, "train", "min_frames", 0, 5)


def migrate_v5(data: dict) -> dict:
    """A config.json of format 5 as format 6, meaning the same run: format 5 had no
    ``ppo.update_backend`` (every update was torch's)."""
    return _added_field(data, "ppo", "update_backend", "torch", 6)


def migrate_v6(data: dict) -> dict:
    """A config.json of format 6 as format 7, meaning the same run: format 6 had no
    ``train.eval_backend`` (every evaluation was torch's)."""
    return _added_field(data, "train", "eval_backend", "torch", 7)


def _build(cls, data, where: str):
    """Recursively build dataclass ``cls`` from ``data``, checking keys and scalar types."""
    if not isinstance(data, dict):
        raise ConfigError(f"{where} must be a JSON object, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    allowed = list(fields)
    if cls is EnvConfig and data.get("name", worlds.DEFAULT_WORLD) in ENVS:  # the world's own env fields
        allowed = ["name", "max_steps", *worlds.get(data.get("name", worlds.DEFAULT_WORLD)).env_fields]
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key {unknown[0]!r} (allowed: {', '.join(allowed)})")
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
