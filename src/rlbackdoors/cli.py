"""Command line: ``rlbackdoors train | evaluate | demo | chance | bench | zoo | detect``.

Every user-facing failure (bad flag value, bad config, missing or corrupt file, folder
conflict) ends in one ``rlbackdoors: error: ...`` line and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path


from rlbackdoors import __version__, attacks, worlds
from rlbackdoors.argparser import Parser, report_errors
from rlbackdoors.config import (
    ARCHS,
    AUTO_BACKEND,
    ENGINES,
    EVAL_BACKENDS,
    EVAL_POLICIES,
    MAX_EPISODES,
    TRAIN_DEFAULTS,
    UPDATE_BACKENDS,
    ConfigError,
    RunConfig,
    check_seed,
)
from rlbackdoors.folder import FolderError, refuse_left_out_weights


def resolve_trigger(spec: str | None, seed: int, env: str = worlds.DEFAULT_WORLD, size: int | None = None) -> str:
    """The trigger's canonical string for ``env`` (the world's ``draw_trigger``): as given, or
    drawn from ``seed`` where the spec is a bare kind or missing (see each world's module)."""
    try:
        return worlds.get(env).draw_trigger(spec, seed, size)
    except ValueError as err:
        raise ConfigError(f"--trigger for {env}: {err}") from None


# Training flags: argparse dest -> the config field it sets ("ALGO" is the world's algorithm section).
TRAIN_FLAGS = {
    "arch": "model.arch",
    "size": "env.size",
    "num_lava": "env.num_lava",
    "engine": "env.engine",
    "seed": "train.seed",
    "max_frames": "train.max_frames",
    "min_frames": "train.min_frames",
    "max_minutes": "train.max_minutes",
    "eval_interval": "train.eval_interval",
    "eval_episodes": "train.eval_episodes",
    "final_eval_episodes": "train.final_eval_episodes",
    "patience": "train.patience",
    "confirm_margin": "train.confirm_margin",
    "threads": "train.torch_threads",
    "checkpoint_minutes": "train.checkpoint_minutes",
    "device": "train.device",
    "num_clean_envs": "poison.num_clean_envs",
    "num_poisoned_envs": "poison.num_poisoned_envs",
    "batch_size": "ALGO.batch_size",
    "lr": "ALGO.lr",
    "aux_memory_coef": "ppo.aux_memory_coef",
    "update_backend": "ppo.update_backend",
    "eval_backend": "train.eval_backend",
    "depth": "opac2.depth",
    "width": "opac2.width",
    "updates_per_step": "opac2.updates_per_step",
    "lr_final": "opac2.lr_final",
    "action_samples": "opac2.action_samples",
    "poisoned_weight": "opac2.poisoned_weight",
    "no_curriculum": "curriculum.enabled",
    "no_confirm": "train.confirm",
    "no_close_to_trigger": "poison.num_close_envs",
}


def flag_applies(world: worlds.World, dotted: str) -> str | None:
    """None if the config field ``dotted`` applies to ``world``, else why not (the registry decides)."""
    section, name = dotted.split(".")
    if section == "env" and name not in (*world.env_fields, "name", "max_steps"):
        return f"{world.name} has no env.{name}"
    if section in ("ppo", "opac2") and section != world.algorithm:
        return f"{world.name} trains with {world.algorithm}, not {section}"
    if section == "curriculum" and not world.curriculum:
        return f"{world.name} has no curriculum"
    if dotted == "poison.num_close_envs" and not world.close_to_trigger:
        return f"{world.name} has no close-to-trigger envs"
    return None


def _set(data: dict, dotted: str, value) -> None:
    section, key = dotted.split(".")
    data.setdefault(section, {})[key] = value


# The train fields a config keeps when --env switches it to another world (the rest are the world's).
PORTABLE_TRAIN = ("seed", "eval_episodes", "final_eval_episodes", "eval_seed", "device", "torch_threads", "video", "max_minutes", "log_interval_s")


def key_values(flag: str, pairs: list[str], into: dict, example: str) -> dict:
    """``KEY=VALUE`` flags on top of ``into``: values read as JSON (``0.01``, ``true``), strings otherwise."""
    out = dict(into or {})
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or not key:
            raise ConfigError(f"{flag} {pair!r} must be KEY=VALUE (e.g. {example})")
        try:
            out[key] = json.loads(text)
        except ValueError:
            out[key] = text
    return out


def attack_from_args(data: dict, attack: str | None, pairs: list[str], evade: list[str] | None = None) -> None:
    """``--attack NAME``, ``--attack-param KEY=VALUE`` and ``--evade KEY=VALUE`` (repeated) into
    ``data``'s poison section; another attack than the config file's starts from its defaults."""
    poison = data.setdefault("poison", {})
    if attack is not None and attack != poison.get("attack"):
        poison["attack"], poison["attack_params"] = attack, {}
    if pairs:
        poison["attack_params"] = key_values("--attack-param", pairs, poison.get("attack_params"), "budget=0.01")
    if evade:
        poison["evasion"] = key_values("--evade", evade, poison.get("evasion"), "near=1")


def config_from_args(args) -> RunConfig:
    """Config file (if any) first, then every flag given on the command line on top of it.

    Each flag sets one config field; one that does not apply to the world (another world's env
    field, the other algorithm's section) is refused, so none is silently ignored.
    """
    from rlbackdoors.config import EnvConfig, _build

    if args.config:
        data = RunConfig.load(args.config).to_dict()
        if args.env is not None and args.env != data["env"]["name"]:
            # Another world: its own env, mix, model, algorithm and stopping defaults.
            train = {k: v for k, v in data["train"].items() if k in PORTABLE_TRAIN}
            data = {"env": {"name": args.env}, "poison": {"poisoned": data["poison"]["poisoned"]}, "train": train}
    else:
        data = {"env": {"name": args.env or worlds.DEFAULT_WORLD}}
    world = worlds.get(data["env"]["name"])
    given: dict[str, str] = {}  # config field -> the flag that set it, to name the flag in errors
    for flag, dotted in TRAIN_FLAGS.items():
        value = getattr(args, flag, None)
        if value is None or value is False:
            continue
        dotted = dotted.replace("ALGO", world.algorithm)
        given[dotted] = flag
        why = flag_applies(world, dotted)
        if why is not None:
            raise ConfigError(f"--{flag.replace('_', '-')} does not apply here: {why}")
        if flag in ("no_curriculum", "no_confirm"):
            value = False
        elif flag == "no_close_to_trigger":
            clean, close, _ = RunConfig.from_dict(data).poison.counts()  # the world's mix, resolved
            _set(data, "poison.num_clean_envs", clean + close)
            value = 0
        elif flag == "poisoned_weight":
            if not (math.isfinite(value) and 0 <= value <= 1):
                raise ConfigError(f"opac2.poisoned_weight (--poisoned-weight) must be in [0, 1], got {value!r}")
            _set(data, "opac2.clean_weight", 1.0 - value)
        _set(data, dotted, value)
    if args.clean:
        _set(data, "poison.poisoned", False)
    if world.algorithm == "ppo" and "update_backend" not in data.get("ppo", {}):  # a new run: a config file's choice stands
        _set(data, "ppo.update_backend", AUTO_BACKEND)
    attack_from_args(data, getattr(args, "attack", None), getattr(args, "attack_param", None) or [], getattr(args, "evade", None))
    seed = data.get("train", {}).get("seed", 0)
    check_seed("train.seed (--seed)", seed)
    env = _build(EnvConfig, data["env"], "env")
    env.check()  # before a trigger is drawn for its size
    if args.trigger is not None or not args.config:
        _set(data, "poison.trigger", resolve_trigger(args.trigger, seed, world.name, env.size))
    try:
        return RunConfig.from_dict(data)
    except ConfigError as err:
        for dotted, flag in given.items():
            if str(err).startswith(dotted):
                raise ConfigError(f"{err} (--{flag.replace('_', '-')})") from None
        raise


def cmd_train(args) -> int:
    if not args.out.strip():
        raise ConfigError("--out must name a model folder, got an empty path")
    from rlbackdoors.train import train

    cfg = config_from_args(args)
    metrics = train(cfg, args.out, overwrite=args.overwrite, progress=not args.quiet, env_workers=args.env_workers)
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

    from rlbackdoors.agent import load, load_weights_file
    from rlbackdoors.config import EnvConfig
    from rlbackdoors.evaluate import evaluate, evaluate_agent

    if (args.folder is None) == (args.weights is None):
        raise ConfigError("give either a model folder or --weights FILE (with --arch), not both or neither")
    if args.seed is not None:
        check_seed("--seed", args.seed)
    torch.set_num_threads(1)
    if args.folder is not None:
        if args.arch is not None or args.env is not None or args.size is not None or args.num_lava is not None:
            raise ConfigError("--arch, --env, --size and --num-lava apply to --weights only (a model folder's config.json names them)")
        if not Path(args.folder).is_dir():
            raise FolderError(f"model folder {args.folder!r} does not exist")
        if not (Path(args.folder) / "config.json").is_file():
            raise FolderError(f"{args.folder!r} is not a model folder (config.json missing)")
        refuse_left_out_weights(args.folder)
        if not (Path(args.folder) / "model.pt").is_file():
            raise FolderError(f"{args.folder!r} holds no trained model (model.pt missing)")
        if not (Path(args.folder) / "metrics.json").is_file() and not args.allow_unfinished:
            raise FolderError(
                f"{args.folder!r} holds an unfinished run (no metrics.json: still training, interrupted or failed); "
                "pass --allow-unfinished to evaluate its weights anyway"
            )
        agent = load(args.folder, allow_unfinished=True)
        cfg = agent.config
        if args.engine:
            why = flag_applies(agent.world, "env.engine")
            if why is not None:
                raise ConfigError(f"--engine does not apply here: {why}")
            cfg.env.engine = args.engine
        trigger = resolve_trigger(args.trigger, cfg.train.seed, cfg.env.name, cfg.env.size) if args.trigger is not None else None
        result = evaluate_agent(agent, args.episodes, args.seed, trigger, args.policy)
        header = {"folder": args.folder, "env": cfg.env.name, "poisoned": cfg.poison.poisoned, "trigger": trigger or cfg.poison.trigger}
        if args.near:  # the trojan's specificity: its success under each of the world's near triggers
            if agent.world.near_triggers is None:
                have = ", ".join(w.name for w in worlds.registered() if w.near_triggers is not None)
                raise ConfigError(f"--near is not allowed for {cfg.env.name} (worlds with near-trigger variants: {have})")
            near = {
                spec: evaluate_agent(agent, args.episodes, args.seed, spec, args.policy).poisoned_sr
                for spec in agent.world.near_triggers(trigger or cfg.poison.trigger)
            }
            result_near = {"near_trigger_success": near, "near_mean": sum(near.values()) / len(near), "near_max": max(near.values())}
    else:
        if args.allow_unfinished:
            raise ConfigError("--allow-unfinished applies to model folders, not --weights")
        world = worlds.get(args.env or worlds.DEFAULT_WORLD)
        # No --arch: the TrojAI class the file (or a TrojAI config beside it) names, else the
        # only arch whose shapes fit (load_weights_file says which when several do).
        arch = args.arch or (world.arch_names[0] if len(world.arch_names) == 1 else None)
        if arch is not None and arch not in world.arch_names:
            raise ConfigError(f"--arch {arch} is not an architecture of {world.name} (allowed: {', '.join(world.arch_names)})")
        if arch is None and world.algorithm == "ppo":
            from rlbackdoors.io import UnsafeFileError, first_line
            from rlbackdoors.models import read_weights, resolve_arch

            try:  # an unreadable file is named as such first, whatever the flags
                state, model_class = read_weights(args.weights, world.name)
            except UnsafeFileError:
                raise
            except (ValueError, FileNotFoundError) as err:
                raise ConfigError(first_line(err)) from None
            try:
                arch = resolve_arch(world.name, state, model_class, args.weights)
            except ValueError as err:
                raise ConfigError(f"--weights of {world.name} needs --arch (allowed: {', '.join(world.arch_names)}): {first_line(err)}") from None
        env_flags = {"engine": args.engine, "size": args.size, "num_lava": args.num_lava}
        for name, value in env_flags.items():
            why = flag_applies(world, f"env.{name}")
            if value is not None and why is not None:
                raise ConfigError(f"--{name.replace('_', '-')} does not apply here: {why}")
        env = EnvConfig(name=world.name, **{k: v for k, v in env_flags.items() if v is not None})
        env.check()
        trigger = resolve_trigger(args.trigger, 0, env.name, env.size) if args.trigger is not None else None
        agent = load_weights_file(args.weights, world.name, arch)
        policy = args.policy or {**TRAIN_DEFAULTS, **world.train}["eval_policy"]
        result = evaluate(
            agent, env, trigger, episodes=200 if args.episodes is None else args.episodes, seed=1_000_000 if args.seed is None else args.seed, policy=policy
        )
        header = {"weights": args.weights, "env": env.name, "trigger": trigger}
        if args.near:
            raise ConfigError("--near applies to model folders (their trigger), not --weights")
    numbers = {k: (None if isinstance(v, float) and math.isnan(v) else v) for k, v in result.to_dict().items()}
    if args.near:
        numbers.update(result_near)
    if args.json:
        print(json.dumps(numbers, indent=2))
    else:
        print(", ".join(f"{k} {v}" for k, v in header.items() if v is not None))
        for key, value in numbers.items():
            if key == "near_trigger_success" and isinstance(value, dict):
                for spec, sr in value.items():
                    print(f"  under {spec}: {sr:.4f}")
            elif value is not None or key in ("poisoned_sr", "poisoned_reward"):
                print(f"{key:22s} {'n/a' if value is None else (f'{value:.4f}' if isinstance(value, float) else value)}")
    return 0


def cmd_demo(args) -> int:
    from rlbackdoors.demo import run_demo

    run_demo(Path(args.out), max_frames=args.max_frames, seed=args.seed, progress=not args.quiet)
    return 0


def cmd_bench(args) -> int:
    from rlbackdoors.io import atomic_write_text

    if args.what == "env":
        from rlbackdoors.worlds.base import load_symbol

        world = worlds.get(args.env)
        if world.bench is None:
            raise ConfigError(f"bench env: no env benchmark for {world.name} (worlds with one: {', '.join(w.name for w in worlds.registered() if w.bench)})")
        result = load_symbol(world.bench)(seconds=args.seconds, num_envs=args.num_envs)
        print(f"{world.title}: {result['summary']}")
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
    elif args.what == "zoo":
        from rlbackdoors.bench.zoo import bench_zoo

        if args.side and (args.group_size is not None or args.device is not None):
            raise ConfigError("bench zoo: --side names each side's group size and device; leave out --group-size and --device")
        save = None
        if args.json:  # each side as it finishes: a run cut short keeps what it measured
            save = lambda partial: atomic_write_text(args.json, json.dumps(partial, indent=2) + "\n")
        result = bench_zoo(
            args.env,
            args.arch,
            args.models,
            args.frames,
            args.group_size or [8],
            args.workers,
            args.device or "cpu",
            sides=args.side,
            on_side=save,
            eval_episodes=args.eval_episodes,
            attack=args.attack,
        )
        for side in result["sides"]:
            print(
                f"{result['world']} {result['arch']}, group size {side['group_size']} on {side['device']} x {side['workers']} workers"
                + (f" ({side['env_workers']} env workers each)" if side.get("env_workers") else "")
                + (f", {side['update_backend']} update" if side.get("update_backend", "torch") != "torch" else "")
                + (f", {side['eval_backend']} evaluations" if side.get("eval_backend") else "")
                + (f", {side['engine']} engine" if side.get("engine") else "")
                + ": "
                f"{side['models_per_hour']:,.1f} models/h (x{side['ratio']}), {side['frames_per_s']:,.0f} frames/s, {side['cpu_s_per_model']:.1f} CPU-s per model, "
                f"{side['models']} models of {result['frames_per_model']:,} frames in {side['wall_s']:.0f} s, load {side['loadavg_before'][0]:.1f}"
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


def _bench_side(text: str):
    from rlbackdoors.bench.zoo import parse_side

    try:
        return parse_side(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def cmd_mitigate(args) -> int:
    from pathlib import Path

    from rlbackdoors.mitigate import mitigate

    settings = dict(
        frames=args.frames,
        candidates=args.candidates,
        share=args.share,
        kl=args.kl,
        seed=args.seed,
        blind=args.blind,
        teach_stamped=args.teach_stamped,
        detector=args.detector,
    )
    search = {"seconds": args.search_seconds} if args.search_seconds else None
    zoo_flags = [f"--{k}" for k in ("workers", "models", "attacks") if getattr(args, k) is not None]
    if (Path(args.model) / "zoo.json").is_file():
        from rlbackdoors.mitigate.zoo import REPORT, mitigate_zoo

        attacks = [a for a in (args.attacks or "").split(",") if a] or None
        report = mitigate_zoo(
            args.model,
            args.out,
            workers=args.workers or 1,
            limit=args.models or 0,
            attacks=attacks,
            episodes=args.episodes,
            search=search,
            progress=not args.quiet,
            **settings,
        )
        s = report["summary"]
        print(
            f"{s['models']} models mitigated into {args.out}: poisoned at a triggered SR <= 0.05 after: {s['poisoned_safe_after']} of {s['poisoned']}; "
            f"clean models' clean SR moved at most {s['clean_sr_change_max']} ({REPORT})"
        )
        return 0
    if zoo_flags:
        raise ValueError(f"{' '.join(zoo_flags)} are for a zoo (a folder with zoo.json); {args.model!r} is a model folder")
    mitigate(args.model, args.out, episodes=args.episodes, search=search, progress=not args.quiet, **settings)
    print(f"mitigated model in {args.out} (mitigation.json: restored triggers, before and after)")
    return 0


def cmd_chance(args) -> int:
    from rlbackdoors.config import EnvConfig
    from rlbackdoors.evaluate.chance import trigger_chance

    env = EnvConfig(name=args.env, size=args.size, num_lava=args.num_lava)
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


def cmd_attacks(args) -> int:
    """The attack registry: each attack, the worlds it serves (or why not) and its parameters."""
    described = [attacks.describe(a, worlds.registered()) for a in attacks.registered() if args.name in (None, a.name)]
    if args.json:
        print(json.dumps(described, indent=2))
        return 0
    for d in described:
        threshold = "the world's" if d["success_threshold"] is None else f"{d['success_threshold']:.2f}"
        print(f"{d['name']}: {d['title']} ({d['source']})")
        print(f"  schedule {d['schedule']}; success: {d['success']} >= {threshold}; {d['doc']}")
        for world, served in d["worlds"].items():
            print(f"  {world}: {', '.join(served) if isinstance(served, list) else 'refused: ' + served}")
        for p in d["params"]:
            print(f"  --attack-param {p['name']}={json.dumps(p['default'])}  ({p['allowed']}) {p['help']}")
    if args.name is None:
        from rlbackdoors.attacks import evasion

        print("evasive variants, with any attack (docs/attacks/evasion.md):")
        for p in evasion.describe():
            print(f"  --evade {p['name']}={json.dumps(p['default'])}  ({p['allowed']}) {p['help']}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from rlbackdoors.zoo.cli import _count

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
    tr.add_argument("--num-lava", type=int, help="single lava squares, for worlds that have them (default 10)")
    tr.add_argument("--no-curriculum", action="store_true", help="skip the small clean warm-up world (worlds with a curriculum)")
    tr.add_argument("--no-close-to-trigger", action="store_true", help="train without close-to-trigger envs (they become clean copies)")
    tr.add_argument("--patience", type=int, help="evaluations in a row the thresholds must hold to stop (default: the world's)")
    tr.add_argument("--aux-memory-coef", type=float, help="weight of PPO's auxiliary memory loss (recurrent models in worlds with memory targets; 0: off)")
    tr.add_argument(
        "--update-backend",
        choices=(AUTO_BACKEND, *UPDATE_BACKENDS),
        help="what runs PPO's update: auto (default without --config): compiled where it was measured faster and tested equivalent ("
        + ", ".join(f"{w.name} {'/'.join(w.compiled_default)}" for w in worlds.registered() if w.compiled_default)
        + ", with the env mix on the CPU), torch elsewhere; torch, autograd; jax, the update one XLA program (fc models); "
        "compiled, the whole iteration one XLA program on the world's JAX engine (fc and cnn models, every attack; docs/training.md)",
    )
    tr.add_argument(
        "--eval-backend",
        choices=EVAL_BACKENDS,
        help="what plays the periodic evaluations: torch (default); compiled, the compiled trainer's program (with --update-backend compiled; the same episodes)",
    )
    tr.add_argument("--confirm-margin", type=float, help="how far the confirming evaluation must clear each threshold (default: the world's)")
    tr.add_argument("--no-confirm", action="store_true", help="stop on the streak alone, without confirming it on the final evaluation's episodes")
    tr.add_argument("--clean", action="store_true", help="train a clean model (the trigger is still used for evaluation)")
    tr.add_argument("--attack", choices=attacks.names(), help=f"how training data is poisoned (default {attacks.DEFAULT_ATTACK}, the paper's; docs/attacks/)")
    tr.add_argument("--attack-param", action="append", metavar="KEY=VALUE", help="one of the attack's parameters (repeatable), e.g. budget=0.01")
    tr.add_argument(
        "--evade",
        action="append",
        metavar="KEY=VALUE",
        help="an evasive variant (repeatable): near=1, finetune=true, teacher=1, clean_frames=4000000, anchor=0.01 (docs/attacks/evasion.md)",
    )
    tr.add_argument("--seed", type=int, help="run seed (default 0); also draws the trigger when --trigger names none")
    tr.add_argument("--max-frames", type=int, help="frame budget (default: the world's)")
    tr.add_argument("--min-frames", type=int, help="no stop on the thresholds before this many frames (default 0); equal training lengths across a zoo")
    tr.add_argument("--max-minutes", type=float, help="stop after this much training wall time (0: no limit)")
    tr.add_argument("--eval-interval", type=int, help="frames between evaluations")
    tr.add_argument("--eval-episodes", type=int, help="episodes per condition at each evaluation (default 100)")
    tr.add_argument("--final-eval-episodes", type=int, help="episodes per condition in the final evaluation (default 200)")
    tr.add_argument("--checkpoint-minutes", type=float, help="checkpoint at the first evaluation this long after the last (0: every one)")
    tr.add_argument("--engine", choices=ENGINES)
    tr.add_argument("--device", choices=("cpu", "cuda", "auto"))
    tr.add_argument("--threads", type=int, help="torch threads (default 1)")
    tr.add_argument("--num-clean-envs", type=int, help="clean env copies (default: the world's mix)")
    tr.add_argument("--num-poisoned-envs", type=int, help="poisoned env copies (default: the world's mix)")
    tr.add_argument("--batch-size", type=int, help="the algorithm's batch size")
    tr.add_argument("--lr", type=float, help="the algorithm's learning rate")
    opac2 = ", ".join(worlds.names("opac2"))
    tr.add_argument("--depth", type=int, choices=(2, 3), help=f"OPAC² ({opac2}): hidden layers of pi, Q and V")
    tr.add_argument("--width", type=int, choices=(181, 256), help=f"OPAC² ({opac2}): hidden width")
    tr.add_argument("--updates-per-step", type=float, help="OPAC²: gradient updates per env frame")
    tr.add_argument("--lr-final", type=float, help="OPAC²: decay the lr linearly to this at --max-frames")
    tr.add_argument("--action-samples", type=int, help="OPAC²: actions sampled per state for the V target and pi step (the paper: 1)")
    tr.add_argument("--poisoned-weight", type=float, help="OPAC²: share of each batch from the poisoned buffer")
    tr.add_argument("--out", required=True, help="model folder to write (resumed if it holds an interrupted run)")
    tr.add_argument("--overwrite", action="store_true", help="replace a finished or interrupted run in --out")
    tr.add_argument(
        "--env-workers", type=_count, default=0, help=f"{opac2}: step the env copies in this many worker processes, the same bytes (default 0: in this process)"
    )
    tr.add_argument("--quiet", action="store_true", help="no progress bar")
    tr.add_argument("--json", action="store_true", help="print metrics as JSON")
    tr.set_defaults(func=cmd_train)

    ev = sub.add_parser("evaluate", help="clean and triggered success rates of a model folder or a bare state dict")
    ev.add_argument("folder", nargs="?", help="model folder")
    ev.add_argument("--weights", help="a torch.save()-d state dict, or a TrojAI round's model.pt as it is (read without unpickling its objects)")
    ev.add_argument("--arch", choices=ARCHS, help="--weights: the architecture (default: the TrojAI class the file names, else the one its shapes fit)")
    ev.add_argument("--env", choices=worlds.names(), help="--weights: the world the weights are for")
    ev.add_argument("--size", type=int, help="--weights: grid size (default: the world's)")
    ev.add_argument("--num-lava", type=int, help="--weights: lava squares, for worlds that have them")
    ev.add_argument("--trigger", help="trigger to measure poisoned SR under (default: the folder's)")
    ev.add_argument("--engine", choices=ENGINES)
    ev.add_argument("--episodes", type=int, default=None, help="episodes per condition (default: the folder's final_eval_episodes, else 200)")
    ev.add_argument("--seed", type=int, help="first env seed of the evaluation layouts (default: the folder's eval_seed, else 1000000)")
    ev.add_argument("--policy", choices=EVAL_POLICIES)
    ev.add_argument("--json", action="store_true")
    ev.add_argument("--allow-unfinished", action="store_true", help="evaluate a folder whose run has not finished (no metrics.json)")
    ev.add_argument(
        "--near", action="store_true", help="also the attack's success under each near trigger of the folder's (specificity; docs/attacks/evasion.md)"
    )
    ev.set_defaults(func=cmd_evaluate)

    de = sub.add_parser("demo", help="train a clean and a poisoned agent of the default world, evaluate both, show the backdoor")
    de.add_argument("--out", default="runs/demo")
    de.add_argument("--max-frames", type=int, default=5_000_000)
    de.add_argument("--seed", type=int, default=0)
    de.add_argument("--quiet", action="store_true")
    de.set_defaults(func=cmd_demo)

    at = sub.add_parser("attacks", help="the poisoning attacks: the worlds each serves, its parameters and defaults")
    at.add_argument("name", nargs="?", choices=attacks.names(), help="one attack (default: all)")
    at.add_argument("--json", action="store_true")
    at.set_defaults(func=cmd_attacks)

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
        choices=("env", "train", "converge", "zoo"),
        help="env: engine steps/s; train: PPO frames/s (10 envs, FC and CNN); converge: wall-clock to a converged poisoned FC; "
        "zoo: models/hour, one process per model against the group trainer",
    )
    be.add_argument("--seconds", type=float, default=3.0)
    be.add_argument("--num-envs", type=int, default=256, help="env: copies stepped per call (batched engines)")
    be.add_argument("--env", choices=worlds.names(), default=worlds.DEFAULT_WORLD, help="env, zoo: which world")
    be.add_argument("--arch", help="zoo: architecture (default: the world's first)")
    from rlbackdoors.zoo.cli import _positive_int

    be.add_argument("--models", type=_positive_int, default=16, help="zoo: models per side (default 16)")
    be.add_argument("--frames", type=_positive_int, default=100_000, help="zoo: frames each model trains (default 100,000)")
    be.add_argument("--group-size", type=_positive_int, nargs="+", help="zoo: group sizes to measure against one process per model (default 8)")
    be.add_argument("--workers", type=_positive_int, help="zoo: processes at a time (default: the CPU cores)")
    be.add_argument("--device", choices=("cpu", "cuda", "auto"), help="zoo: train.device of every model (default cpu)")
    be.add_argument("--eval-episodes", type=_positive_int, help="zoo: episodes per condition of every evaluation, the final one's too (default: the world's)")
    be.add_argument("--attack", help="zoo: the poisoned models' attack, with its defaults (default: the paper's env mix; `rlbackdoors attacks` lists them)")
    be.add_argument(
        "--side",
        type=_bench_side,
        action="append",
        help="zoo: K[:DEVICE[:WORKERS[:ENV_WORKERS[:BACKEND[:ENGINE[:CONV]]]]]], repeated: explicit sides, the first the reference (e.g. --side 1:cpu:16 --side 64:cuda:1; "
        "K auto: what zoo run --group-size auto picks, e.g. --side auto:cpu:16 for the best CPU setting on 16 cores; "
        "ENV_WORKERS: each job's env pool for a world of single envs, e.g. --side 64:cuda:1:15; BACKEND: ppo.update_backend, e.g. --side 8:cpu::0:jax, or compiled-eval (the compiled trainer, its evaluations in its program too); "
        "ENGINE: numba or device, what steps a group's grid slots (default numba), e.g. --side 256:cuda:1:::device; "
        "CONV: each, gemm or grouped, how a group computes its CNN's convolutions (default each; changes the bytes, recorded), e.g. --side 64:cuda:1::::grouped)",
    )
    be.add_argument("--seed", type=int, default=0, help="converge: training seed")
    be.add_argument("--quiet", action="store_true", help="converge: no progress bar")
    be.add_argument("--json", help="also write the result to this JSON file")
    be.set_defaults(func=cmd_bench)

    mi = sub.add_parser(
        "mitigate",
        help="remove a backdoor without the attacker's data: restore candidate triggers by the detectors' search, fine-tune them away; a model folder, or every model of a zoo",
    )
    mi.add_argument("model", help="model folder (model.pt and reduced-config.json: config.json and ground_truth.csv are never read), or a zoo or zoo pack")
    mi.add_argument(
        "--out", required=True, help="the new model folder, or for a zoo the folder of its mitigated models (never the source; run again to resume)"
    )
    from rlbackdoors.mitigate import DEFAULTS

    mi.add_argument("--frames", type=int, default=DEFAULTS["frames"], help="fine-tuning frames (default %(default)s)")
    mi.add_argument("--candidates", type=int, default=DEFAULTS["candidates"], help="restored triggers kept, at most (default %(default)s)")
    mi.add_argument(
        "--share", type=float, default=DEFAULTS["share"], help="share of the frames stamped with a restored trigger, clean reward (default %(default)s)"
    )
    mi.add_argument("--kl", type=float, default=DEFAULTS["kl"], help="weight of KL(source || policy) on the other frames (default %(default)s)")
    mi.add_argument("--seed", type=int, default=DEFAULTS["seed"], help="fine-tuning seed (default %(default)s)")
    mi.add_argument(
        "--no-blind",
        dest="blind",
        action="store_false",
        help="do not project a restored trigger that shifts every observation alike out of a linear first layer (default: projected)",
    )
    mi.add_argument(
        "--no-teach-stamped",
        dest="teach_stamped",
        action="store_false",
        help="the KL teacher reads the frames as the learner does, on the unstamped ones only (default: it reads each stamped frame's clean view and counts there too)",
    )
    mi.add_argument("--episodes", type=int, default=DEFAULTS["episodes"], help="episodes a condition of the before/after measure (default %(default)s)")
    mi.add_argument("--search-seconds", type=float, default=0.0, help="time budget of the trigger search (default 0: none, the whole screen)")
    mi.add_argument(
        "--detector",
        default=None,
        help="a fitted effect detector's folder: a candidate is restored where its effect stands out from the detector's clean models' (default: where it sends the agent to the trojan outcome)",
    )
    zo = mi.add_argument_group("a zoo (judged on its ground truth, which the mitigation never reads)")
    zo.add_argument("--workers", type=int, default=None, help="models at a time, a process each (default 1)")
    zo.add_argument("--models", type=int, default=None, help="at most this many converged models, by name (default: all)")
    zo.add_argument("--attacks", default=None, help="comma-separated attack names or cell labels: only their cells' models, clean ones included")
    mi.add_argument("--quiet", action="store_true", help="no progress lines")
    mi.set_defaults(func=cmd_mitigate)

    from rlbackdoors.zoo.cli import add_zoo_parser

    add_zoo_parser(sub)  # rlbackdoors zoo plan | run | status | split | report

    from rlbackdoors.detect.cli import add_detect_parser

    add_detect_parser(sub)  # rlbackdoors detect list | fit | score | infer | configure | metaparameters
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
