"""``rlbackdoors zoo report ZOO``: the paper's tables over what the zoo holds, in ``ZOO/report/``.

* Tables 1-4 (``tables.csv``): per world x architecture x ground truth, clean SR, poisoned SR,
  clean and poisoned reward: mean ± std, a 95% bootstrap CI of the mean, and n; for the
  dataset (converged models) and for every finished model; the paper's figure beside it where
  the World registry has one (``World.paper``).
* Table 5 (``convergence.csv``): models converged out of attempted (finished or failed), with a
  Wilson 95% interval, next to the paper's rate where the registry has one.
* Frames and wall time to converge (``budget.csv``).
* ``scatter.png`` (clean SR vs poisoned SR, one dot per model, coloured by ground truth),
  ``frames_hist.png`` (frames to converge), ``curves.png`` (each group's evaluation curves:
  median with the interquartile band).
"""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path

import numpy as np

from rlbackdoors import worlds
from rlbackdoors.io import atomic_write, atomic_write_text, refuse_links
from rlbackdoors.zoo.index import ModelState, scan, write_metadata
from rlbackdoors.zoo.plan import Zoo

METRICS = ("clean_sr", "poisoned_sr", "clean_reward", "poisoned_reward")
Z95 = 1.959963984540054
BOOTSTRAP = 2000


def wilson(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (NaN, NaN for n = 0)."""
    if n == 0:
        return math.nan, math.nan
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return max(0.0, centre - half), min(1.0, centre + half)


def bootstrap_ci(values: np.ndarray, seed: int = 0, rounds: int = BOOTSTRAP) -> tuple[float, float]:
    """95% percentile bootstrap interval of the mean (seeded: the report is reproducible)."""
    if len(values) == 0:
        return math.nan, math.nan
    if len(values) == 1:
        return float(values[0]), float(values[0])
    rng = np.random.default_rng(seed)
    means = values[rng.integers(0, len(values), (rounds, len(values)))].mean(axis=1)
    return float(np.percentile(means, 2.5)), float(np.percentile(means, 97.5))


def _key(s: ModelState) -> tuple[str, str, str, str]:
    """(world, arch, label, attack); the attack is "" for the paper's env mix, so its rows read as before."""
    cell = s.model.group.cell
    return cell.world, cell.arch_label, s.model.group.label, "" if cell.attack.is_default else cell.attack.name


def _models(row: dict) -> str:
    """The report's "models" column: the label, and the attack where it is not the env mix."""
    return f"{row['label']} ({row['attack']})" if row.get("attack") else row["label"]


def _number(value) -> float:
    return float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else math.nan


def paper_figure(world: worlds.World, arch: str, label: str, metric: str) -> float | None:
    """The paper's Tables 1-4 figure for models of ``label`` and ``arch`` (``World.paper["tables"]``:
    label -> arch -> (clean SR, poisoned SR, clean reward, poisoned reward)); None where the paper
    has none (N/A, or an arch it did not train)."""
    by_arch = world.paper.get("tables", {}).get(label, {})
    figures = by_arch.get(arch, by_arch.get(world.algorithm))  # OPAC² worlds: one row for the algorithm
    if figures is None:
        return world.paper.get(metric) if label == "poisoned" else None
    return figures[METRICS.index(metric)]


def performance_rows(states: list[ModelState]) -> list[dict]:
    """Tables 1-4, one row per (population, world, arch, label)."""
    rows = []
    for population, chosen in (("dataset", [s for s in states if s.converged]), ("finished", [s for s in states if s.status == "done"])):
        keys = sorted({_key(s) for s in chosen})
        for world_name, arch, label, attack in keys:
            mine = [s for s in chosen if _key(s) == (world_name, arch, label, attack)]
            world = worlds.get(world_name)
            row: dict = {
                "population": population,
                "table": world.paper.get("table", ""),
                "world": world_name,
                "arch": arch,
                "label": label,
                "attack": attack,
                "n": len(mine),
            }
            for metric in METRICS:
                values = np.array([_number((s.metrics or {}).get(metric)) for s in mine])
                values = values[~np.isnan(values)]
                low, high = bootstrap_ci(values)
                row[f"{metric}_mean"] = float(values.mean()) if len(values) else math.nan
                row[f"{metric}_std"] = float(values.std(ddof=1)) if len(values) > 1 else (0.0 if len(values) else math.nan)
                row[f"{metric}_ci_low"], row[f"{metric}_ci_high"] = low, high
                paper = None if attack else paper_figure(world, arch, label, metric)  # the paper has env-mix models only
                row[f"{metric}_paper"] = paper if paper is not None else ""
            rows.append(row)
    return rows


def convergence_rows(states: list[ModelState]) -> list[dict]:
    """Table 5: converged / attempted per world, arch and label (and per world over its archs)."""
    attempted = [s for s in states if s.status in ("done", "failed")]
    rows = []
    keys = sorted({_key(s) for s in attempted} | {(w, "all", label, attack) for w, _, label, attack in (_key(s) for s in attempted)})
    for world_name, arch, label, attack in keys:
        mine = [s for s in attempted if (_key(s)[0], _key(s)[2], _key(s)[3]) == (world_name, label, attack) and (arch == "all" or _key(s)[1] == arch)]
        k, n = sum(s.converged for s in mine), len(mine)
        low, high = wilson(k, n)
        paper = None if attack else worlds.get(world_name).paper.get("convergence_rate" if label == "poisoned" else "clean_convergence_rate")
        rows.append(
            {
                "world": world_name,
                "arch": arch,
                "label": label,
                "attack": attack,
                "converged": k,
                "attempted": n,
                "failed": sum(s.status == "failed" for s in mine),
                "rate": k / n if n else math.nan,
                "wilson_low": low,
                "wilson_high": high,
                "paper_rate": paper if paper is not None else "",
            }
        )
    return rows


def budget_rows(states: list[ModelState]) -> list[dict]:
    """Frames, wall and CPU time of converged models (median, min, max) per world, arch and label.

    CPU time is what a model costs on one core however loaded the machine was; models trained
    before it was recorded count as missing (NaN), not zero.
    """
    rows = []
    chosen = [s for s in states if s.converged]
    for key in sorted({_key(s) for s in chosen}):
        mine = [s for s in chosen if _key(s) == key]
        frames = np.array([_number((s.metrics or {}).get("frames")) for s in mine])
        wall = np.array([_number((s.metrics or {}).get("wall_time_s")) for s in mine])
        cpu = np.array([_number((s.metrics or {}).get("cpu_time_s")) for s in mine])
        rows.append(
            {
                "world": key[0],
                "arch": key[1],
                "label": key[2],
                "attack": key[3],
                "n": len(mine),
                "frames_median": float(np.nanmedian(frames)),
                "frames_min": float(np.nanmin(frames)),
                "frames_max": float(np.nanmax(frames)),
                "wall_time_s_median": float(np.nanmedian(wall)),
                "wall_time_s_total": float(np.nansum(wall)),
                "cpu_time_s_median": float(np.nanmedian(cpu)) if np.isfinite(cpu).any() else None,
            }
        )
    return rows


def _fmt(value, digits: int = 3) -> str:
    if value == "" or value is None:
        return "–"
    if isinstance(value, float):
        return "–" if math.isnan(value) else f"{value:.{digits}f}"
    return str(value)


def _md_table(head: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "|".join("---" for _ in head) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines)


def _stat(row: dict, metric: str) -> str:
    if row["n"] == 0 or math.isnan(row[f"{metric}_mean"]):
        return "–"
    return f"{row[f'{metric}_mean']:.3f} ± {row[f'{metric}_std']:.3f} [{row[f'{metric}_ci_low']:.3f}, {row[f'{metric}_ci_high']:.3f}]"


def markdown(name: str, states: list[ModelState], perf: list[dict], conv: list[dict], budget: list[dict], curves: bool = True) -> str:
    """report.md's text; ``curves``: link the frames histogram and training curves (models were trained)."""
    done = sum(s.status == "done" for s in states)
    parts = [
        f"# Zoo report: {name}",
        "",
        f"{len(states)} planned models: {done} finished, {sum(s.converged for s in states)} converged (the dataset), "
        f"{sum(s.status == 'failed' for s in states)} failed, {sum(s.status in ('pending', 'running') for s in states)} unfinished. "
        "A model is converged when its thresholds hold on its final evaluation (`converged` in metrics.json).",
        "",
        *_skipped_section(states),
        "## Tables 1–4: success rates and rewards of the dataset's models",
        "",
        "mean ± std [95% bootstrap CI of the mean] over models; the paper's figure for the same arch and label beside it (– where the paper has none).",
        "",
    ]
    head = [
        "paper table",
        "world",
        "arch",
        "models",
        "n",
        "clean SR",
        "poisoned SR",
        "clean reward",
        "poisoned reward",
        "paper SR clean / poisoned",
        "paper reward clean / poisoned",
    ]
    body = [
        [
            _fmt(r["table"]),
            r["world"],
            r["arch"],
            _models(r),
            str(r["n"]),
            *(_stat(r, m) for m in METRICS),
            f"{_fmt(r['clean_sr_paper'], 2)} / {_fmt(r['poisoned_sr_paper'], 2)}",
            f"{_fmt(r['clean_reward_paper'], 2)} / {_fmt(r['poisoned_reward_paper'], 2)}",
        ]
        for r in perf
        if r["population"] == "dataset"
    ]
    parts += [
        _md_table(head, body) if body else "(no converged model yet)",
        "",
        "Every finished model, converged or not: `tables.csv` (population `finished`).",
        "",
    ]
    parts += ["## Table 5: how many models converged", "", "converged / attempted (finished or failed), Wilson 95% interval.", ""]
    head = ["world", "arch", "models", "converged / attempted", "rate", "Wilson 95%", "failed", "paper rate"]
    body = [
        [
            r["world"],
            r["arch"],
            _models(r),
            f"{r['converged']} / {r['attempted']}",
            _fmt(r["rate"]),
            f"[{_fmt(r['wilson_low'])}, {_fmt(r['wilson_high'])}]",
            str(r["failed"]),
            _fmt(r["paper_rate"]),
        ]
        for r in conv
    ]
    parts += [_md_table(head, body) if body else "(no finished model yet)", ""]
    parts += ["## Frames and wall time to converge", ""]
    head = ["world", "arch", "models", "n", "frames (median, min–max)", "wall time (median)", "wall time (sum)", "CPU time (median)"]
    body = [
        [
            r["world"],
            r["arch"],
            _models(r),
            str(r["n"]),
            f"{r['frames_median']:,.0f} ({r['frames_min']:,.0f}–{r['frames_max']:,.0f})",
            f"{r['wall_time_s_median']:.0f} s",
            f"{r['wall_time_s_total'] / 60:.1f} min",
            "–" if r["cpu_time_s_median"] is None else f"{r['cpu_time_s_median']:.0f} s",
        ]
        for r in budget
    ]
    parts += [_md_table(head, body) if body else "(no converged model yet)", ""]
    parts += ["## Plots", "", "![clean SR vs poisoned SR](scatter.png)", ""]
    if curves:
        parts += ["![frames to converge](frames_hist.png)", "", "![training curves](curves.png)", ""]
    return "\n".join(parts)


def _save(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    plt.close(fig)


def plot_scatter(states: list[ModelState], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    finished = [s for s in states if s.status == "done"]
    world_names = sorted({s.model.group.cell.world for s in finished}) or ["(none)"]
    fig, axes = plt.subplots(1, len(world_names), figsize=(4.2 * len(world_names), 4), squeeze=False, constrained_layout=True)
    for ax, name in zip(axes[0], world_names):
        for poisoned, colour in ((False, "tab:blue"), (True, "tab:red")):
            for converged, fill in ((True, colour), (False, "none")):
                mine = [s for s in finished if s.model.group.cell.world == name and s.model.group.poisoned == poisoned and s.converged == converged]
                if not mine:
                    continue
                x = [_number((s.metrics or {}).get("clean_sr")) for s in mine]
                y = [_number((s.metrics or {}).get("poisoned_sr")) for s in mine]
                label = f"{'poisoned' if poisoned else 'clean'}{'' if converged else ', not converged'} ({len(mine)})"
                ax.scatter(x, y, s=28, facecolors=fill, edgecolors=colour, label=label)
        title = worlds.get(name).title if name in worlds.names() else name
        ax.set(xlabel="clean SR", ylabel="poisoned SR", xlim=(-0.03, 1.03), ylim=(-0.03, 1.03), title=title)
        if finished:
            ax.legend(fontsize=7, loc="center left")
    _save(fig, path)


def plot_frames(states: list[ModelState], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.6), constrained_layout=True)
    chosen = [s for s in states if s.converged]
    for poisoned, colour in ((False, "tab:blue"), (True, "tab:red")):
        frames = [_number((s.metrics or {}).get("frames")) for s in chosen if s.model.group.poisoned == poisoned]
        if frames:
            ax.hist(frames, bins=min(20, max(3, len(frames))), alpha=0.6, color=colour, label=f"{'poisoned' if poisoned else 'clean'} ({len(frames)})")
    ax.set(xlabel="frames to converge (converged models)", ylabel="models", title="frames to converge")
    if chosen:
        ax.legend(fontsize=8)
    _save(fig, path)


def _curve(folder: Path, key: str) -> tuple[np.ndarray, np.ndarray] | None:
    path = folder / "log.csv"
    if not path.is_file():
        return None
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    try:
        frames = np.array([float(r["frames"]) for r in rows])
        values = np.array([float(r[key]) for r in rows])
    except (KeyError, ValueError):
        return None
    return (frames, values) if len(frames) else None


def plot_curves(states: list[ModelState], path: Path, max_groups: int = 24) -> None:
    """Per group: the median evaluation SRs of its finished models against frames, with the
    interquartile band (each model's curve held at its last value after it stopped)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    finished = [s for s in states if s.status == "done"]
    keys = sorted({s.model.group.key for s in finished})[:max_groups]
    cols = min(4, max(1, len(keys)))
    rows = max(1, math.ceil(len(keys) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3 * rows), squeeze=False, constrained_layout=True)
    for ax in axes.flat[len(keys) :]:
        ax.axis("off")
    for ax, key in zip(axes.flat, keys):
        mine = [s for s in finished if s.model.group.key == key]
        for metric, colour in (("clean_sr", "tab:green"), ("poisoned_sr", "tab:red")):
            curves = [c for c in (_curve(s.folder, metric) for s in mine) if c is not None]
            if not curves:
                continue
            grid = np.unique(np.concatenate([f for f, _ in curves]))
            stacked = np.stack([np.interp(grid, f, v) for f, v in curves])
            ax.plot(grid, np.median(stacked, axis=0), "o-", ms=3, color=colour, label=f"{metric} (median of {len(curves)})")
            ax.fill_between(grid, np.percentile(stacked, 25, axis=0), np.percentile(stacked, 75, axis=0), color=colour, alpha=0.2)
        ax.set(title=key, xlabel="frames", ylabel="SR", ylim=(-0.03, 1.03))
        ax.title.set_fontsize(8)
        ax.legend(fontsize=6, loc="lower right")
    _save(fig, path)


def _csv(rows: list[dict]) -> str:
    if not rows:
        return ""
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return buf.getvalue()


def write_report(out: Path, name: str, states: list[ModelState], trained: list[ModelState] | None = None) -> str:
    """The CSVs and plots of ``states`` in ``out``; returns report.md's text for the caller to write.
    ``trained``: the models with training runs to show (frames, wall time, curves); default all."""
    trained = states if trained is None else trained
    out.mkdir(exist_ok=True)
    perf, conv, budget = performance_rows(states), convergence_rows(states), budget_rows(trained)
    atomic_write_text(out / "tables.csv", _csv(perf))
    atomic_write_text(out / "convergence.csv", _csv(conv))
    atomic_write_text(out / "budget.csv", _csv(budget))
    plot_scatter(states, out / "scatter.png")
    for plot, file in ((plot_frames, "frames_hist.png"), (plot_curves, "curves.png")):
        if trained:
            plot(trained, out / file)
        else:  # nothing trained here (an imported zoo): no empty picture, and no stale one
            (out / file).unlink(missing_ok=True)
    return markdown(name, states, perf, conv, budget, curves=bool(trained))


def _skipped_section(states: list[ModelState]) -> list[str]:
    """The models left out because they failed zoo verify (``--skip-unverified``), and why."""
    skipped = [s for s in states if s.status == "unverified"]
    if not skipped:
        return []
    lines = [f"## Skipped: {len(skipped)} models failed verification", "", "Left out of every table and plot (`zoo verify` names what differs):", ""]
    return [*lines, *(f"* {s.model.name}: {s.reason}" for s in skipped), ""]


def report(path: str | Path, skip: dict[str, str] | None = None) -> Path:
    """Write ``ZOO/report/`` (and refresh ``ZOO/METADATA.csv``); return the report folder.
    ``skip``: models that failed verification (name -> why), left out and named."""
    zoo = Zoo.open(path)
    states = scan(zoo, probe=False, skip=skip)
    write_metadata(zoo, states)
    out = zoo.path / "report"
    if os.path.lexists(out):
        refuse_links(zoo.path, out)
    atomic_write_text(out / "report.md", write_report(out, zoo.spec.name, states))
    return out
