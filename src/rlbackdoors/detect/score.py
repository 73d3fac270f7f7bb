"""Fitting a detector on a train zoo and scoring it on a test zoo.

Scoring never stops halfway: a model that cannot be opened (missing or corrupt file, unknown
architecture) or that the detector fails on gets 0.5 and the reason, as the TrojAI harness
did; seconds per model count opening and predicting. The result: AUC, cross-entropy and Brier
score with bootstrap CIs (:mod:`rlbackdoors.detect.metrics`) for all models, per world and per
metadata factor (architecture, trigger family, ...), per-model rows (probability, seconds,
error, and what the detector reports, e.g. the trigger a search found, next to the true
trigger, read from config.json for the report only), ``score.json``, ``roc.png`` and
``calibration.png``.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from rlbackdoors import __version__
from rlbackdoors.detect import metrics
from rlbackdoors.detect.api import Detector, Prediction
from rlbackdoors.detect.dataset import FACTORS, ZooModel, list_models
from rlbackdoors.detect.handle import DetectError, ModelHandle, open_model
from rlbackdoors.io import atomic_write_text, first_line


def open_all(models: list[ZooModel]) -> list[ModelHandle]:
    """Handles of every model; the first that cannot be opened stops it (fitting needs them all)."""
    out = []
    for m in models:
        try:
            out.append(open_model(m.folder, name=m.name))
        except DetectError as err:
            raise DetectError(f"model {m.name!r}: {err}") from None
    return out


def fit(detector: Detector, zoo: str | Path, progress: Callable[[str], None] | None = None) -> dict:
    """Fit ``detector`` on every model of ``zoo``; returns what to record about the fit."""
    started = time.perf_counter()
    models = list_models(zoo)
    labels = np.array([m.label for m in models])
    if progress:
        progress(f"fitting {detector.name} on {len(models)} models ({int(labels.sum())} poisoned) of {zoo}")
    handles = open_all(models)
    detector.fit(handles, labels)
    seconds = time.perf_counter() - started
    return {
        "zoo": str(zoo),
        "models": len(models),
        "poisoned": int(labels.sum()),
        "seconds": round(seconds, 3),
        "seconds_per_model": round(seconds / len(models), 4),
        "rlbackdoors": __version__,
    }


def predict_model(detector: Detector, model: ZooModel) -> Prediction:
    """One model, as the harness sees it: 0.5 and the reason when it cannot be opened."""
    started = time.perf_counter()
    try:
        handle = open_model(model.folder, name=model.name)
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
) -> dict:
    """Score ``detector`` on ``zoo`` (module doc); writes score.json and the plots into ``out``."""
    if not detector.fitted:
        raise DetectError(f"detector {detector.name!r} is not fitted (run detect fit first)")
    models = list_models(zoo)
    rows = []
    for i, model in enumerate(models):
        prediction = predict_model(detector, model)
        facts = model.facts()
        rows.append(
            {
                "model": model.name,
                "label": model.label,
                "probability": prediction.probability,
                "seconds": round(prediction.seconds, 4),
                "error": prediction.error,
                **facts,
                **{k: v for k, v in prediction.info.items()},
                **{f: model.metadata.get(f, facts.get(f, "")) for f in factors},
            }
        )
        if progress:
            found = f", found {prediction.info['found_trigger']}" if prediction.info.get("found_trigger") else ""
            why = f" ({prediction.error})" if prediction.error else ""
            progress(f"[{i + 1}/{len(models)}] {model.name}: p={prediction.probability:.3f} in {prediction.seconds:.2f}s{found}{why}")
    p = np.array([r["probability"] for r in rows])
    y = np.array([r["label"] for r in rows])
    seconds = np.array([r["seconds"] for r in rows])
    levels = {f: [str(r.get(f, "")) for r in rows] for f in dict.fromkeys(("world", *factors))}
    by: dict = metrics.breakdown(p, y, levels, resamples, seed)
    for world in by["world"]:
        mask = np.array([v == world for v in levels["world"]])
        by["world"][world]["seconds_per_model"] = float(seconds[mask].mean())
    result = {
        "detector": detector.name,
        "params": detector.params,
        "zoo": str(zoo),
        "resamples": resamples,
        "seed": seed,
        "all": metrics.summarize(p, y, resamples, seed),
        "by": by,
        "seconds_per_model": {"mean": float(seconds.mean()), "median": float(np.median(seconds)), "max": float(seconds.max()), "total": float(seconds.sum())},
        "failed": sum(1 for r in rows if r["error"]),
        "models": rows,
        "rlbackdoors": __version__,
    }
    if out is not None:
        out = Path(out)
        atomic_write_text(out / "score.json", json.dumps(_jsonable(result), indent=2) + "\n")
        title = f"{detector.name} on {Path(zoo).name}"
        metrics.plot_roc(p, y, levels["world"], out / "roc.png", title=f"ROC: {title}")
        metrics.plot_calibration(p, y, out / "calibration.png", title=f"calibration: {title}")
        result["written"] = [str(out / n) for n in ("score.json", "roc.png", "calibration.png")]
    return result


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
    return "\n".join(out)


__all__ = ["fit", "open_all", "predict_model", "score", "table"]
