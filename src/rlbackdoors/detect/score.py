"""Fitting a detector on a train zoo and scoring it on a test zoo.

Scoring never stops halfway: a model that cannot be opened (missing or corrupt file, unknown
architecture) or that the detector fails on gets 0.5 and the reason, as the TrojAI harness
did; seconds per model count opening and predicting. A fit or a score written into a folder
resumes after a kill (:mod:`rlbackdoors.detect.resume`): models done before are read back, not
redone. The result: AUC, cross-entropy and Brier
score with bootstrap CIs (:mod:`rlbackdoors.detect.metrics`) for all models, per world and per
metadata factor (architecture, trigger family, ...), per-model rows (probability, seconds,
error, and what the detector reports, e.g. the trigger a search found, next to the true
trigger, read from config.json for the report only), ``score.json``, ``roc.png`` and
``calibration.png``.

A dataset too small to split into train and test zoos of a useful size (a world whose models
take CPU-hours each) is scored by cross-validation instead (:func:`cross_validate`,
``detect cv``): the same metrics over out-of-fold probabilities.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import cast

import numpy as np

from rlbackdoors import __version__
from rlbackdoors.detect import metrics
from rlbackdoors.detect.api import FAILED_PROBABILITY, Detector, FeatureDetector, Prediction, make_detector
from rlbackdoors.detect.dataset import FACTORS, Dataset, ZooModel, list_models
from rlbackdoors.detect.handle import Contradiction, DetectError, ModelHandle, open_model
from rlbackdoors.detect.resume import ResultStore, clear, eta, state_digest
from rlbackdoors.detect.scope import check_model, model_scope, record
from rlbackdoors.io import LOCK_NAME, FolderLock, LockedError, atomic_write_text, first_line, remove_tree


@contextlib.contextmanager
def holding(out: str | Path, what: str) -> Iterator[None]:
    """``out``'s lock for a job's length; another process holding it is a DetectError naming it."""
    try:
        lock = FolderLock(out, what).acquire()
    except LockedError as err:
        raise DetectError(str(err)) from None
    try:
        yield
    finally:
        lock.release()


def open_one(model: ZooModel) -> ModelHandle:
    """A train model's handle; one that cannot be opened stops the fit (it needs them all)."""
    try:
        return open_model(model.folder, name=model.name)
    except Contradiction as err:
        raise Contradiction(f"model {model.name!r}: {err}", err.world, err.arch) from None
    except DetectError as err:
        raise DetectError(f"model {model.name!r}: {err}") from None


def open_all(models: list[ZooModel]) -> list[ModelHandle]:
    return [open_one(m) for m in models]


class Unsupported(DetectError):
    """A model the detector cannot compute at all (its world or env settings): the whole job stops."""


def refuse_unsupported(detector: Detector, handle: ModelHandle, name: str) -> None:
    """Unsupported naming the model and the reason, when ``detector`` cannot compute it."""
    why = detector.unsupported(handle)
    if why is not None:
        raise Unsupported(f"model {name!r}: {why}")


def scope_flags(detector: Detector, models: list[ZooModel], allow: bool) -> dict[str, str]:
    """Each model outside what ``detector`` was fitted for, and why (rlbackdoors.detect.scope),
    checked before any model is scored; a DetectError naming the first unless ``allow``. A model
    that cannot be opened is left to the scoring, which gives it 0.5 and the reason."""
    flags: dict[str, str] = {}
    for model in models:
        try:
            handle = open_model(model.folder, name=model.name, allow_contradiction=True)  # refused or flagged by check_model
        except Exception:  # scored 0.5 with its reason below
            continue
        why = check_model(detector, handle, allow, model.name)
        if why is not None:
            flags[model.name] = why
    return flags


def _say_skipped(models: Dataset, progress: Callable[[str], None] | None) -> None:
    """One progress line per model --skip-unverified left out, and why (also in the job's result)."""
    for name, why in models.skipped.items():
        if progress:
            progress(f"skipped {name} (--skip-unverified): {why}")


def check_factors(models: list[ZooModel], factors: Sequence[str]) -> None:
    """A DetectError naming a breakdown factor that is no METADATA.csv column of the dataset."""
    known = set(FACTORS).union(*(set(m.metadata) | set(m.facts()) for m in models))
    unknown = [f for f in factors if f not in known]
    if unknown:
        raise DetectError(f"--factor {unknown[0]}: not a METADATA.csv column of this dataset (columns: {', '.join(sorted(known))})")


def fit(
    detector: Detector, zoo: str | Path, progress: Callable[[str], None] | None = None, work: str | Path | None = None, skip_unverified: bool = False
) -> dict:
    """Fit ``detector`` on every model of ``zoo``; returns what to record about the fit.

    A :class:`FeatureDetector`'s features are computed model by model and, with ``work`` (the
    folder the detector will be saved in), kept there as they come, so a killed fit started
    again computes only the rest (:func:`fit_into` does all of it under the folder's lock)."""
    started = time.perf_counter()
    models = list_models(zoo, skip_unverified)
    _say_skipped(models, progress)
    labels = np.array([m.label for m in models])
    if progress:
        progress(f"fitting {detector.name} on {len(models)} models ({int(labels.sum())} poisoned) of {zoo}")
    resumed = 0
    if isinstance(detector, FeatureDetector):
        store = ResultStore(work, "fit", {"detector": detector.name, "params": detector.params}) if work is not None else None
        results, resumed = feature_rows(detector, models, store, progress, strict=True)
        detector.fit_rows([r["features"] for r in results], [r["group"] for r in results], labels)
        scopes = [r["scope"] for r in results]
    else:
        handles = open_all(models)
        for model, handle in zip(models, handles):
            refuse_unsupported(detector, handle, model.name)
        detector.fit(handles, labels)  # records what it saw
    if isinstance(detector, FeatureDetector):
        detector.fitted_on = record(detector, scopes)
    seconds = time.perf_counter() - started
    return {
        "zoo": str(zoo),
        "models": len(models),
        "poisoned": int(labels.sum()),
        "resumed": resumed,
        "seconds": round(seconds, 3),
        "seconds_per_model": round(seconds / len(models), 4),
        "skipped": dict(models.skipped),
        "rlbackdoors": __version__,
    }


def feature_rows(
    detector: FeatureDetector, models: list[ZooModel], store: ResultStore | None, progress: Callable[[str], None] | None, strict: bool
) -> tuple[list[dict], int]:
    """Each model's ``{"features", "group", "info", "seconds"}`` (read back from ``store`` where
    done before, else computed and stored as it comes) and how many were read back. ``strict``
    (a fit, which needs every model): a model that fails stops the job; otherwise (a
    cross-validation) it gets ``{"error": why}`` and is not stored, so a rerun tries it again."""
    done = store.stored(models) if store else {}
    if progress and done:
        progress(f"resuming: features of {len(done)} of {len(models)} models were computed before")
    results, computed, spent = [], 0, 0.0
    for i, model in enumerate(models):
        result = done.get(model.name)
        if result is None:
            begun = time.perf_counter()
            detector.last_info = {}
            try:
                handle = open_one(model)
                refuse_unsupported(detector, handle, model.name)
                features = detector.fit_features(handle)
                result = {"features": features, "group": detector.group(handle), "info": dict(detector.last_info), "scope": model_scope(detector, handle)}
            except (Unsupported, Contradiction):  # the whole job, a cross-validation too: not one 0.5 among many
                raise
            except DetectError as err:
                if strict:
                    raise
                result = {"error": str(err)}
            took = time.perf_counter() - begun
            result["seconds"] = round(took, 4)
            if store and "error" not in result:
                store.put(model.name, model.folder, result)
            computed, spent = computed + 1, spent + took
            if progress:
                why = f" ({result['error']})" if "error" in result else ""
                progress(f"[{i + 1}/{len(models)}] {model.name}: features in {took:.2f} s{why}{eta(computed, len(models) - len(done), spent)}")
        results.append(result)
    return results, len(done)


def fit_into(
    detector: Detector,
    zoo: str | Path,
    out: str | Path,
    progress: Callable[[str], None] | None = None,
    extra: dict | None = None,
    skip_unverified: bool = False,
) -> dict:
    """Fit and save ``detector`` into ``out`` (``detector.json``, ``arrays.npz``, ``fit.json``),
    holding ``out``'s lock; resumes a fit that was killed there."""
    from rlbackdoors.detect.trojai import write_metaparameters

    out = Path(out)
    created = not out.exists()
    try:
        with holding(out, "detector folder"):
            info = {**fit(detector, zoo, progress, work=out, skip_unverified=skip_unverified), **(extra or {})}
            detector.save(out)
            write_metaparameters(detector, out)  # what infer must be given: the parameters fitted with
            atomic_write_text(out / "fit.json", json.dumps(info, indent=2) + "\n")
            clear(out)
    except Exception:
        if created and not any(p.is_file() and p.name != LOCK_NAME for p in out.rglob("*")):
            remove_tree(out)  # a fit refused before any work leaves no empty folder behind
        raise
    return info


def predict_model(detector: Detector, model: ZooModel, allow_contradiction: bool = False) -> Prediction:
    """One model, as the harness sees it: 0.5 and the reason when it cannot be opened.
    ``allow_contradiction``: a folder that contradicts itself is scored from its weights (its
    flag comes from :func:`scope_flags`)."""
    started = time.perf_counter()
    try:
        handle = open_model(model.folder, name=model.name, allow_contradiction=allow_contradiction)
    except Exception as err:  # a bad file must not stop the zoo
        return Prediction(0.5, time.perf_counter() - started, f"{type(err).__name__}: {first_line(err)}")
    opened = time.perf_counter() - started
    prediction = detector.predict([handle])[0]
    prediction.seconds += opened
    return prediction


def score(
    detector: Detector,
    zoo: str | Path,
    out: str | Path | None = None,
    factors: Sequence[str] = FACTORS,
    resamples: int = metrics.RESAMPLES,
    seed: int = metrics.SEED,
    progress: Callable[[str], None] | None = None,
    allow_mismatch: bool = False,
    params_mismatch: str | None = None,
    skip_unverified: bool = False,
) -> dict:
    """Score ``detector`` on ``zoo`` (module doc); writes score.json and the plots into ``out``.

    A model outside what the detector was fitted for (another world, architecture group or env
    settings: :mod:`rlbackdoors.detect.scope`) stops the job before any model is scored, unless
    ``allow_mismatch``: then its row carries ``mismatch`` and the result counts them;
    ``params_mismatch`` is the flag of parameters other than the fitted ones (``with_params``)."""
    if not detector.fitted:
        raise DetectError(f"detector {detector.name!r} is not fitted (run detect fit first)")
    models = list_models(zoo, skip_unverified)
    _say_skipped(models, progress)
    check_factors(models, factors)
    flags = scope_flags(detector, models, allow_mismatch)
    with holding(out, "score folder") if out is not None else contextlib.nullcontext():
        store = (
            ResultStore(out, "score", {"detector": detector.name, "params": detector.params, "state": state_digest(*detector.get_state())})
            if out is not None
            else None
        )
        done = store.stored(models) if store else {}
        resumed = len(done)
        if progress and resumed:
            progress(f"resuming: {resumed} of {len(models)} models were scored before")
        rows, computed, spent = [], 0, 0.0
        for i, model in enumerate(models):
            cached = done.get(model.name)
            if cached is None:
                prediction = predict_model(detector, model, allow_contradiction=allow_mismatch)
                cached = {"probability": prediction.probability, "seconds": round(prediction.seconds, 4), "error": prediction.error, "info": prediction.info}
                if store:
                    store.put(model.name, model.folder, cached)
                computed, spent = computed + 1, spent + prediction.seconds
                if progress:
                    found = f", found {prediction.info['found_trigger']}" if prediction.info.get("found_trigger") else ""
                    why = f" ({prediction.error})" if prediction.error else ""
                    left = eta(computed, len(models) - resumed, spent)
                    progress(f"[{i + 1}/{len(models)}] {model.name}: p={prediction.probability:.3f} in {prediction.seconds:.2f}s{found}{why}{left}")
            flag = {"mismatch": flags[model.name]} if model.name in flags else {}
            rows.append(
                _report_row(model, factors, cached["info"], probability=cached["probability"], seconds=cached["seconds"], error=cached["error"], **flag)
            )
        result = _summarise(detector, zoo, rows, factors, resamples, seed, resumed)
        result["mismatched"] = len(flags)
        result["params_mismatch"] = params_mismatch
        result["skipped"] = dict(models.skipped)
        if out is not None:
            _write_score(Path(out), result, rows, f"{detector.name} on {Path(zoo).name}")
            clear(out)
    return result


def cross_validate(
    detector: Detector,
    zoo: str | Path,
    out: str | Path,
    folds: int = 5,
    factors: Sequence[str] = FACTORS,
    resamples: int = metrics.RESAMPLES,
    seed: int = metrics.SEED,
    progress: Callable[[str], None] | None = None,
    skip_unverified: bool = False,
) -> dict:
    """Out-of-fold scores of a feature detector on one dataset, for a world whose models are too
    dear to make both a train and a test zoo of a useful size.

    Features are computed once per model and kept in ``out`` (a killed run resumes; a rerun with
    more models, other folds or another seed computes only the new models' features);
    the models are dealt into ``folds`` stratified folds (``seed``), and each fold is predicted by
    a fresh detector fitted on the others, so every probability comes from a classifier that never
    saw that model. A model whose features fail gets 0.5 and the reason, and trains no fold. The
    result is what :func:`score` writes (``score.json`` with a ``cv`` section, the plots)."""
    from sklearn.model_selection import StratifiedKFold

    if not isinstance(detector, FeatureDetector):
        raise DetectError(f"detector {detector.name!r} is not a features-and-classifier detector; cross-validation refits only the classifier")
    if folds < 2:
        raise DetectError(f"--folds must be at least 2, got {folds}")
    models = list_models(zoo, skip_unverified)
    _say_skipped(models, progress)
    check_factors(models, factors)
    with holding(out, "cross-validation folder"):
        store = ResultStore(out, "features", {"detector": detector.name, "params": detector.params})
        if progress:
            progress(f"cross-validating {detector.name} on {len(models)} models of {zoo}")
        results, resumed = feature_rows(detector, models, store, progress, strict=False)
        usable = np.array([i for i, r in enumerate(results) if "error" not in r], dtype=np.int64)
        y = np.array([m.label for m in models])
        smallest = min(int(y[usable].sum()), len(usable) - int(y[usable].sum())) if len(usable) else 0
        if smallest < 2:
            raise DetectError(f"cross-validation needs at least 2 models of each label with features; {zoo} has {smallest} of one")
        k = min(folds, smallest)
        if progress and k < folds:
            progress(f"{k} folds, not {folds}: the smaller label has {smallest} models")
        probability = np.full(len(models), FAILED_PROBABILITY)
        fold_of = np.full(len(models), -1)
        info: list[dict] = [dict(r.get("info") or {}) for r in results]
        split = StratifiedKFold(n_splits=k, shuffle=True, random_state=seed).split(np.zeros((len(usable), 1)), y[usable])
        for f, (train, test) in enumerate(split):
            member = cast(FeatureDetector, make_detector(detector.name, **detector.params))
            member.fit_rows([results[i]["features"] for i in usable[train]], [results[i]["group"] for i in usable[train]], y[usable[train]])
            for i in usable[test]:
                member.last_info = {}
                probability[i] = member.classify(results[i]["features"], results[i]["group"])
                fold_of[i] = f
                info[i].update(member.last_info)
        rows = [
            _report_row(
                model, factors, info[i], probability=float(probability[i]), seconds=results[i]["seconds"], error=results[i].get("error"), fold=int(fold_of[i])
            )
            for i, model in enumerate(models)
        ]
        result = _summarise(detector, zoo, rows, factors, resamples, seed, resumed)
        result["cv"] = {"folds": k, "seed": seed, "scheme": "stratified k-fold; features once per model, the classifier refitted per fold"}
        result["skipped"] = dict(models.skipped)
        _write_score(Path(out), result, rows, f"{detector.name} on {Path(zoo).name} ({k}-fold cross-validation)")
        # The features stay (unlike a fit's or a score's): a dataset that gains models, or other
        # folds, computes only what is new.
    return result


def _report_row(model: ZooModel, factors: Sequence[str], info: dict, **fields) -> dict:
    """One model's row of score.json: name, label, ``fields`` (probability, seconds, error, ...),
    the report-only facts (true trigger ...), what the detector reported, and each factor's level."""
    facts = model.facts()
    return {
        "model": model.name,
        "label": model.label,
        **fields,
        **facts,
        **info,
        **{f: model.metadata.get(f, facts.get(f, "")) for f in factors},
    }


def _write_score(out: Path, result: dict, rows: list[dict], title: str) -> None:
    """score.json, roc.png and calibration.png into ``out``; their paths into ``result``."""
    atomic_write_text(out / "score.json", json.dumps(_jsonable(result), indent=2) + "\n")
    p, y = np.array([r["probability"] for r in rows]), np.array([r["label"] for r in rows])
    metrics.plot_roc(p, y, [str(r.get("world", "")) for r in rows], out / "roc.png", title=f"ROC: {title}")
    metrics.plot_calibration(p, y, out / "calibration.png", title=f"calibration: {title}")
    result["written"] = [str(out / n) for n in ("score.json", "roc.png", "calibration.png")]


def _summarise(detector: Detector, zoo: str | Path, rows: list[dict], factors: Sequence[str], resamples: int, seed: int, resumed: int) -> dict:
    """score.json's content: the metrics over all models, per world and factor level, and the rows."""
    p = np.array([r["probability"] for r in rows])
    y = np.array([r["label"] for r in rows])
    seconds = np.array([r["seconds"] for r in rows])
    levels = {f: [str(r.get(f, "")) for r in rows] for f in dict.fromkeys(("world", *factors))}
    by: dict = metrics.breakdown(p, y, levels, resamples, seed)
    for world in by["world"]:
        mask = np.array([v == world for v in levels["world"]])
        by["world"][world]["seconds_per_model"] = float(seconds[mask].mean())
    return {
        "detector": detector.name,
        "params": detector.params,
        "zoo": str(zoo),
        "resamples": resamples,
        "seed": seed,
        "all": metrics.summarize(p, y, resamples, seed),
        "by": by,
        "seconds_per_model": {"mean": float(seconds.mean()), "median": float(np.median(seconds)), "max": float(seconds.max()), "total": float(seconds.sum())},
        "failed": sum(1 for r in rows if r["error"]),
        "resumed": resumed,
        "models": rows,
        "rlbackdoors": __version__,
    }


def _jsonable(value):
    """NaN (an AUC over one label) as null: score.json is strict JSON."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    return value


def _cell(summary: dict, name: str) -> str:
    m = summary[name]
    if m["value"] is None or not math.isfinite(m["value"]):
        return "–"
    low, high = m["ci"]
    ci = f" [{low:.3f}, {high:.3f}]" if low is not None and math.isfinite(low) else ""
    return f"{m['value']:.3f}{ci}"


def table(result: dict) -> str:
    """The printed score: one row for all models, per world and per factor level; then, where the
    detector reports a found trigger, one row per model with the true trigger beside it."""
    head = ("group", "n", "pois.", "AUC [95% CI]", "CE [95% CI]", "Brier [95% CI]", "s/model")
    lines = [("all", result["all"], result["seconds_per_model"]["mean"])]
    for factor, levels in result["by"].items():
        for level, summary in levels.items():
            sec = summary.get("seconds_per_model")
            lines.append((f"{factor}={level or '?'}", summary, sec))
    rows = [head] + [
        (name, str(s["n"]), str(s["poisoned"]), _cell(s, "auc"), _cell(s, "ce"), _cell(s, "brier"), f"{sec:.2f}" if sec is not None else "")
        for name, s, sec in lines
    ]
    widths = [max(len(r[i]) for r in rows) for i in range(len(head))]
    text = ["  ".join(v.ljust(w) if i == 0 else v.rjust(w) for i, (v, w) in enumerate(zip(r, widths))) for r in rows]
    text.insert(1, "  ".join("-" * w for w in widths))
    out = [f"{result['detector']} on {result['zoo']}: {result['all']['n']} models, {result['failed']} failed (scored 0.5)", *text]
    if any(r.get("found_trigger") for r in result["models"]):
        found = [f"{r.get('found_trigger') or '-'} ({r.get('found_trojan_rate', 0.0):.2f})" for r in result["models"]]
        name_w = max(5, *(len(r["model"]) for r in result["models"]))
        found_w = max(len("found trigger (trojan rate)"), *(len(f) for f in found))
        out += ["", f"{'model':<{name_w}}  label      p  {'found trigger (trojan rate)':<{found_w}}  true trigger"]
        for r, f in zip(result["models"], found):
            out.append(f"{r['model']:<{name_w}}  {r['label']:>5}  {r['probability']:.3f}  {f:<{found_w}}  {r.get('true_trigger') or '-'}")
    errors = [r for r in result["models"] if r["error"]]
    for r in errors[:20]:
        out.append(f"{r['model']}: scored 0.5: {r['error']}")
    for name, why in (result.get("skipped") or {}).items():
        out.append(f"{name}: skipped (--skip-unverified): {why}")
    if result.get("params_mismatch"):
        out.append(f"MISMATCH (--allow-mismatch): {result['params_mismatch']}")
    flagged = [r for r in result["models"] if r.get("mismatch")]
    if flagged:
        out.append(f"MISMATCH (--allow-mismatch): {len(flagged)} of {len(result['models'])} models lie outside what the detector was fitted on:")
        out += [f"  {r['model']}: {r['mismatch']}" for r in flagged[:20]]
    return "\n".join(out)


__all__ = ["fit", "fit_into", "open_all", "predict_model", "score", "table"]
