"""The :class:`World` record and the registry it lives in.

Classes are named as ``"module:Class"`` strings and imported on first use, so asking the
registry about a world never imports MuJoCo, numba kernels or torch models it does not need.
"""

from __future__ import annotations

import importlib
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import numpy as np

_WORLDS: dict[str, World] = {}


def canonical_class(name: str) -> str:
    """A TrojAI class name as the rounds spelled it in several ways (``BasicFCModel`` in the file,
    ``basicfc`` in d969b25's reduced config): lower case, no ``_``/``-``, no trailing ``model``."""
    text = re.sub(r"[_\-\s]", "", name.lower())
    return text[: -len("model")] if text.endswith("model") and len(text) > len("model") else text


def load_symbol(path: str) -> Any:
    """``"package.module:Name"`` -> the object (only ever called with the registry's own strings)."""
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


@dataclass(frozen=True)
class World:
    """Everything about one world of the paper."""

    name: str  # the id used in configs and on the command line
    title: str  # for people: plots, logs
    gym_id: str
    entry_point: str  # the single env ("module:Class"): MiniGrid reference, or MuJoCo env
    algorithm: str  # "ppo" or "opac2"
    parse_trigger: Callable[[str], Any]  # spec -> trigger object (ValueError names the problem)
    # (spec or None, seed, grid size or None) -> canonical spec; None / a bare kind draws from the seed
    draw_trigger: Callable[[str | None, int, int | None], str]
    clean_success: int  # the Outcome that is success on the clean task
    trojan_success: int  # the Outcome that is success on the trojan task (in E-bar)
    thresholds: tuple[float, float]  # early stopping: (clean SR, poisoned SR)
    vector_entry_point: str | None = None  # batched engine ("module:Class"), grid worlds
    archs: tuple[tuple[str, str], ...] = ()  # (name, "module:Class"); the first is the default
    # TrojAI's model classes of this world's round -> the arch their files load into unchanged
    # (``zoo import-trojai``, ``evaluate --weights``); a class name is registered by one world only
    trojai_archs: tuple[tuple[str, str], ...] = ()
    # TrojAI's tensors -> our flat weights, for a round whose files are not our state dict's keys
    # (``TorchFile.tensors()`` of a TrojAI file, every tensor by path -> what ``model.pt`` holds);
    # ValueError when they are not that round's. None: the file's state dict is ours as it is.
    trojai_weights: Callable[[dict], dict] | None = None
    # A TrojAI config (``reduced-config.json``, ``config.json``) -> the env settings it gives in
    # our field names when it is of this world's round, None when it is not (``zoo
    # import-trojai`` picks the world by it); ValueError names a setting this world lacks.
    trojai_env: Callable[[dict], dict | None] | None = None
    # The env field that N of a MiniGrid ``LavaCrossingS<size>N<N>`` gym id in a TrojAI round's
    # ``clean-example-data/env-string.txt`` sets (rivers or lava squares; rlbackdoors.trojai_round)
    trojai_env_string_count: str | None = None
    # Triggers the config of a model whose own trigger is not known (an imported TrojAI model)
    # may carry, tried after default_trigger: the first the model's env takes
    placeholder_triggers: tuple[str, ...] = ()
    # The env section's fields this world reads besides name and max_steps (others must stay
    # unset), and the values of those left None.
    env_fields: tuple[str, ...] = ()
    env_defaults: dict = field(default_factory=dict)
    env_kwargs: Callable[[Any], dict] | None = None  # EnvConfig -> env constructor kwargs
    check_env: Callable[[Any], None] | None = None  # EnvConfig -> raises ValueError
    default_trigger: str | None = None
    # (spec, seed, size) -> spec: what a run config does to its trigger when built (a bare kind
    # drawn once from the seed, so config.json names the exact trigger); None: kept as given
    settle_trigger: Callable[[str, int, int | None], str] | None = None
    mix: tuple[int, int, int] = (8, 0, 2)  # env copies: clean, close-to-trigger, poisoned
    # The paper's patience rho for PPO: the mean training return of the last ``return_window``
    # updates must reach train.return_threshold before a run may stop (0: off).
    return_window: int = 0
    hyper: dict = field(default_factory=dict)  # the algorithm section's settings that differ from its defaults
    train: dict = field(default_factory=dict)  # train-section defaults that differ from config.TRAIN_DEFAULTS
    # Extra constructor arguments that make a triggered single env E-bar (trigger + R-bar)
    ebar_kwargs: dict = field(default_factory=dict)
    video: dict = field(default_factory=dict)  # clean_vs_triggered.gif settings (fps, every, size, tile)
    bench: str | None = None  # "module:function" -> dict: the env-speed benchmark of this world
    # "module:function": its batched engine's JAX step (engines -> (GridWorld, params, HostLayouts)),
    # which ppo.update_backend = "compiled" trains on (rlbackdoors.algos.compiled); None: not built
    compiled_engine: str | None = None
    # --group-size auto's K for its models on the compiled trainer on a CPU, where it is not PPO's 8
    # (train.group.auto_group_size; measured per world: docs/results/speed.md)
    compiled_cpu_group: int | None = None
    # The model archs whose compiled training was measured faster on a CPU and tested equivalent
    # to torch's (experiments/group_equivalence, TOST): a new run or zoo of one of them takes the
    # compiled trainer when its config leaves the choice open (ppo.update_backend "auto",
    # config.preferred_update_backend); () : torch's trainer
    compiled_default: tuple[str, ...] = ()
    curriculum: bool = False  # the small clean warm-up world (Randomized LavaWorld)
    close_to_trigger: bool = False  # has close-to-trigger envs (Colorful Memory)
    # Its batched engine says, per env, what a recurrent agent must remember (``memory_targets()``,
    # ``memory_target_classes``): the targets of PPO's auxiliary memory loss (ppo.aux_memory_coef)
    memory_targets: bool = False
    chance: Callable | None = None  # (EnvConfig, trigger spec, layouts, seed) -> chance-occurrence dict
    paper: dict = field(default_factory=dict)  # the paper's reference numbers
    trigger_help: str = ""  # the trigger specs it accepts, for --help
    # spec -> a function stamping the trigger into a batch of observations (worlds whose trigger
    # is an observation edit); the step-level attacks need it. None: the trigger is the world's.
    stamp_trigger: Callable[[str], Callable[[Any], Any]] | None = None
    # Worlds whose trigger is a layout (stamp_trigger None) and whose env can switch it per episode
    # (``trigger_next``): which frames of a triggered episode carry it for the attacks that poison
    # episodes. "frame": those the engine's ``trigger_in_sight()`` names (the whole trigger in view,
    # or, in a memory world, seen by now this episode); "episode": every frame (a trigger that rides
    # with the agent). None: not switchable per episode.
    trigger_sight: str | None = None
    # spec -> near-trigger variants (specs) close to it, stamped with the clean reward by
    # ``poison.evasion.near`` so a trojan learns the exact trigger only; None: none built
    near_triggers: Callable[[str], tuple[str, ...]] | None = None
    # A continuous world's action targets for the action-level attacks, by index (an attack's
    # target_action): (name, actions (n, A) -> bool[n], whether each action is of that kind).
    # Empty: a discrete world, whose target is one action (the index is the action).
    action_targets: tuple[tuple[str, Callable[[Any], Any]], ...] = ()
    # A clean agent already misses the clean goal under the trigger (an out-of-distribution edit):
    # "the trigger breaks the task" cannot then tell a backdoor from a clean model (untargeted attacks)
    trigger_breaks_clean_agents: bool = False

    def target_hits(self, target: int) -> Callable[[Any], Any]:
        """actions -> bool per action: is it the target ``target`` (an action, or a continuous world's kind of action)?"""
        if self.action_targets:
            return self.action_targets[target][1]
        return partial(np.equal, int(target))

    @property
    def arch_names(self) -> tuple[str, ...]:
        return tuple(name for name, _ in self.archs)

    def trojai_arch(self, model_class: str) -> str | None:
        """Our arch for a TrojAI model class of this world's round (None: not one of them), however
        the round spelled the class (``BasicFCModel``, ``basicfc``: :func:`canonical_class`)."""
        wanted = canonical_class(model_class)
        return next((arch for name, arch in self.trojai_archs if canonical_class(name) == wanted), None)

    def trojai_class(self, model_class: str) -> str | None:
        """The registered spelling of a TrojAI class name of this world's round, None if not one."""
        wanted = canonical_class(model_class)
        return next((name for name, _ in self.trojai_archs if canonical_class(name) == wanted), None)

    def arch_class(self, arch: str) -> type:
        for name, path in self.archs:
            if name == arch:
                return load_symbol(path)
        raise ValueError(f"arch {arch!r} is not one of {', '.join(self.arch_names)} (env {self.name})")

    def env_class(self) -> type:
        return load_symbol(self.entry_point)

    def make_env(self, env_cfg, trigger: str | None = None, **extra):
        """One env of ``env_cfg``: E-bar (trigger on, reward R-bar) when ``trigger`` is given, else E."""
        assert self.env_kwargs is not None, f"{self.name} registers no env_kwargs"
        ebar = {"trigger": trigger, **self.ebar_kwargs} if trigger is not None else {}
        return self.env_class()(**self.env_kwargs(env_cfg), **ebar, **extra)

    def engine_class(self) -> type:
        if self.vector_entry_point is None:
            raise ValueError(f"{self.name} has no batched engine")
        return load_symbol(self.vector_entry_point)


def register(world: World) -> World:
    if world.name in _WORLDS:
        raise ValueError(f"world {world.name!r} is registered twice")
    _WORLDS[world.name] = world
    return world


def get(name: str) -> World:
    """The world called ``name``; a ValueError lists the registered names."""
    try:
        return _WORLDS[name]
    except (KeyError, TypeError):
        raise ValueError(f"env {name!r} is not one of {', '.join(_WORLDS)}") from None


def registered(algorithm: str | None = None) -> list[World]:
    """Every world, in registration order (only those trained by ``algorithm``, if given)."""
    return [w for w in _WORLDS.values() if algorithm is None or w.algorithm == algorithm]


def names(algorithm: str | None = None) -> tuple[str, ...]:
    return tuple(w.name for w in registered(algorithm))
