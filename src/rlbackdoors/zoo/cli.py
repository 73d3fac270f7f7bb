"""``rlbackdoors zoo plan | run | verify | status | split | report | import-trojai``.

:func:`add_zoo_parser` mounts the ``zoo`` command on the main CLI's sub-parsers; ``python -m
rlbackdoors.zoo.cli plan ...`` runs the same commands on their own. Errors follow the CLI's
contract (:func:`rlbackdoors.argparser.report_errors`): one ``rlbackdoors: error: ...`` line,
exit 2; an interrupted run exits 130 and resumes when run again.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys

from rlbackdoors.argparser import Parser, sub_cli_main
from rlbackdoors.validate import ConfigError


def cmd_plan(args) -> int:
    from rlbackdoors.zoo.plan import plan
    from rlbackdoors.zoo.spec import load_spec

    spec = load_spec(args.spec)
    zoo, written = plan(spec, args.out)
    models = sum(g.wanted for g in spec.groups)
    if written:
        print(f"{args.out}: planned {models} models in {len(spec.cells)} cells ({written} folders written); run them with: rlbackdoors zoo run {args.out}")
        print(f"trainers: {_trainers(zoo)} (docs/training.md: which trainer a run takes)")
        if not spec.matched and {g.poisoned for g in spec.groups if g.wanted} == {False, True}:
            # matched = false stays the default so that older specs plan the same models; a detection
            # dataset should not be built this way unknowingly (training length alone can tell the label)
            print(
                "zoo: note: not matched: clean and poisoned models start from different seeds and stop at their own frames, so training"
                " length can tell the label; for a detection benchmark set matched = true and overrides.train.min_frames (docs/zoos.md: longer runs still show)",
                file=sys.stderr,
            )
        elif spec.matched and _unequal_frames(args.out):
            # measured in a benchmark zoo: a poisoned run that converged late trained longer
            # than its twin, and the weight statistics found those runs (docs/attacks/evasion.md)
            print(
                "zoo: note: matched, but min_frames < max_frames: a poisoned run that converges late trains longer than its clean twin,"
                " and training length can tell the label; set overrides.train.max_frames = min_frames for equal frames (docs/zoos.md)",
                file=sys.stderr,
            )
    else:
        print(f"{args.out}: already planned from this spec; nothing written")
    return 0


def cmd_replan(args) -> int:
    from rlbackdoors.zoo.plan import replan

    zoo, moved, into = replan(args.spec, args.zoo)
    kept = sum(1 for _ in zoo.models_dir.glob("id-*"))
    where = f"; moved to {into}" if into is not None else ""
    print(
        f"{args.zoo}: replanned; {len(moved)} model folders drawn otherwise by the new spec{where}; {kept} folders planned; run them with: rlbackdoors zoo run {args.zoo}"
    )
    return 0


def _trainers(zoo) -> str:
    """Which trainer each cell's models were planned on (its first planned model's config says):
    ``compiled: a, b; torch: c``; an OPAC² world's cells are named by their algorithm."""
    from rlbackdoors.config import RunConfig

    by: dict[str, list[str]] = {}
    for group in zoo.spec.groups:
        folder = zoo.folder(zoo.model(group, 0))
        if not group.wanted or not (folder / "config.json").is_file():
            continue
        cfg = RunConfig.load(folder / "config.json")
        trainer = cfg.ppo.update_backend if cfg.ppo is not None else cfg.algorithm
        if group.cell.key not in by.setdefault(trainer, []):
            by[trainer].append(group.cell.key)
    return "; ".join(f"{trainer}: {', '.join(keys)}" for trainer, keys in sorted(by.items()))


def _unequal_frames(zoo) -> bool:
    """Whether a planned zoo's models may stop at different frames (some min_frames < max_frames):
    read from the configs just planned, where each world's defaults are already filled in."""
    from pathlib import Path

    from rlbackdoors.config import RunConfig

    configs = (RunConfig.load(p).train for p in sorted(Path(zoo, "models").glob("*/config.json")))
    return any(t.min_frames < t.max_frames for t in configs)


def _imported(zoo: str, command: str) -> bool:
    """Whether ``zoo`` was imported from TrojAI; raises for the commands that do not apply to one."""
    from rlbackdoors.zoo.spec import ZooError
    from rlbackdoors.zoo.trojai_import import is_imported

    if not is_imported(zoo):
        return False
    if command in ("run", "split"):
        why = (
            "nothing to train: its models were trained by TrojAI"
            if command == "run"
            else "its triggers are not known, and TrojAI ships its own train and test rounds"
        )
        raise ZooError(f"zoo {zoo!r} was imported from TrojAI (zoo import-trojai); zoo {command} does not apply ({why})")
    return True


def cmd_import_trojai(args) -> int:
    from rlbackdoors.zoo.trojai_import import import_trojai

    summary = import_trojai(
        args.dir,
        args.out,
        world=args.world,
        arch=args.arch,
        size=args.size,
        num_lava=args.num_lava,
        max_steps=args.max_steps,
        num_cubes=args.num_cubes,
        label=args.label,
        trigger=args.trigger,
        episodes=args.eval_episodes,
        examples=args.examples,
        seed=args.seed,
        policy=args.policy,
    )
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        kinds = sorted({f"{m['world']}/{m['arch']}" + (f" ({m['class']})" if m["class"] else "") for m in summary["per_model"]})
        print(f"{args.out}: {summary['models']} TrojAI models ({', '.join(kinds)}): {summary['written']} imported, {summary['skipped']} already there")
    return 0


def cmd_run(args) -> int:
    from rlbackdoors.zoo.run import run

    _imported(args.zoo, "run")

    summary = run(
        args.zoo,
        workers=args.workers,
        backend=args.backend,
        address=args.address,
        max_retries=args.max_retries,
        retry_failed=args.retry_failed,
        progress_interval=args.progress_interval,
        retrain_tampered=args.retrain_tampered,
        group_size=args.group_size,
        env_workers=args.env_workers,
        device=args.device,
    )
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        short = f"; short of converged models: {', '.join(summary['short'])}" if summary["short"] else ""
        print(
            f"{args.zoo}: {summary['done']} of {summary['models']} models finished, {summary['converged']} converged, "
            f"{summary['failed']} failed; {summary['trained']} trained in {summary['seconds']:.0f} s{short}"
        )
    return 0


def _verified(args, command: str) -> dict[str, str]:
    """``zoo verify`` before ``command`` reads the zoo: refused if it fails, unless
    ``--skip-unverified`` (then the failing models, name -> why, are printed to stderr and
    returned for the command to leave out)."""
    from rlbackdoors.zoo.spec import ZooError
    from rlbackdoors.zoo.verify import guard, skipped_lines

    skipped = guard(args.zoo, command, args.skip_unverified)
    if skipped and _imported(args.zoo, command):
        raise ZooError(
            f"zoo {args.zoo!r} was imported from TrojAI: import it again rather than skipping models ({next(iter(skipped))}: {next(iter(skipped.values()))})"
        )
    if command != "status":  # status names them under its table
        for line in skipped_lines(skipped):
            print(f"zoo {command}: {line}", file=sys.stderr)
    return skipped


def cmd_verify(args) -> int:
    from rlbackdoors.zoo.spec import ZooError
    from rlbackdoors.zoo.verify import verify

    result = verify(args.zoo, write_manifest=args.write_manifest, expect=args.expect)
    if args.json:
        print(
            json.dumps(
                {"ok": result.ok, "models": result.models, "problems": result.problems, "adopted": result.adopted, "digest": f"sha256:{result.digest}"},
                indent=2,
            )
        )
    else:
        for name in result.adopted:
            print(f"{name}: {MANIFEST_WRITTEN}")
        for line in result.lines():
            print(line)
    if not result.ok:
        raise ZooError(f"{result.summary()}; {result.remedy()}")
    if not args.json:
        print(f"{args.zoo}: {result.models} model folders verified; digest sha256:{result.digest} (publish it; check with --expect)")
    return 0


def cmd_pack(args) -> int:
    from rlbackdoors.zoo.pack import pack

    packed = pack(args.zoo, args.out, converged_weights_only=args.converged_weights_only)
    if args.json:
        print(json.dumps({**dataclasses.asdict(packed), "out": str(packed.out)}))
    else:
        print(packed.line())
    return 0


def cmd_status(args) -> int:
    skipped = _verified(args, "status")
    if _imported(args.zoo, "status"):
        from rlbackdoors.zoo.trojai_import import status as imported_status

        print(imported_status(args.zoo))
        return 0
    from rlbackdoors.zoo.run import status

    print(status(args.zoo, skipped))
    return 0


def cmd_split(args) -> int:
    from rlbackdoors.zoo.split import split

    _imported(args.zoo, "split")
    skipped = _verified(args, "split")
    hold_out = args.hold_out_attack or None
    if hold_out is None and (args.train is None or args.test is None):
        raise ConfigError("zoo split needs --train and --test shares (or --hold-out-attack NAME)")
    if hold_out is not None and (args.train is not None or args.test is not None):
        raise ConfigError("--hold-out-attack decides the split itself; drop --train and --test")
    result = split(
        args.zoo, args.train or 0.0, args.test or 0.0, args.out_train, args.out_test, seed=args.seed, link=args.link, skip=skipped, hold_out_attacks=hold_out
    )
    for name, out in (("train", args.out_train), ("test", args.out_test)):
        r = result[name]
        print(f"{name}: {out}: {r['models']} models ({r['poisoned']} poisoned)")
    if skipped:
        print(f"{len(skipped)} models failed verification and were left out (split.json names them)")
    return 0


def cmd_report(args) -> int:
    skipped = _verified(args, "report")
    if _imported(args.zoo, "report"):
        from rlbackdoors.zoo.trojai_import import report as imported_report

        out = imported_report(args.zoo)
    else:
        from rlbackdoors.zoo.report import report

        out = report(args.zoo, skipped)
    print(f"wrote {out / 'report.md'} (tables.csv, convergence.csv, budget.csv, scatter.png, frames_hist.png, curves.png)")
    return 0


MANIFEST_WRITTEN = "no manifest; its files passed the other checks, manifest written (adopted)"


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _group_size(text: str) -> int | str:
    if text == "auto":
        return text
    try:
        return _positive_int(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"must be auto or an integer >= 1, got {text!r}") from None


def _count(text: str) -> int:
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {value}")
    return value


def _episodes(text: str) -> int:
    from rlbackdoors.config import MAX_EPISODES

    value = _count(text)
    if value > MAX_EPISODES:
        raise argparse.ArgumentTypeError(f"must be <= {MAX_EPISODES:,}, got {value}")
    return value


def _share(text: str) -> float:
    value = float(text)
    if not 0 < value < 1:
        raise argparse.ArgumentTypeError(f"must be in (0, 1), got {text}")
    return value


def _seconds(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def add_commands(parser: argparse.ArgumentParser) -> None:
    """The zoo's sub-commands on ``parser`` (``rlbackdoors zoo``, or the standalone parser)."""
    from rlbackdoors.config import DEVICES
    from rlbackdoors.zoo.run import BACKENDS

    sub = parser.add_subparsers(dest="zoo_command", required=True, parser_class=Parser)
    pl = sub.add_parser("plan", help="draw every model's config from the spec's master seed and write the zoo's folders (nothing trains)")
    pl.add_argument("spec", help="zoo spec (TOML; see docs/zoos.md)")
    pl.add_argument("--out", required=True, help="zoo folder to write (new or empty; the same spec again is a no-op)")
    pl.set_defaults(func=cmd_plan)

    rp = sub.add_parser(
        "replan", help="plan a changed spec onto a planned zoo: folders it draws the same stay (trained or not), the others move to ZOO/replaced/N/"
    )
    rp.add_argument("spec", help="the new zoo spec (TOML): the same master seed, cells' groups and max_attempts")
    rp.add_argument("zoo", help="the planned zoo")
    rp.set_defaults(func=cmd_replan)

    ru = sub.add_parser("run", help="train every planned model that is not finished; top cells up until they have their converged models")
    ru.add_argument("zoo", help="zoo folder (from zoo plan)")
    ru.add_argument("--workers", type=_positive_int, help="jobs at a time (default: local, the CPU cores; ray, the cluster's CPUs)")
    ru.add_argument(
        "--group-size",
        type=_group_size,
        default=1,
        help="train up to K models of a worker in one process, their networks stacked and batched (local back-end; "
        "auto: the measured rule per world's algorithm and each model's device; default 1: a process per model, today's bytes)",
    )
    ru.add_argument(
        "--device",
        choices=DEVICES,
        help="where every model's math runs instead of its planned train.device (local back-end; recorded in its metrics.json, "
        "config.json stays the plan's; a started model resumes only on the device it began on)",
    )
    ru.add_argument(
        "--env-workers",
        type=_count,
        default=0,
        help="worlds of single envs (OPAC²'s): each job steps its env copies in this many worker processes, the same bytes (default 0: in the job's process)",
    )
    ru.add_argument("--backend", choices=BACKENDS, default="local", help="local: a child process per job; ray: Ray tasks (pip install 'rlbackdoors[ray]')")
    ru.add_argument("--address", help="Ray cluster address (e.g. auto or ray://head:10001; default: start a local Ray)")
    ru.add_argument("--max-retries", type=_count, default=2, help="retries of a job that fails before it is recorded as failed (default 2)")
    ru.add_argument("--retry-failed", action="store_true", help="run models recorded as failed (failed.json) again")
    ru.add_argument("--progress-interval", type=_seconds, default=10.0, help="seconds between progress lines on stderr (default 10)")
    ru.add_argument(
        "--retrain-tampered", action="store_true", help="empty the models that fail zoo verify and train them again (default: such a zoo is refused)"
    )
    ru.add_argument("--json", action="store_true", help="print the summary as JSON")
    ru.set_defaults(func=cmd_run)

    ve = sub.add_parser("verify", help="check every model folder against its manifest, the plan and METADATA.csv; no link is followed")
    ve.add_argument("zoo")
    ve.add_argument("--write-manifest", action="store_true", help="adopt a zoo built before manifests: finished folders that pass the other checks get one")
    ve.add_argument("--expect", metavar="DIGEST", help="the zoo's published digest (sha256:...): anything else fails")
    ve.add_argument("--json", action="store_true", help="print the result as JSON")
    ve.set_defaults(func=cmd_verify)

    pa = sub.add_parser("pack", help="a copy small enough for git: finished models' weights, configs and metrics with manifests, the plan; no logs or pictures")
    pa.add_argument("zoo")
    pa.add_argument("--out", required=True, help="pack folder (new, or a pack of this same zoo, replaced once the new one verifies)")
    pa.add_argument(
        "--converged-weights-only",
        action="store_true",
        help="leave out the weights of finished models that did not converge (no detector reads them); each keeps its metrics and counts as an attempt",
    )
    pa.add_argument("--json", action="store_true", help="print what was packed as JSON")
    pa.set_defaults(func=cmd_pack)

    skip_help = "leave the models that fail zoo verify out, and name them (default: such a zoo is refused)"
    st = sub.add_parser("status", help="the table of cells: wanted / converged / not converged / failed / running / left")
    st.add_argument("zoo")
    st.add_argument("--skip-unverified", action="store_true", help=skip_help)
    st.set_defaults(func=cmd_status)

    sp = sub.add_parser("split", help="disjoint train and test datasets of converged models, by model and by trigger")
    sp.add_argument("zoo")
    sp.add_argument("--train", type=_share, help="share of the converged models for training (e.g. 0.5)")
    sp.add_argument("--test", type=_share, help="share for testing (train + test <= 1)")
    sp.add_argument(
        "--hold-out-attack",
        action="append",
        metavar="NAME",
        help="test on the models of this attack's cells (repeatable), train on the others (no shared trigger); instead of --train/--test",
    )
    sp.add_argument("--out-train", required=True, help="folder of the train dataset")
    sp.add_argument("--out-test", required=True, help="folder of the test dataset")
    sp.add_argument("--seed", type=int, default=0, help="order in which trigger groups are dealt (default 0)")
    sp.add_argument("--link", action="store_true", help="hard-link the model files instead of copying them (same file system)")
    sp.add_argument("--skip-unverified", action="store_true", help=skip_help)
    sp.set_defaults(func=cmd_split)

    re = sub.add_parser("report", help="the paper's Tables 1-5 and plots over the zoo, in ZOO/report/")
    re.add_argument("zoo")
    re.add_argument("--skip-unverified", action="store_true", help=skip_help)
    re.set_defaults(func=cmd_report)

    from rlbackdoors.config import EVAL_POLICIES

    im = sub.add_parser("import-trojai", help="index a TrojAI RL round's model folders as a zoo (read as data, never unpickled; docs/trojai.md)")
    im.add_argument("dir", help="TrojAI folder: a round (models/id-*/ or id-*/), or one model folder; or folders rlbackdoors train wrote (only read)")
    im.add_argument("--out", required=True, help="zoo folder to write (new or empty; the same import again adds only what is new)")
    im.add_argument("--world", help="world of every model (default: from the TrojAI class each folder names)")
    im.add_argument("--arch", help="architecture of every model (needs --world; default: from the TrojAI class, else the one the shapes fit)")
    im.add_argument("--size", type=_positive_int, help="grid size (default: TrojAI's grid_size, else the world's)")
    im.add_argument("--num-lava", type=_count, help="single lava squares, worlds that have them (default: TrojAI's num_lava_squares, else the world's)")
    im.add_argument("--max-steps", type=_positive_int, help="episode step limit (default: TrojAI's max_steps / max_ep_length, else the world's)")
    im.add_argument(
        "--num-cubes", type=_positive_int, help="wandering cubes, worlds that have them (default: TrojAI's env_kwargs.num_mogwais, else the world's)"
    )
    im.add_argument("--label", type=int, choices=(0, 1), help="ground truth of folders without ground_truth.csv (default: such folders are refused)")
    im.add_argument("--trigger", help="trigger to measure every model's poisoned SR under (needs --world; default: none, TrojAI's are not named)")
    # dest differs: the main CLI's --episodes check (>= 1) is for commands that must play
    im.add_argument(
        "--episodes", dest="eval_episodes", type=_episodes, default=100, help="clean episodes per model measured at import, in our world (default 100; 0: none)"
    )
    im.add_argument("--examples", type=_episodes, default=5, help="clean example episodes per model in clean-example-data/ (default 5)")
    im.add_argument("--seed", type=int, default=1_000_000, help="first env seed of the measured episodes (default 1000000)")
    im.add_argument("--policy", choices=EVAL_POLICIES, help="sample or greedy (default: the world's evaluation policy)")
    im.add_argument("--json", action="store_true", help="print the summary as JSON")
    im.set_defaults(func=cmd_import_trojai)


def add_zoo_parser(subparsers) -> argparse.ArgumentParser:
    """Mount ``zoo`` on the main CLI: ``add_zoo_parser(sub)`` in ``rlbackdoors.cli.build_parser``."""
    zoo = subparsers.add_parser(
        "zoo", help="datasets of clean and poisoned agents: plan, run (local or Ray), verify, pack, status, split, report, import-trojai"
    )
    add_commands(zoo)
    return zoo


def main(argv: list[str] | None = None) -> int:
    return sub_cli_main("rlbackdoors zoo", "Build TrojAI-style datasets of clean and poisoned agents (docs/zoos.md).", add_commands, argv)


if __name__ == "__main__":
    sys.exit(main())
