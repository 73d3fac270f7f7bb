"""Score detectors on a benchmark round kept in git (issue 80), in one command, training nothing:

    python benchmarks/round_table.py lavaworld                              # the shipped detectors
    python benchmarks/round_table.py lavaworld --detectors mine --plugin my_detector.py
    python benchmarks/round_table.py --markdown                             # docs/benchmark.md's tables

A round is two packed zoos, ``datasets/round-WORLD-train`` and ``datasets/round-WORLD-test``, on
disjoint triggers, every attack family and evasive variant of the world in both, each model's
settings and training length drawn from ranges (``examples/round-WORLD-*.toml``). Each detector is
scored on the test split under two protocols:

* **trojai**: fitted on the whole train split (TrojAI's: every family in both splits);
* **envmix**: fitted on the train split's clean and env-mix models alone (the paper's attack),
  then scored on every family: how well a detector holds on attacks it never saw.

Per protocol, detector and family (its poisoned test models against every clean test model: a
clean model trains the same whatever cell planned it): AUC, cross-entropy and Brier score with
95 % bootstrap CIs and counts; and the **length control**, the AUC of frames trained alone on the
same models (read from ``metrics.json`` by this script, never by a detector), which a round drawn
well keeps near 0.5. Writes ``benchmarks/results/rounds/round-WORLD.json`` with the machine and its
load. Fits and scores are read back when the script runs again (``runs/rounds/``), unless the
split's converged models changed (``--fresh`` starts over). Each detector's reliability curve
(5 bins) and expected calibration error are in the JSON too. ``--markdown`` rewrites the tables
of docs/benchmark.md, and draws the reliability curves beside the JSON, from the committed JSON alone.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import shutil
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from _detect_cli import Refused, rlbackdoors
from sklearn.metrics import roc_auc_score

from rlbackdoors.bench.machine import machine_info
from rlbackdoors.detect.metrics import reliability, summarize_rows
from rlbackdoors.io import atomic_write_bytes, atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "rounds"
DOC = ROOT / "docs" / "benchmark.md"
DETECTORS = ("effect", "weights", "behaviour", "attribution", "stack")
# Parameters a detector is fitted with here (others: its defaults). The round's stack is of the three
# members that err on different families: effect (misses action-level trojans under offsets),
# weights (the env mix) and behaviour (docs/results/detectors.md).
DETECTOR_PARAMS = {"stack": {"members": "effect,weights,behaviour"}}
PROTOCOLS = ("trojai", "envmix")
RELIABILITY_BINS = 5  # the reliability curve's equal-width bins: about 20 of a round's 100 test models a bin, not 10 noisy points
DEFAULT_FAMILY = "envmix"  # the paper's attack: the cell label of a spec's plain env-mix cells


def family(row: dict) -> str:
    """A METADATA row's family: its cell's attack label (``world/arch/trigger/label``), else the env mix."""
    parts = row["cell"].split("/")
    return parts[3] if len(parts) >= 4 else DEFAULT_FAMILY


def converged_rows(zoo: Path) -> list[dict]:
    """The zoo's converged models as its folders stand (a pack still training has no final METADATA.csv)."""
    from rlbackdoors.zoo.index import metadata_rows, scan
    from rlbackdoors.zoo.plan import Zoo

    return [r for r in metadata_rows(scan(Zoo.open(zoo))) if r["status"] == "done" and r["converged"]]


def envmix_fit_split(train: Path, out: Path) -> Path:
    """The train split's clean and env-mix models as a dataset of their own (copies; split.json names them)."""
    from rlbackdoors.zoo.index import scan
    from rlbackdoors.zoo.plan import Zoo
    from rlbackdoors.zoo.split import write_split

    zoo = Zoo.open(train)
    states = [s for s in scan(zoo, probe=False) if s.converged]
    keep = [s for s in states if not s.model.group.poisoned or s.model.group.cell.attack.name == DEFAULT_FAMILY]
    if not (out / "METADATA.csv").is_file():
        write_split(zoo, "train", keep, out, link=False, info={"zoo": train.resolve().name, "protocol": "envmix"})
    return out


def fit(name: str, train: Path, det: Path, plugins: list[str]) -> None:
    if not (det / "detector.json").is_file():
        params = [x for k, v in DETECTOR_PARAMS.get(name, {}).items() for x in ("--param", f"{k}={json.dumps(v)}")]
        rlbackdoors("detect", "fit", "--detector", name, "--zoo", str(train), "--out", str(det), "--quiet", *params, *plugins)


def score(det: Path, test: Path, out: Path, plugins: list[str]) -> dict:
    scored = out / "score.json"
    if not scored.is_file() or scored.stat().st_mtime < (det / "detector.json").stat().st_mtime:
        rlbackdoors("detect", "score", str(det), "--zoo", str(test), "--out", str(out), "--quiet", *plugins)
    return json.loads(scored.read_text())


def auc(labels: list[int], values: list[float]) -> float | None:
    return float(roc_auc_score(labels, values)) if 0 < sum(labels) < len(labels) else None


def per_family(models: list[dict], families: dict[str, str], frames: dict[str, float]) -> dict:
    """Each family's poisoned test models with every clean one: the detector's summary and the length control."""
    clean = [m for m in models if m["label"] == 0]
    out = {}
    for fam in ["all", *sorted({families[m["model"]] for m in models if m["label"] == 1})]:
        rows = models if fam == "all" else [m for m in models if m["label"] == 1 and families[m["model"]] == fam] + clean
        summary = summarize_rows(rows)
        length = auc([m["label"] for m in rows], [frames[m["model"]] for m in rows])
        out[fam] = {"models": summary.pop("n"), **summary, "length_auc": length}
    return out


def long_trained_gap(models: list[dict], long: dict[str, bool]) -> dict:
    """Issue 81's check that training length is no tell to the detector: the mean probability of
    the clean test models trained on past convergence (a drawn ``train.min_frames``) minus that of
    those stopped at it (asked: within 0.05)."""
    out: dict = {}
    for key, want in (("long", True), ("stopped", False)):
        p = [m["probability"] for m in models if m["label"] == 0 and long[m["model"]] is want]
        out[key] = {"models": len(p), "mean_probability": round(sum(p) / len(p), 4) if p else None}
    long_p, stopped_p = out["long"]["mean_probability"], out["stopped"]["mean_probability"]
    out["gap"] = None if long_p is None or stopped_p is None else round(long_p - stopped_p, 4)
    return out


def run(args: argparse.Namespace) -> Path:
    train = Path(args.train or ROOT / "datasets" / f"round-{args.world}-train")
    test = Path(args.test or ROOT / "datasets" / f"round-{args.world}-test")
    for where in (train, test):
        if not (where / "zoo.json").is_file():
            sys.exit(f"rlbackdoors: error: {where} is not a round's zoo (no zoo.json); its spec is examples/round-{args.world}-*.toml")
    base = Path(args.runs) / f"round-{args.world}"
    rows = {"train": converged_rows(train), "test": converged_rows(test)}
    shared = {r["poison.trigger"] for r in rows["train"]} & {r["poison.trigger"] for r in rows["test"]}
    if shared:  # a round tests on triggers its train split never held
        sys.exit(
            f"rlbackdoors: error: {len(shared)} trigger(s) occur in both splits (first: {sorted(shared)[0]}); a round's splits must be disjoint by trigger"
        )
    record = {k: sorted(r["model_name"] for r in v) for k, v in rows.items()}
    if base.is_dir() and (args.fresh or not (base / "models.json").is_file() or json.loads((base / "models.json").read_text()) != record):
        shutil.rmtree(base)  # the splits' converged models changed: fits and scores are made afresh
    base.mkdir(parents=True, exist_ok=True)
    atomic_write_text(base / "models.json", json.dumps(record, indent=1) + "\n")
    families = {r["model_name"]: family(r) for r in rows["test"]}
    frames = {r["model_name"]: float(r["metrics.frames"]) for r in rows["test"]}
    long = {r["model_name"]: float(r.get("train.min_frames") or 0) > 0 for r in rows["test"]}
    fits = {"trojai": train, "envmix": envmix_fit_split(train, base / "fit-envmix")}
    plugins = [x for p in args.plugin for x in ("--plugin", p)]
    load = _loadavg()
    start = time.time()
    table: dict = {}
    refused: dict = {}

    def job(protocol: str, name: str) -> dict | Refused:
        det = base / protocol / name
        try:
            fit(name, fits[protocol], det, plugins)
            return score(det, test, det / "score-test", plugins)
        except Refused as why:  # said in the table, not scored
            return why

    # Each (protocol, detector) is its own subprocess on one thread: --jobs of them at once.
    pairs = [(protocol, name) for protocol in PROTOCOLS for name in args.detectors]
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        done = dict(zip(pairs, pool.map(lambda pair: job(*pair), pairs)))
    for (protocol, name), scored in done.items():
        if isinstance(scored, Refused):
            refused.setdefault(protocol, {})[name] = str(scored)
            continue
        models = [m for m in scored["models"] if m.get("probability") is not None]
        table.setdefault(protocol, {})[name] = {
            "families": per_family(models, families, frames),
            "failed": len(scored["models"]) - len(models),
            "long_trained_clean": long_trained_gap(models, long),
            "seconds_per_model": (scored.get("seconds_per_model") or {}).get("mean"),  # one core's (one BLAS thread)
            "reliability": reliability([m["probability"] for m in models], [m["label"] for m in models], RELIABILITY_BINS),
        }
    counts = {
        split: {
            "models": len(r),
            "clean": sum(not x["poisoned"] for x in r),
            "poisoned_by_family": _count({family(x) for x in r}, [family(x) for x in r if x["poisoned"]]),
        }
        for split, r in rows.items()
    }
    counts["fit_envmix"] = {"models": len(list((fits["envmix"] / "models").iterdir()))}
    result = {
        "command": "python benchmarks/round_table.py " + " ".join(sys.argv[1:]),
        "round": args.world,
        "train": str(train.relative_to(ROOT)) if train.is_relative_to(ROOT) else train.name,
        "test": str(test.relative_to(ROOT)) if test.is_relative_to(ROOT) else test.name,
        "counts": counts,
        "length_control_test": auc([int(r["poisoned"]) for r in rows["test"]], [frames[r["model_name"]] for r in rows["test"]]),
        "protocols": table,
        "refused": refused,
        "machine": machine_info(),
        "loadavg_before": load,
        "loadavg_after": _loadavg(),
        "elapsed_minutes": round((time.time() - start) / 60, 1),
    }
    out = Path(args.out or RESULTS / f"round-{args.world}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out, json.dumps(result, indent=1) + "\n")
    return out


def _count(keys: set[str], values: list[str]) -> dict:
    return {k: values.count(k) for k in sorted(keys) if values.count(k)}


def _loadavg() -> list[float]:
    try:
        return [float(x) for x in Path("/proc/loadavg").read_text().split()[:3]]
    except OSError:
        return []


# ----- docs/benchmark.md ------------------------------------------------------------------------
BEGIN, END = "<!-- round-tables: python benchmarks/round_table.py --markdown -->", "<!-- /round-tables -->"


def _cell(summary: dict, key: str) -> str:
    value, ci = summary[key]["value"], summary[key]["ci"]
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    return f"{value:.3f} [{ci[0]:.2f}, {ci[1]:.2f}]" if ci and None not in ci else f"{value:.3f}"


def markdown(results: list[dict], figures: dict[str, Path] | None = None) -> str:
    """The tables of every committed round: per protocol, family x detector, AUC and CE with CIs;
    ``figures``: round -> its reliability curves' PNG (:func:`plot_reliability`), shown below its tables."""
    lines: list[str] = []
    for res in results:
        c = res["counts"]
        m = res["machine"]
        lines += [
            f"### {res['round']}",
            "",
            f"Test split `{res['test']}`: {c['test']['models']} converged models, {c['test']['clean']} clean; poisoned per family "
            + ", ".join(f"{k} {v}" for k, v in c["test"]["poisoned_by_family"].items())
            + f". Train split `{res['train']}`: {c['train']['models']} ({c['train']['clean']} clean); the env-mix fit: {c['fit_envmix']['models']}. "
            f"Length control (AUC of frames trained alone, test split): **{res['length_control_test']:.3f}**. "
            f"Scored on {m.get('cpu', m.get('processor', '?'))}, load {res['loadavg_before'][:1]}, `{res['command']}`.",
            "",
        ]
        for protocol, title in (("trojai", "fitted on the train split (TrojAI's protocol)"), ("envmix", "fitted on the env mix alone")):
            dets = res["protocols"].get(protocol, {})
            if not dets:
                continue
            fams = sorted({f for d in dets.values() for f in d["families"]}, key=lambda f: (f != "all", f))
            lines += [f"AUC / CE [95 % CI], {title}; `length` is the control on the same models:", ""]
            lines.append("| family | models | " + " | ".join(dets) + " | length |")
            lines.append("|---|---|" + "---|" * (len(dets) + 1))
            for fam in fams:
                first = next(d["families"][fam] for d in dets.values() if fam in d["families"])
                cells = [f"{_cell(d['families'][fam], 'auc')} / {_cell(d['families'][fam], 'ce')}" if fam in d["families"] else "–" for d in dets.values()]
                length = first["length_auc"]
                lines.append(f"| {fam} | {first['models']} | " + " | ".join(cells) + f" | {'–' if length is None else f'{length:.2f}'} |")
            secs = ", ".join(f"{n} {d['seconds_per_model']:.2f}" for n, d in dets.items() if d.get("seconds_per_model") is not None)
            gaps = ", ".join(f"{n} {g['gap']:+.3f}" for n, d in dets.items() if (g := d.get("long_trained_clean")) and g.get("gap") is not None)
            lines += ["", f"Seconds per model (one core): {secs}."]
            eces = ", ".join(f"{n} {d['reliability']['ece']:.3f}" for n, d in dets.items() if d.get("reliability"))
            if eces:
                lines += [
                    f"Expected calibration error over the test models ({RELIABILITY_BINS} bins; 0: each bin's share poisoned is its mean probability): {eces}."
                ]
            if gaps:
                one = next(d["long_trained_clean"] for d in dets.values() if d.get("long_trained_clean"))
                lines += [
                    f"Long-trained clean models' mean probability minus that of the clean models stopped at convergence "
                    f"({one['long']['models']} and {one['stopped']['models']}; asked within 0.05): {gaps}."
                ]
            lines += [""]
        figure = (figures or {}).get(res["round"])
        if figure is not None:
            rel = figure.relative_to(ROOT).as_posix()
            lines += [f"![Reliability curves of {res['round']}'s detectors, both protocols](../{rel})", ""]
        for protocol, why in res.get("refused", {}).items():
            lines += [f"Refused ({protocol}): " + "; ".join(f"{n}: {w}" for n, w in why.items()), ""]
    return "\n".join(lines).rstrip() + "\n"


def plot_reliability(res: dict, folder: Path = RESULTS) -> Path | None:
    """The round's reliability curves from its JSON (one panel a protocol, a line a detector, each
    point a bin sized by its models) as ``folder/round-WORLD-reliability.png``; None where no
    detector has one."""
    panels = [(p, d) for p, d in res["protocols"].items() if any(x.get("reliability") for x in d.values())]
    if not panels:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4.6), dpi=110, squeeze=False)
    for ax, (protocol, dets) in zip(axes[0], panels):
        ax.plot([0, 1], [0, 1], color="grey", ls="--", lw=0.8)
        for name, d in dets.items():
            curve = (d.get("reliability") or {}).get("bins") or []
            if curve:
                xs, ys = [b["mean_probability"] for b in curve], [b["share_poisoned"] for b in curve]
                line = ax.plot(xs, ys, lw=1, label=f"{name} (ECE {d['reliability']['ece']:.3f})")[0]
                ax.scatter(xs, ys, s=[8 + 3 * b["models"] for b in curve], color=line.get_color(), alpha=0.6)
        title = "fitted on the train split (TrojAI)" if protocol == "trojai" else "fitted on the env mix alone"
        ax.set(xlim=(0, 1), ylim=(-0.02, 1.02), xlabel="mean predicted probability (bin)", ylabel="share poisoned", title=f"{res['round']}: {title}")
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    out = folder / f"round-{res['round']}-reliability.png"
    buf = io.BytesIO()
    fig.savefig(buf, format="png", metadata={"Software": None})
    plt.close(fig)
    atomic_write_bytes(out, buf.getvalue())
    return out


def write_markdown() -> Path:
    results = [json.loads(p.read_text()) for p in sorted(RESULTS.glob("round-*.json"))]
    text = DOC.read_text()
    if BEGIN not in text or END not in text:
        sys.exit(f"rlbackdoors: error: {DOC} has no {BEGIN} ... {END} block to fill")
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    figures = {res["round"]: figure for res in results if (figure := plot_reliability(res)) is not None}
    body = markdown(results, figures) if results else "No round has been scored yet.\n"
    atomic_write_text(DOC, f"{head}{BEGIN}\n{body}{END}{tail}")
    return DOC


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("world", nargs="?", help="the round: datasets/round-WORLD-train and -test")
    parser.add_argument("--detectors", nargs="+", default=list(DETECTORS))
    parser.add_argument("--plugin", action="append", default=[], metavar="FILE", help="a Python file of your own detectors (detect fit --plugin)")
    parser.add_argument("--train", help="the train split's zoo (default: datasets/round-WORLD-train)")
    parser.add_argument("--test", help="the test split's zoo (default: datasets/round-WORLD-test)")
    parser.add_argument("--runs", default=str(ROOT / "runs" / "rounds"), help="where fits and scores are kept")
    parser.add_argument("--out", help="the JSON (default: benchmarks/results/rounds/round-WORLD.json)")
    parser.add_argument("--fresh", action="store_true", help="fit and score afresh")
    parser.add_argument(
        "--jobs", type=int, default=1, help="fits and scores run at once, one core each (seconds per model are then one core's under that load)"
    )
    parser.add_argument("--markdown", action="store_true", help="rewrite docs/benchmark.md's tables from the committed JSON; score nothing")
    args = parser.parse_args()
    if args.jobs < 1:
        sys.exit(f"rlbackdoors: error: --jobs must be at least 1, got {args.jobs}")
    if args.markdown:
        print(write_markdown())
    elif args.world:
        print(run(args))
    else:
        parser.error("give a round (e.g. lavaworld) or --markdown")


if __name__ == "__main__":
    main()
