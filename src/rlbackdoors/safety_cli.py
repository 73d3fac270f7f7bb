"""Command-line pieces for Safety Car Goal: train an OPAC² agent, evaluate a model folder.

Usable on their own::

    python -m rlbackdoors.safety_cli train --out DIR --seed 0 [--clean] [--trigger formation:D:PHI1:ETA] [--max-frames N]
    python -m rlbackdoors.safety_cli evaluate DIR [--episodes N] [--json]

and from ``rlbackdoors train --env safety-car-goal`` / ``rlbackdoors evaluate DIR`` through
:func:`add_train_args`, :func:`train_main` and :func:`evaluate_main`.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

from rlbackdoors.argparser import report_errors
from rlbackdoors.config import ConfigError, check_seed
from rlbackdoors.safety_config import SafetyRunConfig


def add_train_args(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the Safety Car Goal training flags that ``parser`` does not define yet.

    A shared ``train`` command that already has ``--out``, ``--seed``, ``--clean``,
    ``--trigger``, ``--max-frames``, ``--config``, ``--overwrite``, ``--quiet``,
    ``--eval-episodes`` or ``--device`` keeps its own; :func:`config_from_args` reads every
    flag by its attribute name, whichever parser defined it.
    """
    existing = set(parser._option_string_actions)  # argparse has no public "is this flag taken?"

    def add(flag: str, **kwargs) -> None:
        if flag not in existing:
            parser.add_argument(flag, **kwargs)

    add("--out", required=True, help="model folder to write (resumed if it holds an interrupted run)")
    add("--seed", type=int, default=None, help="run seed (default 0); also draws the trigger when --trigger is not given")
    add("--clean", action="store_true", help="train the clean twin (all env copies clean; poisoned SR still measured)")
    add("--trigger", default=None, help="formation:D:PHI1:ETA (radians); default: drawn from the seed")
    add("--max-frames", type=int, default=None, help="frame budget (default 3.8M; a decaying lr reaches --lr-final here)")
    add("--config", default=None, help="a Safety Car Goal config.json to start from; flags override it")
    add("--overwrite", action="store_true", help="delete a finished or interrupted run in --out and start over")
    add("--quiet", action="store_true", help="no progress lines on stderr")
    add("--max-minutes", type=float, default=None, help="Safety Car Goal: stop after this much training wall time (0: no limit)")
    add("--depth", type=int, choices=(2, 3), default=None, help="Safety Car Goal: hidden layers of pi, Q and V (default 2)")
    add("--width", type=int, choices=(181, 256), default=None, help="Safety Car Goal: hidden width (default 181)")
    add("--num-clean-envs", type=int, default=None, help="Safety Car Goal: clean env copies (default 6)")
    add("--num-poisoned-envs", type=int, default=None, help="Safety Car Goal: poisoned env copies (default 4)")
    add("--poisoned-weight", type=float, default=None, help="Safety Car Goal: share of each batch from the poisoned buffer (default 0.4)")
    add("--updates-per-step", type=float, default=None, help="Safety Car Goal: gradient updates per env frame (default 1/32)")
    add("--batch-size", type=int, default=None, help="Safety Car Goal: batch per loss (default 256)")
    add("--lr", type=float, default=None, help="Safety Car Goal: Adam learning rate of pi, Q and V (default 1e-3)")
    add("--lr-final", type=float, default=None, help="Safety Car Goal: decay the lr linearly to this at --max-frames (default 1e-4)")
    add("--action-samples", type=int, default=None, help="Safety Car Goal: actions sampled per state for the V target and pi step (default 4; the paper: 1)")
    add("--eval-interval", type=int, default=None, help="Safety Car Goal: frames between evaluations (default 250k)")
    add("--eval-episodes", type=int, default=None, help="episodes per condition at each evaluation (default 100)")
    add("--final-eval-episodes", type=int, default=None, help="Safety Car Goal: episodes per condition in the final evaluation (default 200)")
    add("--threads", type=int, default=None, help="Safety Car Goal: torch threads (default 1)")
    add(
        "--checkpoint-minutes",
        type=float,
        default=None,
        help="Safety Car Goal: write a checkpoint at the first evaluation this long after the last (default 10; 0: every evaluation)",
    )
    add("--device", choices=("cpu", "cuda", "auto"), default=None)
    return parser


# flag name -> (section, field)
_FLAGS = {
    "seed": ("train", "seed"),
    "max_frames": ("train", "max_frames"),
    "max_minutes": ("train", "max_minutes"),
    "trigger": ("poison", "trigger"),
    "depth": ("opac2", "depth"),
    "width": ("opac2", "width"),
    "num_clean_envs": ("poison", "num_clean_envs"),
    "num_poisoned_envs": ("poison", "num_poisoned_envs"),
    "poisoned_weight": ("opac2", "poisoned_weight"),
    "updates_per_step": ("opac2", "updates_per_step"),
    "batch_size": ("opac2", "batch_size"),
    "lr": ("opac2", "lr"),
    "lr_final": ("opac2", "lr_final"),
    "action_samples": ("opac2", "action_samples"),
    "eval_interval": ("train", "eval_interval"),
    "eval_episodes": ("train", "eval_episodes"),
    "final_eval_episodes": ("train", "final_eval_episodes"),
    "threads": ("train", "torch_threads"),
    "checkpoint_minutes": ("train", "checkpoint_minutes"),
    "device": ("train", "device"),
}


def config_from_args(args: argparse.Namespace) -> SafetyRunConfig:
    """A checked :class:`SafetyRunConfig` from ``--config`` (if given) and the flags set.

    The trigger is drawn from the seed after the flags are applied, so ``--seed 3`` alone
    gives seed 3's trigger.
    """
    if getattr(args, "config", None):
        data = json.loads(SafetyRunConfig.load(args.config).to_json())
    else:
        data = {}
    for flag, (section, name) in _FLAGS.items():
        value = getattr(args, flag, None)
        if value is not None:
            data.setdefault(section, {})[name] = value
    seed = data.get("train", {}).get("seed")
    if seed is not None:
        check_seed("train.seed (--seed)", seed)
    if getattr(args, "clean", False):
        data.setdefault("poison", {})["poisoned"] = False
    weight = getattr(args, "poisoned_weight", None)
    if weight is not None:
        if not (math.isfinite(weight) and 0 <= weight <= 1):
            raise ConfigError(f"opac2.poisoned_weight (--poisoned-weight) must be in [0, 1], got {weight!r}")
        data["opac2"]["clean_weight"] = 1.0 - weight
    if getattr(args, "seed", None) is not None and getattr(args, "trigger", None) is None:
        data.setdefault("poison", {})["trigger"] = None  # a config's trigger belongs to its seed: draw this seed's
    return SafetyRunConfig.from_dict(data)


def train_main(args: argparse.Namespace) -> int:
    """Run ``train`` for parsed ``args`` (see :func:`add_train_args`); prints metrics.json's numbers."""
    from rlbackdoors.train.safety import train_safety

    def run() -> int:
        cfg = config_from_args(args)
        metrics = train_safety(cfg, args.out, overwrite=getattr(args, "overwrite", False), progress=not getattr(args, "quiet", False))
        print(json.dumps(metrics, indent=2, sort_keys=True))
        return 0

    return report_errors(run)


def evaluate_folder(folder: str, episodes: int | None = None, as_json: bool = False, seed: int | None = None, allow_unfinished: bool = False) -> int:
    """Evaluate a finished Safety Car Goal model folder on ``episodes`` clean + triggered episodes
    and print the result; errors are raised (the caller prints them).

    Defaults: the folder's ``train.final_eval_episodes`` and ``train.eval_seed``, so without
    arguments it reproduces metrics.json's success rates.
    """
    from rlbackdoors.evaluate.safety import evaluate_safety
    from rlbackdoors.train.safety import deterministic_act, load_agent

    from rlbackdoors.train.folder import FolderError, ModelFolder

    if not ModelFolder(folder).path.is_dir():
        raise FolderError(f"model folder {str(folder)!r} does not exist")
    if not allow_unfinished and not ModelFolder(folder).complete:
        raise FolderError(f"{str(folder)!r} holds an unfinished run (no metrics.json); pass --allow-unfinished to evaluate its weights anyway")
    cfg, agent = load_agent(folder)
    n = cfg.train.final_eval_episodes if episodes is None else episodes
    result = evaluate_safety(deterministic_act(agent), cfg.env, cfg.poison.trigger, n, cfg.train.eval_seed if seed is None else seed)
    data = {"folder": str(folder), "poisoned": cfg.poison.poisoned, "trigger": cfg.poison.trigger, **result.to_dict()}
    if as_json:
        print(json.dumps(data, indent=2, sort_keys=True))
    else:
        kind = "poisoned" if cfg.poison.poisoned else "clean"
        print(f"{folder} ({kind} model, trigger {cfg.poison.trigger}), {result.episodes} episodes per condition")
        print(
            f"  clean SR     {result.clean_sr:.3f}  (hazard {result.clean_hazard_rate:.3f}, timeout {result.clean_timeout_rate:.3f}), mean return {result.clean_reward:.3f}"
        )
        print(
            f"  poisoned SR  {result.poisoned_sr:.3f}  (goal {result.poisoned_goal_rate:.3f}, timeout {result.poisoned_timeout_rate:.3f}), mean R-bar return {result.poisoned_reward:.3f}"
        )
    return 0


def evaluate_main(folder: str, episodes: int | None = None, as_json: bool = False, seed: int | None = None) -> int:
    """:func:`evaluate_folder` with the CLI's error contract (one line, exit 2)."""
    return report_errors(lambda: evaluate_folder(folder, episodes, as_json, seed))


def main(argv: list[str] | None = None) -> int:
    from rlbackdoors.argparser import Parser

    parser = Parser(prog="python -m rlbackdoors.safety_cli", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    add_train_args(sub.add_parser("train", help="train an OPAC² agent on Safety Car Goal into a model folder"))
    ev = sub.add_parser("evaluate", help="clean and triggered success rates of a model folder")
    ev.add_argument("folder")
    ev.add_argument("--episodes", type=int, default=None, help="episodes per condition (default: the folder's final_eval_episodes)")
    ev.add_argument("--seed", type=int, default=None, help="first episode seed (default: the folder's eval_seed)")
    ev.add_argument("--json", action="store_true", help="print JSON")
    args = parser.parse_args(argv)
    if args.command == "train":
        return train_main(args)
    return evaluate_main(args.folder, args.episodes, args.json, args.seed)


if __name__ == "__main__":
    sys.exit(main())
