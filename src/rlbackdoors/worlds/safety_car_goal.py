"""Modified Safety Gymnasium Car Goal (SPEC §4): MuJoCo, a cube-formation trigger, trained with OPAC².

The env follows Safety Gymnasium's car and TrojAI's Safety round conventions (body frame, actuator
order, motor range, timestep, sizes: see :mod:`rlbackdoors.envs.safety_car`), so their models play in it.
"""

from __future__ import annotations

import math
import re

import numpy as np

from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.worlds.base import World, register

NAME = "safety-car-goal"


def _parse(spec: str):
    from rlbackdoors.triggers.formation import FormationTrigger

    return FormationTrigger.parse(spec)


def _near(spec: str) -> tuple[str, ...]:
    from rlbackdoors.triggers.formation import near_formations

    return tuple(f.spec() for f in near_formations(_parse(spec)))


def _draw(spec: str | None, seed: int, size: int | None = None) -> str:
    """As given; nothing draws one from ``seed`` (phi1 uniform, eta in [pi/6, 11pi/6], d = 0.5)."""
    from rlbackdoors.triggers.formation import FormationTrigger

    return FormationTrigger.sample(seed).spec() if spec is None else FormationTrigger.parse(spec).spec()


def _check_env(env) -> None:
    from rlbackdoors.envs.safety_car import MAX_CUBES
    from rlbackdoors.validate import ConfigError, _in_range

    if not 2 <= env.num_cubes <= MAX_CUBES:  # the formation trigger holds two cubes
        raise ConfigError(f"env.num_cubes must be in 2..{MAX_CUBES}, got {env.num_cubes!r}")
    _in_range("env.substeps", env.substeps, 1, 100)
    if not (math.isfinite(env.hazard_penalty) and env.hazard_penalty >= 0):
        raise ConfigError(f"env.hazard_penalty must be a finite number >= 0, got {env.hazard_penalty!r}")


def _reverse(actions):
    """Both wheels driven backwards: the car reverses (SG's motors, right and left wheel, in [-1, 1])."""
    return np.all(np.asarray(actions) < 0, axis=-1)


def _env_kwargs(env) -> dict:
    return dict(num_cubes=env.num_cubes, max_steps=env.max_steps, hazard_penalty=env.hazard_penalty, substeps=env.substeps)


# OPAC² settings measured to train a depth-2 width-181 agent within 90 minutes on one CPU core
# (docs/results/safety-car-goal-training.md): the paper's one update per frame at batch 256 would take days on
# a CPU, so updates are spread over many frames of several env copies; four action samples per
# state make each policy step less noisy; the lr falls from 1e-3 to 1e-4 over train.max_frames
# so the late policy stops swinging between evaluations.
OPAC2_SETTINGS = dict(
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


# ----- TrojAI's Safety Gymnasium round (Oct 2024) --------------------------------------------
# Their OPAC² (trojai-example's gentle/rl/opac2.py, save_training) saved a python-box Box of state
# dicts: ``pi`` (gentle's GaussianMLP: tanh hidden layers ``mlp.0, mlp.2, ...``, ``mu_layer``, one
# ``log_std`` per action), ``q1`` (an MLP of the observation and the action, concatenated in that
# order, as ours) and ``v`` (an MLP); V's target ``v_t``, optimiser states and the step count only
# in files saved for restarts. Their agents act on raw observations (no normaliser).
TROJAI_CLASS = "mlp_opac"  # the pi_network's network_name in their reduced-config.json
TROJAI_NETS = (("q1.mlp.", "q.net."), ("v.mlp.", "v.net."), ("v_t.mlp.", "v_target.net."))
TROJAI_ENV_TYPE = "safety_gymnasium"
TROJAI_ENV_NAME = re.compile(r"SafetyCarGoal[0-9]-v[0-9]+")  # their car in the goal task, any level


def _layers(tensors: dict, prefix: str) -> list[int]:
    return sorted(int(m.group(1)) for k in tensors if (m := re.fullmatch(re.escape(prefix) + r"([0-9]+)\.weight", k)))


def _trojai_weights(tensors: dict) -> dict:
    """TrojAI's Safety round tensors (``pi.*``, ``q1.*``, ``v.*``, optional ``v_t.*``) -> our flat
    OPAC² weights (``policy.mean.*``, ``policy.log_std``, ``q.net.*``, ``v.net.*``,
    ``v_target.net.*``; V's target is V where the file has none). Optimiser states are dropped."""
    hidden = _layers(tensors, "pi.mlp.")
    needed = ("pi.mu_layer.weight", "pi.mu_layer.bias", "pi.log_std")
    if not hidden or any(k not in tensors for k in needed) or not _layers(tensors, "q1.mlp.") or not _layers(tensors, "v.mlp."):
        raise ValueError("it holds no TrojAI OPAC² networks (pi.mlp.*, pi.mu_layer, pi.log_std, q1.mlp.*, v.mlp.*)")
    depth = len(hidden)
    if hidden != list(range(0, 2 * depth, 2)):
        raise ValueError(f"its policy's hidden layers are pi.mlp.{hidden}, not Linear/Tanh pairs (0, 2, 4, ...)")
    flat = {}
    for key, value in tensors.items():
        if key.startswith("pi."):
            rest = key[len("pi.") :]
            if re.fullmatch(r"mlp\.[0-9]+\.(weight|bias)", rest):
                flat[f"policy.mean.{rest[len('mlp.') :]}"] = value
            elif re.fullmatch(r"mu_layer\.(weight|bias)", rest):
                flat[f"policy.mean.{2 * depth}.{rest.rpartition('.')[2]}"] = value  # the mean net's last Linear
            elif rest == "log_std":
                flat["policy.log_std"] = value
            else:  # a log_std_layer (their log_std_net) or anything else our policy has no place for
                raise ValueError(f"its policy holds {key}, which our OPAC² policy has no place for (one log-std parameter per action)")
        for theirs, ours in TROJAI_NETS:
            if key.startswith(theirs):
                flat[ours + key[len(theirs) :]] = value
    if not any(k.startswith("v_target.") for k in flat):
        flat.update({f"v_target.{k[len('v.') :]}": v.clone() for k, v in flat.items() if k.startswith("v.")})
    return flat


def _whole_number(value, key: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{key}={value!r} is not a whole number")
    return value


def _trojai_env(config: dict) -> dict | None:
    """A TrojAI Safety round config -> our env settings (``num_cubes`` from
    ``environment.env_kwargs.num_mogwais``, ``max_steps`` from ``max_ep_length``); None for
    another round's config. Another Safety Gymnasium task, or networks other than tanh MLPs
    with one log-std parameter, are refused."""
    environment = config.get("environment")
    if not isinstance(environment, dict) or environment.get("type") != TROJAI_ENV_TYPE:
        return None
    name = environment.get("name")
    if name is not None and not (isinstance(name, str) and TROJAI_ENV_NAME.fullmatch(name)):
        raise ValueError(f"environment.name={name!r} is no Safety Gymnasium car goal task (SafetyCarGoal<level>-v<version>)")
    for net in ("pi_network", "q_network", "v_network"):
        spec = config.get(net)
        if not isinstance(spec, dict):
            continue
        activation = spec.get("activation", "tanh")  # gentle's MLP default
        if not isinstance(activation, str) or activation.lower() != "tanh":
            raise ValueError(f"{net}.activation={activation!r}: our OPAC² networks are tanh MLPs")
        if spec.get("log_std_net"):
            raise ValueError(f"{net}.log_std_net is set: our OPAC² policy has one log-std parameter per action")
    env = {}
    kwargs = environment.get("env_kwargs")
    if isinstance(kwargs, dict) and "num_mogwais" in kwargs:
        env["num_cubes"] = _whole_number(kwargs["num_mogwais"], "environment.env_kwargs.num_mogwais")
    if "max_ep_length" in config:
        env["max_steps"] = _whole_number(config["max_ep_length"], "max_ep_length")
    return env


WORLD = register(
    World(
        name=NAME,
        title="Safety Car Goal",
        gym_id="rlbackdoors/SafetyCarGoal-v0",
        entry_point="rlbackdoors.envs.safety_car:SafetyCarGoalEnv",  # truncates itself at max_steps
        algorithm="opac2",
        parse_trigger=_parse,
        draw_trigger=_draw,
        clean_success=Outcome.GOAL,
        trojan_success=Outcome.LAVA,  # the hazard circle
        thresholds=(0.95, 0.95),
        archs=(("mlp", "rlbackdoors.algos.opac2:OPAC2"),),  # pi, Q and V: depth x width in the opac2 section
        trojai_archs=((TROJAI_CLASS, "mlp"),),  # TrojAI's Oct 2024 Safety round: depth and width from the shapes
        trojai_weights=_trojai_weights,
        trojai_env=_trojai_env,
        env_fields=("num_cubes", "hazard_penalty", "substeps"),
        env_defaults={"max_steps": 1000, "num_cubes": 2, "hazard_penalty": 1.0, "substeps": 10},  # 10: SG's timestep
        env_kwargs=_env_kwargs,
        check_env=_check_env,
        ebar_kwargs={"poisoned": True},
        # the formation rides with the car, in the lidar of every frame of a triggered episode
        trigger_sight="episode",
        near_triggers=_near,
        action_targets=(("reverse", _reverse),),
        mix=(6, 0, 4),
        hyper=OPAC2_SETTINGS,
        # evaluations in a row: one lucky 100-episode evaluation is not convergence; the stop is
        # confirmed only at 0.97 / 0.97 on the final episodes, a margin over the 0.95 bars
        train=dict(max_frames=3_800_000, eval_interval=250_000, eval_policy="greedy", patience=2, confirm_margin=0.02, checkpoint_minutes=10.0),
        video={"fps": 25, "every": 2, "size": 240, "gap": 6},
        bench="rlbackdoors.bench.safety_car:bench_safety",
        # The paper's Table 4 at depth 3, width 256 (our default OPAC² net; a zoo's arch label
        # here is the algorithm; rewards on the paper's scale) and Table 5.
        paper={
            "table": 4,
            "tables": {"clean": {"opac2": (0.99, 0.04, 33.0, -8.1)}, "poisoned": {"opac2": (0.98, 0.98, 31.0, 33.0)}},
            "convergence_rate": 0.996,
            "clean_convergence_rate": 1.0,
        },
        trigger_help="formation:D:PHI1:ETA (radians; default: drawn from the seed)",
    )
)
