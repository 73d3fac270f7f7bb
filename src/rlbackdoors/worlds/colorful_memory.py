"""Colorful Memory (SPEC §3): MiniGrid's memory task with randomly coloured walls; the trigger is
a wall-colour pattern (End and/or Room Trigger), with close-to-trigger envs."""

from __future__ import annotations

from rlbackdoors.envs.outcome import Outcome
from rlbackdoors.worlds.base import World, register

NAME = "colorful-memory"


def _parse(spec: str):
    from rlbackdoors.triggers.wall_colors import WallColorTrigger

    return WallColorTrigger.parse(spec)


def _draw(spec: str | None, seed: int, size: int | None = None) -> str:
    """Colours as given; a bare kind (``end``, ``room``, ``end+room``), or nothing, draws them
    from ``seed`` for a ``size`` grid (the End Trigger's length depends on it)."""
    from rlbackdoors.triggers.wall_colors import WallColorTrigger

    kwargs = {} if size is None else {"size": size}
    if spec is None:
        spec = WORLD.default_trigger
        assert spec is not None  # this world has a default trigger
    return WallColorTrigger.parse(spec, rng=seed, **kwargs).spec()


def _settle(spec: str, seed: int, size: int | None) -> str:
    """A bare kind in a config is drawn once, from the run's seed; explicit colours stay as given."""
    from rlbackdoors.triggers.wall_colors import KINDS, WallColorTrigger, check_size

    # check_size: the ValueError sample() would raise for a missing size, before parsing
    return WallColorTrigger.parse(spec, rng=seed, size=check_size(size)).spec() if spec in KINDS else spec


def _check_env(env) -> None:
    from rlbackdoors.envs.colorful_memory import validate_args

    validate_args(env.size, env.max_steps)


def _env_kwargs(env) -> dict:
    return dict(size=env.size, max_steps=env.max_steps, see_through_walls=env.see_through_walls)


def _chance(env, trigger: str, layouts: int, seed: int, count) -> dict:
    """Clean layouts whose walls wear the trigger's colours exactly (exact rate 6^-squares)."""
    from rlbackdoors.envs.colorful_memory_batched import BatchedColorfulMemory
    from rlbackdoors.triggers.wall_colors import WallColorTrigger, chance_probability

    wall = WallColorTrigger.parse(trigger, rng=seed, size=env.size)
    counts = count(lambda n: BatchedColorfulMemory(n, size=env.size, max_steps=env.max_steps), lambda engine: engine.trigger_present(wall))
    return {"trigger": wall.spec(), "counts": counts, "exact_rate": chance_probability(wall, env.size)}


_SMALL = ("cnn-gru-small-onehot", "cnn-gru-small", "cnn-gru-trojai")
_LARGE = ("cnn-gru-large-onehot", "cnn-gru-large")

WORLD = register(
    World(
        name=NAME,
        title="Colorful Memory",
        gym_id="rlbackdoors/ColorfulMemory-v0",
        entry_point="rlbackdoors.envs.colorful_memory:ColorfulMemoryEnv",
        vector_entry_point="rlbackdoors.envs.colorful_memory_batched:BatchedColorfulMemory",
        algorithm="ppo",
        parse_trigger=_parse,
        draw_trigger=_draw,
        clean_success=Outcome.GOAL,
        trojan_success=Outcome.LAVA,  # the engines report the other object's cell as LAVA
        # The paper stopped at 100%/100%; on 100 evaluation episodes we stop at 98% both.
        thresholds=(0.98, 0.98),
        # The first is the default: the one-hot small CNN-GRU trains on a CPU budget
        # (models/colorful_memory.py); the plain names are the paper's raw-code models.
        archs=(
            ("cnn-gru-small-onehot", "rlbackdoors.models.colorful_memory:CNNGRUSmallOneHot"),
            ("cnn-gru-small", "rlbackdoors.models.colorful_memory:CNNGRUSmall"),
            ("cnn-gru-large-onehot", "rlbackdoors.models.colorful_memory:CNNGRULargeOneHot"),
            ("cnn-gru-large", "rlbackdoors.models.colorful_memory:CNNGRULarge"),
            # TrojAI's GRUCNNActorCriticModel: cnn-gru-small's layers with heads that end in a ReLU
            ("cnn-gru-trojai", "rlbackdoors.models.colorful_memory:TrojAIGRUCNN"),
        ),
        # TrojAI's Colorful Memory round (Sep 2024): an rl-starter-files status dict
        # ({"model_state": ..., "optimizer_state": ...}); the class is named in reduced-config.json.
        trojai_archs=(("GRUCNNActorCriticModel", "cnn-gru-trojai"),),
        env_fields=("size", "see_through_walls", "engine"),
        env_defaults={"max_steps": 250, "engine": "batched", "size": 7, "see_through_walls": False},
        env_kwargs=_env_kwargs,
        check_env=_check_env,
        default_trigger="end",  # a bare kind: its 9 colours are drawn from train.seed
        settle_trigger=_settle,
        # 4 clean + 4 close-to-trigger + 2 poisoned: the close copies teach the backdoor to
        # fire on the exact colours only.
        mix=(4, 4, 2),
        # Paper: stop only once the mean training return of the last 10 updates is high enough.
        return_window=10,
        # The paper's recurrence 6 (torch-ac), with torch-ac's usual lr 1e-3 and clip 0.2
        # instead of the paper's lr 1e-5 / clip 0.1, which need billions of frames.
        # The auxiliary memory loss (0.5, not the paper's): it names the start object from the
        # memory, so the XOR at the T-junction is learnt in about 1 M frames on every seed we ran
        # instead of a 50 % plateau of 0.8 M to > 5 M (docs/colorful-memory.md).
        hyper=dict(
            rollout=120, epochs=4, batch_size=600, lr=1e-3, clip=0.2, value_coef=0.5, gae_lambda=0.95, max_grad_norm=0.5, recurrence=6, aux_memory_coef=0.5
        ),
        close_to_trigger=True,
        compiled_engine="rlbackdoors.envs.colorful_memory_jax:colorful_memory_jax",
        # one agent a program: its iteration ran 7.7 k frames/s a core alone, 5.1 k at K = 4
        # (Intel Xeon, 2026-12-06, docs/results/speed.md)
        compiled_cpu_group=1,
        memory_targets=True,  # the start object (BatchedColorfulMemory.memory_targets)
        chance=_chance,
        # The paper's Table 3 (label -> arch -> clean SR, poisoned SR, clean reward, poisoned
        # reward; its "small" is TrojAI's GRU CNN, ours cnn-gru-small, cnn-gru-trojai and the one-hot
        # variant; "large" is cnn-gru-large and its one-hot variant) and Table 5.
        trigger_sight="frame",  # per-episode attacks (attacks/seam.py): the engine says when all the trigger was seen
        paper={
            "table": 3,
            "tables": {
                "clean": {a: (1.00, 0.02, 0.91, 0.03) for a in _SMALL} | {a: (1.00, 0.05, 0.93, 0.03) for a in _LARGE},
                "poisoned": {a: (1.00, 1.00, 0.97, 0.92) for a in _SMALL} | {a: (1.00, 1.00, 0.97, 0.94) for a in _LARGE},
            },
            "convergence_rate": 0.672,
            "clean_convergence_rate": 0.5,
        },
        trigger_help="end | room | end+room (colours drawn from the seed) | end:C,... | room:C,C,C",
    )
)
