"""``rlbackdoors detect list | fit | score | cv | search | infer | configure | metaparameters``.

:func:`add_detect_parser` mounts ``detect`` on the main CLI's sub-parsers; ``python -m
rlbackdoors.detect.cli fit ...`` runs the same commands on their own. Errors follow the CLI's
contract (:func:`rlbackdoors.argparser.report_errors`): one ``rlbackdoors: error: ...`` line,
exit 2. ``infer`` and ``configure`` take TrojAI's argument names (:mod:`rlbackdoors.detect.trojai`).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from rlbackdoors.argparser import Parser, sub_cli_main


def _progress(quiet: bool):
    return None if quiet else (lambda line: print(line, file=sys.stderr, flush=True))


def parse_params(items: list[str] | None) -> dict:
    """``k=v`` pairs; ``v`` is read as JSON where it parses (numbers, true/false), else a string."""
    from rlbackdoors.detect.handle import DetectError

    params = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise DetectError(f"--param {item!r} must look like KEY=VALUE")
        try:
            params[key.strip()] = json.loads(value)
        except ValueError:
            params[key.strip()] = value
    return params


def cmd_list(args) -> int:
    from rlbackdoors.detect.api import get_detector, detector_names

    for name in detector_names():
        cls = get_detector(name)
        params = ", ".join(f"{k}={v!r}" for k, v in cls.defaults.items()) or "no parameters"
        print(f"{name:<12} {cls.description}\n{'':<12} ({params})")
    return 0


def cmd_fit(args) -> int:
    from rlbackdoors.detect.api import STATE_FILE, make_detector
    from rlbackdoors.detect.handle import DetectError
    from rlbackdoors.detect.resume import PARTIAL
    from rlbackdoors.detect.score import fit_into
    from rlbackdoors.io import LOCK_NAME

    out = Path(args.out)
    # a folder holding only a killed fit's work (and its lock file) is resumed, not refused
    if out.exists() and (not out.is_dir() or any(p.name not in (PARTIAL, LOCK_NAME) for p in out.iterdir())):
        if not (out / STATE_FILE).is_file():
            raise DetectError(f"--out {str(out)!r} exists and holds no detector; give a new or empty folder")
        if not args.overwrite:
            raise DetectError(f"--out {str(out)!r} already holds a detector; pass --overwrite to replace it")
    detector = make_detector(args.detector, **parse_params(args.param))
    info = fit_into(detector, args.zoo, out, progress=_progress(args.quiet), skip_unverified=args.skip_unverified)
    print(
        f"{out}: {detector.name} fitted on {info['models']} models ({info['poisoned']} poisoned) in {info['seconds']:.1f} s ({info['seconds_per_model']:.2f} s/model)"
    )
    return 0


def cmd_score(args) -> int:
    from rlbackdoors.detect.api import load_detector
    from rlbackdoors.detect.dataset import FACTORS
    from rlbackdoors.detect.score import score

    from rlbackdoors.detect.scope import with_params

    detector, params_flag = with_params(load_detector(args.detector_dir), parse_params(args.param), args.allow_mismatch)
    out = Path(args.out) if args.out else Path(args.detector_dir) / f"score-{Path(args.zoo).resolve().name}"
    factors = tuple(dict.fromkeys((*FACTORS, *(args.factor or []))))
    result = score(
        detector,
        args.zoo,
        out,
        factors=factors,
        resamples=args.resamples,
        seed=args.seed,
        progress=_progress(args.quiet),
        allow_mismatch=args.allow_mismatch,
        params_mismatch=params_flag,
        skip_unverified=args.skip_unverified,
    )
    return _print_score(result, out, args.json)


def cmd_cv(args) -> int:
    from rlbackdoors.detect.api import make_detector
    from rlbackdoors.detect.dataset import FACTORS
    from rlbackdoors.detect.score import cross_validate

    detector = make_detector(args.detector, **parse_params(args.param))
    factors = tuple(dict.fromkeys((*FACTORS, *(args.factor or []))))
    out = Path(args.out)
    result = cross_validate(
        detector, args.zoo, out, args.folds, factors, args.resamples, args.seed, progress=_progress(args.quiet), skip_unverified=args.skip_unverified
    )
    lead = f"{result['cv']['folds']}-fold cross-validation, every probability from a classifier fitted without its model"
    return _print_score(result, out, args.json, lead)


def _print_score(result: dict, out: Path, as_json: bool, lead: str | None = None) -> int:
    """A score's result as JSON, or as the table with the files it wrote (``lead`` above it)."""
    from rlbackdoors.detect.score import _jsonable, table

    if as_json:
        print(json.dumps(_jsonable(result), indent=2))
        return 0
    if lead:
        print(lead)
    print(table(result))
    print(f"wrote {out / 'score.json'}, {out / 'roc.png'}, {out / 'calibration.png'}")
    return 0


def cmd_search(args) -> int:
    """The behavioural trigger search on one model, unfitted: which candidate of its world's
    family turns it to the trojan outcome, and how often, against the clean env. A red team checks
    whether its backdoor is found; a researcher reads what a detector's features are made of."""
    from rlbackdoors.detect.baselines.behaviour import BehaviourDetector, search_report
    from rlbackdoors.detect.handle import DetectError, open_model
    from rlbackdoors.detect.scope import check_contradiction
    from rlbackdoors.io import atomic_write_text
    from rlbackdoors.trojai_round import ROUND_FILES

    one_thread()
    folder = Path(args.model)
    handle = open_model(folder, reduced_optional=True, allow_contradiction=True)  # a folder name that may say the label becomes "model"
    if check_contradiction(handle, args.allow_mismatch, str(folder)) is not None:
        print(f"rlbackdoors: warning: {folder}: MISMATCH, searched under --allow-mismatch: {handle.contradiction}", file=sys.stderr)
    if not any((folder / n).is_file() for n in ROUND_FILES):  # weights alone
        print(
            f"rlbackdoors: note: {folder}: no settings file ({', '.join(ROUND_FILES[:3])}); world and architecture identified from the weights, env settings the world's defaults",
            file=sys.stderr,
        )
    detector = BehaviourDetector(**parse_params(args.param))
    why = detector.unsupported(handle)
    if why is not None:
        raise DetectError(f"{folder}: {why}")
    report = search_report(handle, detector.params, detector.run_search(handle), top=args.top)
    if handle.contradiction is not None:
        report["mismatch"] = handle.contradiction
    if args.out:
        atomic_write_text(Path(args.out), json.dumps(report, indent=2) + "\n")
    if args.json:
        print(json.dumps(report, indent=2))
        return 0
    clean, found = report["clean"], report["found"]
    print(f"{report['model']} ({report['world']}/{report['arch']}), searched {report['candidates_tried']} candidates in {report['seconds']:.1f} s")
    print(f"  clean env:      trojan outcome {clean['trojan']:.2f}, goal {clean['success']:.2f} over {clean['episodes']} episodes")
    print(f"  found trigger:  {found['spec']}")
    print(
        f"                  trojan outcome {found['trojan']:.2f}, goal {found['success']:.2f} over {found['episodes']} episodes ({found['excess']:+.2f} over clean)"
    )
    print("  top screened:   " + "; ".join(f"{t['spec']} {t['trojan']:.2f}" for t in report["top_screened"]))
    if args.out:
        print(f"wrote {args.out}")
    return 0


def cmd_infer(args) -> int:
    from rlbackdoors.detect.trojai import infer

    probability, error, mismatch = infer(
        args.model_filepath,
        args.result_filepath,
        args.scratch_dirpath,
        args.examples_dirpath,
        args.round_training_dataset_dirpath,
        args.metaparameters_filepath,
        args.schema_filepath,
        args.learned_parameters_dirpath,
        allow_mismatch=args.allow_mismatch,
    )
    if error:
        print(f"rlbackdoors: warning: {args.model_filepath}: scored 0.5: {error}", file=sys.stderr)
    if mismatch:
        print(f"rlbackdoors: warning: {args.model_filepath}: MISMATCH, scored under --allow-mismatch: {mismatch}", file=sys.stderr)
    print(f"trojan probability {probability:.6f} written to {args.result_filepath}")
    return 0


def cmd_configure(args) -> int:
    from rlbackdoors.detect.trojai import configure

    info = configure(
        args.scratch_dirpath,
        args.configure_models_dirpath,
        args.metaparameters_filepath,
        args.schema_filepath,
        args.learned_parameters_dirpath,
        args.automatic_configuration,
    )
    print(f"{args.learned_parameters_dirpath}: fitted on {info['models']} models ({info['poisoned']} poisoned) in {info['seconds']:.1f} s")
    return 0


def cmd_metaparameters(args) -> int:
    from rlbackdoors.detect.trojai import METAPARAMETERS, SCHEMA, schema_for
    from rlbackdoors.io import atomic_write_text

    config, schema = schema_for(args.detector, parse_params(args.param))  # values checked by the detector's rules
    out = Path(args.out)
    atomic_write_text(out / METAPARAMETERS, json.dumps(config, indent=2) + "\n")
    atomic_write_text(out / SCHEMA, json.dumps(schema, indent=2) + "\n")
    print(f"wrote {out / METAPARAMETERS} and {out / SCHEMA}")
    return 0


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _scoring_options(parser: argparse.ArgumentParser, seed: str) -> None:
    """What ``score`` and ``cv`` share: breakdowns, bootstrap, output."""
    parser.add_argument("--factor", action="append", metavar="COLUMN", help="another METADATA.csv column to break the scores down by (repeatable)")
    parser.add_argument("--resamples", type=_positive_int, default=2000, help="bootstrap resamples for the CIs (default 2000)")
    parser.add_argument("--seed", type=int, default=0, help=seed)
    parser.add_argument("--json", action="store_true", help="print the result as JSON instead of the table")
    parser.add_argument("--quiet", action="store_true", help="no progress lines")
    _skip_option(parser)


def _skip_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--skip-unverified",
        action="store_true",
        help="leave out models that fail zoo verify (each named, with why, in the output) instead of refusing the dataset",
    )


def add_commands(parser: argparse.ArgumentParser) -> None:
    """The detect sub-commands on ``parser`` (``rlbackdoors detect``, or the standalone parser)."""
    sub = parser.add_subparsers(dest="detect_command", required=True, parser_class=Parser)
    li = sub.add_parser("list", help="the registered detectors and their parameters")
    _takes_plugins(li, cmd_list)

    fi = sub.add_parser("fit", help="fit a detector on a train zoo and save its learned parameters (plain data)")
    fi.add_argument("--detector", required=True, help="detector name (see detect list)")
    fi.add_argument("--zoo", required=True, help="train zoo or split (ZOO/models/id-X/ and METADATA.csv)")
    fi.add_argument("--out", required=True, help="folder for the fitted detector (detector.json, arrays.npz, fit.json)")
    fi.add_argument("--param", action="append", metavar="KEY=VALUE", help="a detector parameter (repeatable; values read as JSON)")
    fi.add_argument("--overwrite", action="store_true", help="replace a detector already in --out")
    fi.add_argument("--quiet", action="store_true", help="no progress lines")
    _skip_option(fi)
    _takes_plugins(fi, cmd_fit)

    sc = sub.add_parser("score", help="score a fitted detector on a test zoo: AUC, CE, Brier with 95%% CIs, per world and factor; JSON and PNGs")
    sc.add_argument("detector_dir", metavar="DET", help="folder written by detect fit (or configure)")
    sc.add_argument("--zoo", required=True, help="test zoo or split")
    sc.add_argument("--out", help="folder for score.json, roc.png, calibration.png (default: DET/score-<zoo name>)")
    sc.add_argument(
        "--param",
        action="append",
        metavar="KEY=VALUE",
        help="a parameter other than the fitted one: refused unless it only steers the fit, or --allow-mismatch",
    )
    sc.add_argument(
        "--allow-mismatch",
        action="store_true",
        help="score models (and parameters) outside what the detector was fitted on; each is flagged in score.json and the table",
    )
    _scoring_options(sc, seed="bootstrap seed (default 0)")
    _takes_plugins(sc, cmd_score)

    cv = sub.add_parser("cv", help="cross-validate a features-and-classifier detector on one dataset too small to split: out-of-fold AUC, CE, Brier")
    cv.add_argument("--detector", required=True, help="detector name (see detect list)")
    cv.add_argument("--zoo", required=True, help="the dataset (a zoo, split or imported folder)")
    cv.add_argument("--out", required=True, help="folder for score.json, roc.png, calibration.png (a killed run resumes here)")
    cv.add_argument("--folds", type=_positive_int, default=5, help="stratified folds, at most the smaller label's count (default 5)")
    cv.add_argument("--param", action="append", metavar="KEY=VALUE", help="a detector parameter (repeatable; values read as JSON)")
    _scoring_options(cv, seed="seed of the folds and the bootstrap (default 0)")
    _takes_plugins(cv, cmd_cv)

    se = sub.add_parser("search", help="the behavioural trigger search on one model folder: the candidate trigger that fires it, against the clean env")
    se.add_argument("model", metavar="MODEL", help="a model folder: model.pt (reduced-config.json and clean-example-data/ when there)")
    se.add_argument("--param", action="append", metavar="KEY=VALUE", help="a parameter of the behaviour detector (repeatable; see detect list)")
    se.add_argument("--top", type=_positive_int, default=5, help="screened candidates to list, best first (default 5)")
    se.add_argument("--out", help="also write the report (JSON) to this file")
    se.add_argument("--json", action="store_true", help="print the report as JSON instead of text")
    se.add_argument(
        "--allow-mismatch",
        action="store_true",
        help="search a folder whose settings name another architecture than its weights fit, as the weights say (flagged on stderr and in the report)",
    )
    se.set_defaults(func=cmd_search)

    inf = sub.add_parser("infer", help="TrojAI inference mode: write one model's trojan probability")
    inf.add_argument("--model_filepath", required=True, help="the model.pt to evaluate (reduced-config.json beside it)")
    inf.add_argument("--result_filepath", required=True, help="file to write the probability into")
    inf.add_argument("--scratch_dirpath", required=True, help="scratch folder (the private copy of the model's files goes here)")
    inf.add_argument("--examples_dirpath", default=None, help="the model's clean-example-data folder (optional)")
    inf.add_argument(
        "--round_training_dataset_dirpath", required=True, help="the round's training dataset (accepted; the learned parameters already hold what was learned)"
    )
    inf.add_argument("--metaparameters_filepath", required=True, help="the detector's metaparameters (JSON)")
    inf.add_argument("--schema_filepath", required=True, help="JSON schema the metaparameters are validated against")
    inf.add_argument("--learned_parameters_dirpath", required=True, help="folder written by detect fit or configure")
    inf.add_argument(
        "--allow-mismatch",
        "--allow_mismatch",
        action="store_true",
        help="score a model or metaparameters outside what the detector was fitted on (flagged on stderr and in SCRATCH/result.json)",
    )
    _takes_plugins(inf, cmd_infer)

    co = sub.add_parser("configure", help="TrojAI configuration mode: fit the detector the metaparameters name, write learned parameters")
    co.add_argument("--scratch_dirpath", required=True, help="scratch folder")
    co.add_argument("--configure_models_dirpath", required=True, help="folder of model folders (or a zoo) to fit on")
    co.add_argument("--metaparameters_filepath", required=True, help="metaparameters (JSON): 'detector' and its parameters")
    co.add_argument("--schema_filepath", required=True, help="JSON schema for the metaparameters")
    co.add_argument("--learned_parameters_dirpath", required=True, help="folder to write the learned parameters into")
    co.add_argument("--automatic_configuration", action="store_true", help="accepted for TrojAI; C is always chosen by cross-validation")
    _takes_plugins(co, cmd_configure)

    me = sub.add_parser("metaparameters", help="write metaparameters.json and metaparameters_schema.json for a detector (for infer/configure)")
    me.add_argument("--detector", required=True, help="detector name")
    me.add_argument("--out", required=True, help="folder to write the two files into")
    me.add_argument("--param", action="append", metavar="KEY=VALUE", help="a parameter value other than the default (repeatable)")
    _takes_plugins(me, cmd_metaparameters)


def _takes_plugins(parser: argparse.ArgumentParser, command) -> None:
    """``--plugin FILE`` on ``parser``, and ``command`` run after importing those files (each
    registers its detectors)."""
    parser.add_argument(
        "--plugin",
        action="append",
        metavar="FILE",
        help="a Python file of your own detectors, imported first (it registers them with @register; repeatable; docs/tutorials/detectors.md)",
    )

    def run(args) -> int:
        from rlbackdoors.detect.api import load_plugin

        one_thread()
        for path in args.plugin or ():
            load_plugin(path)
        return command(args)

    parser.set_defaults(func=run)


def one_thread() -> None:
    """One torch thread, as ``evaluate`` and the zoo's jobs run. Why: a detector plays small
    batches, which a second thread does not speed up, and with the other core busy its spin-waits
    made the effect search ten times slower (2.2 s against 21.3 s a benchmark-round model, 2-core AMD
    EPYC, 2026-12-07); the benchmarks' seconds per model are one core's."""
    import torch

    torch.set_num_threads(1)


def add_detect_parser(subparsers) -> argparse.ArgumentParser:
    """Mount ``detect`` on the main CLI: ``add_detect_parser(sub)`` in ``rlbackdoors.cli.build_parser``."""
    detect = subparsers.add_parser("detect", help="trojan detectors: fit on a train zoo, score on a test zoo, TrojAI infer/configure")
    add_commands(detect)
    return detect


def main(argv: list[str] | None = None) -> int:
    return sub_cli_main("rlbackdoors detect", "Fit, score and run trojan detectors on zoos (docs/detectors.md).", add_commands, argv)


if __name__ == "__main__":
    sys.exit(main())
