"""Command line: ``rlbackdoors train | evaluate | demo | chance | bench``.

Every user-facing failure (bad flag value, bad config, missing or corrupt file, folder
conflict) ends in one ``rlbackdoors: error: ...`` line and exit code 2.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path


from rlbackdoors import __version__, worlds
from rlbackdoors.argparser import Parser, report_errors
from rlbackdoors.config import ARCHS, ENGINES, ENVS, EVAL_POLICIES, MAX_EPISODES, ConfigError, RunConfig, check_seed
from rlbackdoors.train.folder import FolderError

METRIC_KEYS = (
    "clean_sr",
    "poisoned_sr",
    "poisoned_sr_raw",
    "trigger_seen_rate",
    "clean_reward",
    "poisoned_reward",
    "close_sr",
    "close_trojan_rate",
    "episodes",
)


def resolve_trigger(spec: str | None, seed: int, env: str = worlds.DEFAULT_WORLD, size: int | None = None) -> str:
    """The trigger's canonical string for ``env`` (the world's ``draw_trigger``): as given, or
    drawn from ``seed`` where the spec is a bare kind or missing (see each world's module)."""
    try:
        return worlds.get(env).draw_trigger(spec, seed, size)
    except ValueError as err:
        raise ConfigError(f"--trigger for {env}: {err}") from None


def _set(data: dict, dotted: str, value) -> None:
    section, key = dotted.split(".")
    data.setdefault(section, {})[key] = value


def config_from_args(args) -> RunConfig:
    """Config file (if any) first, then every flag given on the command line on top of it."""
    from rlbackdoors.config import EnvConfig, _build

    if args.config:
        data = RunConfig.load(args.config).to_dict()
        if args.env is not None and args.env != data["env"]["name"]:
            # Another world: its own defaults (size, walls), not the config's world's.
            data["env"] = dataclasses.asdict(EnvConfig(name=args.env, engine=data["env"]["engine"]))
            data["poison"]["trigger"] = None  # the new world's default trigger, unless --trigger
            for key in ("num_clean_envs", "num_close_envs", "num_poisoned_envs"):
                data["poison"][key] = None  # ... and its mix, model and PPO settings
            data["model"]["arch"], data["ppo"] = None, None
            data["train"]["patience"] = None
            data.setdefault("curriculum", {})["enabled"] = None
    else:
        data = RunConfig(env=EnvConfig(name=args.env or worlds.DEFAULT_WORLD)).to_dict()
    flags = {
        "env.engine": args.engine,
        "env.size": args.size,
        "env.num_lava": args.num_lava,
        "model.arch": args.arch,
        "train.seed": args.seed,
        "train.max_frames": args.max_frames,
        "train.eval_episodes": args.eval_episodes,
        "train.device": args.device,
        "train.patience": args.patience,
    }
    for dotted, value in flags.items():
        if value is not None:
            _set(data, dotted, value)
    if args.clean:
        _set(data, "poison.poisoned", False)
    if args.no_curriculum:
        _set(data, "curriculum.enabled", False)
    if args.no_close_to_trigger:
        clean, close, _ = RunConfig.from_dict(data).poison.counts()  # the world's mix, resolved
        _set(data, "poison.num_clean_envs", clean + close)
        _set(data, "poison.num_close_envs", 0)
    check_seed("train.seed (--seed)", data["train"]["seed"])
    _build(EnvConfig, data["env"], "env").check()  # before a trigger is drawn for its size
    world = data["env"]["name"]
    for flag, readers in WORLD_FLAGS.items():
        if getattr(args, flag) not in (None, False) and world not in readers:
            raise ConfigError(f"--{flag.replace('_', '-')} applies to {' and '.join(readers)} only, not {world}")
    if args.trigger is not None or not args.config:
        _set(data, "poison.trigger", resolve_trigger(args.trigger, data["train"]["seed"], world, data["env"].get("size")))
    return RunConfig.from_dict(data)


# Grid flags that only some grid worlds read: refused for the others.
WORLD_FLAGS = {flag: tuple(w.name for w in worlds.registered() if flag in w.flags) for w in worlds.registered() for flag in w.flags}
# Flags that only one kind of world reads: refused for the other, so none is silently ignored.
GRID_ONLY_FLAGS = ("arch", "size", "num_lava", "no_curriculum", "engine", "patience", "no_close_to_trigger")
SAFETY_ONLY_FLAGS = (
    "max_minutes",
    "depth",
    "width",
    "num_clean_envs",
    "num_poisoned_envs",
    "poisoned_weight",
    "updates_per_step",
    "batch_size",
    "lr",
    "lr_final",
    "action_samples",
    "eval_interval",
    "final_eval_episodes",
    "threads",
    "checkpoint_minutes",
)


def _config_json(path: str | Path | None) -> dict | None:
    if not path or not Path(path).is_file():
        return None
    try:
        return json.loads(Path(path).read_bytes().decode("utf-8"))
    except (ValueError, RecursionError, OSError):
        return None  # RunConfig.load reports it


def _refuse(args, flags: tuple[str, ...], world: str) -> None:
    for name in flags:
        if getattr(args, name, None) not in (None, False):
            raise ConfigError(f"--{name.replace('_', '-')} does not apply to {world}")


def cmd_train(args) -> int:
    if not args.out.strip():
        raise ConfigError("--out must name a model folder, got an empty path")
    from rlbackdoors.safety_config import is_safety_config
    from rlbackdoors.train import train

    if args.env in worlds.names("opac2") or (args.env is None and is_safety_config(_config_json(args.config))):
        return _train_safety(args)
    _refuse(args, SAFETY_ONLY_FLAGS, "the grid worlds (they are Safety Car Goal's OPAC² settings)")
    cfg = config_from_args(args)
    metrics = train(cfg, args.out, overwrite=args.overwrite, progress=not args.quiet)
    print(json.dumps(metrics, indent=2) if args.json else _summary(args.out, metrics))
    return 0


def _train_safety(args) -> int:
    """Safety Car Goal trains with OPAC² (its own config, :mod:`rlbackdoors.safety_config`)."""
    from rlbackdoors.safety_cli import config_from_args as safety_config_from_args
    from rlbackdoors.train.safety import train_safety

    _refuse(args, GRID_ONLY_FLAGS, args.env or "an OPAC² world")
    cfg = safety_config_from_args(args)
    metrics = train_safety(cfg, args.out, overwrite=args.overwrite, progress=not args.quiet)
    print(json.dumps(metrics, indent=2) if args.json else _summary(args.out, metrics))
    return 0


def _summary(where, metrics: dict) -> str:
    return (
        f"{where}: clean SR {metrics['clean_sr']:.3f}, poisoned SR {metrics['poisoned_sr']:.3f}, "
        f"clean reward {metrics['clean_reward']:.3f}, poisoned reward {metrics['poisoned_reward']:.3f} "
        f"({metrics['episodes']} episodes; {metrics['frames']:,} frames, {metrics['wall_time_s']:.0f} s, "
        f"{'converged' if metrics['converged'] else 'not converged'})"
    )


def cmd_evaluate(args) -> int:
    import torch

    from rlbackdoors.config import EnvConfig
    from rlbackdoors.evaluate import evaluate
    from rlbackdoors.models import build_model, load_weights
    from rlbackdoors.train import ModelFolder

    if (args.folder is None) == (args.weights is None):
        raise ConfigError("give either a model folder or --weights FILE (with --arch), not both or neither")
    if args.seed is not None:
        check_seed("--seed", args.seed)
    torch.set_num_threads(1)
    if args.folder is not None:
        folder = ModelFolder(args.folder)
        if not folder.path.is_dir():
            raise FolderError(f"model folder {args.folder!r} does not exist")
        if not folder.file("config.json").is_file():
            raise FolderError(f"{args.folder!r} is not a model folder (config.json missing)")
        if not folder.file("model.pt").is_file():
            raise FolderError(f"{args.folder!r} holds no trained model (model.pt missing)")
        if not folder.complete and not args.allow_unfinished:
            raise FolderError(
                f"{args.folder!r} holds an unfinished run (no metrics.json: still training, interrupted or failed); "
                "pass --allow-unfinished to evaluate its weights anyway"
            )
        from rlbackdoors.safety_config import is_safety_config

        if is_safety_config(_config_json(folder.file("config.json"))):
            for flag in ("trigger", "policy", "engine", "arch", "env"):
                if getattr(args, flag) is not None:
                    raise ConfigError(f"--{flag} does not apply to a Safety Car Goal folder (it is evaluated with its own trigger and deterministic policy)")
            from rlbackdoors.safety_cli import evaluate_folder

            return evaluate_folder(args.folder, args.episodes, args.json, args.seed, allow_unfinished=True)
        cfg = folder.read_config()
        if args.arch is not None or args.env is not None:
            raise ConfigError("--arch and --env apply to --weights only (a model folder's config.json names them)")
        if args.engine:
            cfg.env.engine = args.engine
        env, trigger, arch, policy = cfg.env, cfg.poison.trigger, cfg.model.arch, cfg.train.eval_policy
        close_k: tuple[int, int] | None = (cfg.poison.close_k_min, cfg.poison.close_k_max)
        if args.trigger is not None:
            trigger = resolve_trigger(args.trigger, cfg.train.seed, env.name, env.size)
        weights = folder.file("model.pt")
    else:
        if args.arch is None:
            raise ConfigError(f"--weights needs --arch (allowed: {', '.join(ARCHS)})")
        if args.allow_unfinished:
            raise ConfigError("--allow-unfinished applies to model folders, not --weights")
        env = EnvConfig(name=args.env or worlds.DEFAULT_WORLD, engine=args.engine or "batched")
        env.check()
        trigger = resolve_trigger(args.trigger, 0, env.name) if args.trigger is not None else None
        arch, policy, weights = args.arch, "sample", Path(args.weights)
        close_k = (1, 3)
    policy = args.policy or policy
    assert arch is not None  # --arch, or a model folder's checked config
    model = load_weights(build_model(arch, env.name), weights)
    if not env.world.close_to_trigger or trigger is None:
        close_k = None  # close-to-trigger layouts exist only in worlds that have them
    seed = 1_000_000 if args.seed is None else args.seed
    episodes = 200 if args.episodes is None else args.episodes
    result = evaluate(model, env, trigger, episodes=episodes, seed=seed, policy=policy, close_k=close_k).to_dict()
    result = {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in result.items()}
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        for key in METRIC_KEYS:
            value = result[key]
            print(f"{key:18s} {'n/a' if value is None else (f'{value:.4f}' if isinstance(value, float) else value)}")
    return 0


def cmd_demo(args) -> int:
    from rlbackdoors.demo import run_demo

    run_demo(Path(args.out), max_frames=args.max_frames, seed=args.seed, progress=not args.quiet)
    return 0


def cmd_bench(args) -> int:
    from rlbackdoors.io import atomic_write_text

    if args.what == "env":
        from rlbackdoors.bench.env import bench_env

        result = bench_env(seconds=args.seconds, num_envs=args.num_envs)
        print(
            f"env steps/s: batched {result['batched_steps_per_s']:,.0f} (B={result['num_envs']}), "
            f"Farama MiniGrid {result['minigrid_steps_per_s']:,.0f}, ratio {result['ratio']:.0f}x"
        )
    elif args.what == "train":
        from rlbackdoors.bench.train import bench_train

        result = bench_train(seconds=args.seconds)
        for arch in ("fc", "cnn"):
            r = result[arch]
            print(
                f"PPO {arch}: batched {r['batched_fps']:,.0f} frames/s "
                f"({r['batched_collect_share']:.0%} collecting), "
                f"MiniGrid {r['minigrid_fps']:,.0f} frames/s, ratio {r['ratio']:.1f}x"
            )
    elif args.what == "safety":
        from rlbackdoors.bench.safety import bench_safety

        result = bench_safety(seconds=args.seconds)
        print(
            f"Safety Car Goal ({result['num_cubes']} cubes): env {result['env_steps_per_s']:,.0f} steps/s, "
            f"plain mujoco loop {result['physics_steps_per_s']:,.0f} steps/s, ratio {result['ratio_to_physics']:.2f}"
        )
    else:
        from rlbackdoors.bench.train import bench_converge

        result = bench_converge(seed=args.seed, progress=not args.quiet)
        print(
            f"poisoned FC (seed {result['seed']}, {result['trigger']}): converged={result['converged']} "
            f"after {result['frames']:,} frames in {result['wall_clock_s']:.0f} s wall-clock; "
            f"clean SR {result['clean_sr']:.3f}, poisoned SR {result['poisoned_sr']:.3f} ({result['episodes']} episodes)"
        )
    if args.json:
        atomic_write_text(args.json, json.dumps(result, indent=2) + "\n")
    return 0


def cmd_chance(args) -> int:
    from rlbackdoors.config import EnvConfig
    from rlbackdoors.evaluate.chance import trigger_chance

    env = EnvConfig(name=args.env, size=args.size, num_lava=args.num_lava if args.num_lava is not None else 10)
    env.check()
    result = trigger_chance(env, args.trigger, layouts=args.layouts, seed=args.seed)
    if args.json:
        print(json.dumps(result, indent=2))
    elif "exact_rate" in result:
        print(
            f"{result['trigger']}: in {result['rate']:.3%} ± {result['stderr']:.3%} of {result['layouts']:,} clean "
            f"{env.size}x{env.size} layouts (exact: {result['exact_rate']:.3g})"
        )
    else:
        print(
            f"{result['trigger']}: in {result['rate']:.3%} ± {result['stderr']:.3%} of {result['layouts']:,} clean "
            f"{env.size}x{env.size} layouts with {env.num_lava} lava ({result['placements_per_layout']:.4f} placements per layout)"
        )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="rlbackdoors", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"rlbackdoors {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)

    tr = sub.add_parser("train", help="train one clean or poisoned agent into a model folder")
    tr.add_argument("--config", help="JSON config (see config.json of any model folder); flags override it")
    tr.add_argument(
        "--env",
        choices=worlds.names(),
        help=f"the world (default {worlds.DEFAULT_WORLD}); {', '.join(worlds.names('opac2'))} trains with OPAC², the others with PPO",
    )
    tr.add_argument("--arch", choices=ARCHS)
    tr.add_argument(
        "--trigger",
        help="; ".join(f"{w.name}: {w.trigger_help}" for w in worlds.registered()),
    )
    tr.add_argument("--size", type=int, help="grid size (default: the world's)")
    only = {flag: " and ".join(names) for flag, names in WORLD_FLAGS.items()}
    tr.add_argument("--num-lava", type=int, help=f"{only['num_lava']}: number of lava squares (default 10)")
    tr.add_argument("--no-curriculum", action="store_true", help=f"{only['no_curriculum']}: skip the small clean warm-up world")
    tr.add_argument(
        "--no-close-to-trigger",
        action="store_true",
        help=f"{only['no_close_to_trigger']}: train without close-to-trigger envs (they become clean copies)",
    )
    tr.add_argument("--patience", type=int, help="updates the mean training return must hold over before stopping (0: off)")
    tr.add_argument("--clean", action="store_true", help="train a clean model (the trigger is still used for evaluation)")
    tr.add_argument("--seed", type=int)
    tr.add_argument("--max-frames", type=int)
    tr.add_argument("--eval-episodes", type=int)
    tr.add_argument("--engine", choices=ENGINES)
    tr.add_argument("--device", choices=("cpu", "cuda", "auto"))
    tr.add_argument("--out", required=True, help="model folder to write")
    tr.add_argument("--overwrite", action="store_true", help="replace a finished model in --out")
    tr.add_argument("--quiet", action="store_true", help="no progress bar")
    tr.add_argument("--json", action="store_true", help="print metrics as JSON")
    from rlbackdoors.safety_cli import add_train_args

    add_train_args(tr)  # Safety Car Goal's OPAC² flags (the shared ones above stay as they are)
    tr.set_defaults(func=cmd_train)

    ev = sub.add_parser("evaluate", help="clean and triggered success rates of a model folder or a bare state dict")
    ev.add_argument("folder", nargs="?", help="model folder")
    ev.add_argument("--weights", help="a torch.save()-d state dict, e.g. a TrojAI round model")
    ev.add_argument("--arch", choices=ARCHS)
    ev.add_argument("--env", choices=ENVS)
    ev.add_argument("--trigger", help="trigger to measure poisoned SR under (default: the folder's)")
    ev.add_argument("--engine", choices=ENGINES)
    ev.add_argument("--episodes", type=int, default=None, help="episodes per condition (default 200; Safety Car Goal: the folder's final_eval_episodes)")
    ev.add_argument("--seed", type=int, help="first env seed of the evaluation layouts (default 1000000; Safety Car Goal: the folder's)")
    ev.add_argument("--policy", choices=EVAL_POLICIES)
    ev.add_argument("--json", action="store_true")
    ev.add_argument("--allow-unfinished", action="store_true", help="evaluate a folder whose run has not finished (no metrics.json)")
    ev.set_defaults(func=cmd_evaluate)

    de = sub.add_parser("demo", help="train a clean and a poisoned LavaWorld agent, evaluate both, show the backdoor")
    de.add_argument("--out", default="runs/demo")
    de.add_argument("--max-frames", type=int, default=3_000_000)
    de.add_argument("--seed", type=int, default=0)
    de.add_argument("--quiet", action="store_true")
    de.set_defaults(func=cmd_demo)

    ch = sub.add_parser("chance", help="how often a layout trigger occurs by chance in clean layouts")
    layout_worlds = [w for w in worlds.registered() if w.chance is not None]
    ch.add_argument("--env", choices=[w.name for w in layout_worlds], default=layout_worlds[0].name)
    ch.add_argument(
        "--trigger",
        required=True,
        help="; ".join(f"{w.name}: {w.trigger_help}" for w in layout_worlds) + " (a bare kind is drawn with --seed)",
    )
    ch.add_argument("--size", type=int)
    ch.add_argument("--num-lava", type=int)
    ch.add_argument("--layouts", type=int, default=100_000)
    ch.add_argument("--seed", type=int, default=12_345)
    ch.add_argument("--json", action="store_true")
    ch.set_defaults(func=cmd_chance)

    be = sub.add_parser("bench", help="speed benchmarks, measured side by side with Farama MiniGrid")
    be.add_argument(
        "what",
        choices=("env", "train", "converge", "safety"),
        help="env: engine steps/s; train: PPO frames/s (10 envs, FC and CNN); converge: wall-clock to a converged "
        "poisoned FC; safety: Safety Car Goal steps/s vs a plain mujoco loop",
    )
    be.add_argument("--seconds", type=float, default=3.0)
    be.add_argument("--num-envs", type=int, default=256)
    be.add_argument("--seed", type=int, default=0, help="converge: training seed")
    be.add_argument("--quiet", action="store_true", help="converge: no progress bar")
    be.add_argument("--json", help="also write the result to this JSON file")
    be.set_defaults(func=cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    episodes = getattr(args, "episodes", None)
    if episodes is not None and not 1 <= episodes <= MAX_EPISODES:
        parser.error(f"--episodes must be in 1..{MAX_EPISODES:,}, got {episodes}")
    return report_errors(lambda: args.func(args))


if __name__ == "__main__":
    sys.exit(main())
