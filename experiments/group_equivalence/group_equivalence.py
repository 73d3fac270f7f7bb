"""Do agents trained in a group behave like agents trained alone? (issue 35's equivalence check)

    python experiments/group_equivalence/group_equivalence.py --side alone  &   # one core
    python experiments/group_equivalence/group_equivalence.py --side group  &   # the other core
    python experiments/group_equivalence/group_equivalence.py --report          # tests and the table

Trains the same configs (LavaWorld FC, poisoned, default trigger, seeds 0..N-1, the world's
stopping rule: real convergence runs) once each alone (``rlbackdoors.train.train``, one run after
another in this process) and once in a group (``train_group``, ``--group-size`` at a time, slots
refilled). Both sides resume after a kill: a finished run is read, a started one continues from
its checkpoint. ``--report`` compares the sides: converged counts (Fisher's exact test), frames
to converge, final clean SR and poisoned SR (two-sided Mann-Whitney U on the 200-episode final
evaluations), equivalence within stated margins on the same three (two one-sided tests, TOST:
``MARGINS``), and the CPU seconds per model each side spent (metrics.json's ``cpu_time_s``: the
group trainer apportions its batched work among its runs). Writes
``experiments/group_equivalence/group_equivalence.json`` and prints a Markdown table;
``--retest REPORT...`` runs the tests again on committed reports' per-run rows, and
``--plot REPORT... --png FILE`` draws their runs, side by side.

``--device cuda`` trains the group side on a GPU (its bytes are the GPU's, recorded per run with
any group convolution way, ``RLBACKDOORS_STACKED_CONV``), to be tested against a lone side trained
on a CPU (``--report --against``): e.g. on a lease, ``--side group --group-size 20 --device cuda``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def config(world: str, arch: str, seed: int, update_backend: str = "torch"):
    from rlbackdoors.config import RunConfig

    data = {"env": {"name": world}, "model": {"arch": arch}, "train": {"seed": seed, "video": False}}
    if update_backend != "torch":  # ppo.update_backend (a PPO world's): only where asked, so older configs keep their bytes
        data["ppo"] = {"update_backend": update_backend}
    return RunConfig.from_dict(data)


def run_side(side: str, args) -> None:
    import torch

    from rlbackdoors.train import train
    from rlbackdoors.train.group import train_group

    torch.set_num_threads(1)
    out = Path(args.out) / side
    seeds = range(args.first_seed, args.seeds)
    todo = [s for s in seeds if not (out / f"s{s}" / "metrics.json").is_file()]
    print(f"{side}: {len(todo)} of {len(seeds)} runs to train", file=sys.stderr, flush=True)
    if side == "alone":
        for s in todo:
            m = train(config(args.world, args.arch, s), out / f"s{s}", progress=False)
            print(f"alone s{s}: converged={m['converged']} at {m['converged_at_frames']} frames, {m['cpu_time_s']} CPU-s", file=sys.stderr, flush=True)
    else:

        def done(key, metrics, error) -> None:
            state = (
                f"converged={metrics['converged']} at {metrics['converged_at_frames']} frames, {metrics['cpu_time_s']} CPU-s" if metrics else f"failed: {error}"
            )
            print(f"group s{key}: {state}", file=sys.stderr, flush=True)

        result = train_group(
            [(s, config(args.world, args.arch, s, args.update_backend), out / f"s{s}") for s in todo], args.group_size, on_done=done, device=args.device
        )
        if result.errors:
            raise SystemExit(f"group: {len(result.errors)} runs failed: {result.errors}")


# The equivalence margins (two one-sided tests, TOST): a grouped model's outcome counts as the
# same as a lone one's when the shift between the sides is provably inside these. Success rates:
# 0.02, 4 of the final evaluation's 200 episodes (one model's own binomial error there is about
# 0.012 at SR 0.97). Frames to converge: a quarter of the lone side's median, a zoo's cost.
MARGINS = {"frames_to_converge": {"relative_to_alone_median": 0.25}, "clean_sr": {"absolute": 0.02}, "poisoned_sr": {"absolute": 0.02}}


def column(rows: list[dict], key: str) -> list:
    return [r[key] for r in rows if r.get(key) is not None]


def conv_frames(rows: list[dict]) -> list[int]:
    """Frames to converge; a run that met the thresholds only on its final evaluation (at max_frames) converged at its last frame."""
    return [r["converged_at_frames"] or r["frames"] for r in rows if r["converged"]]


def tost_p(alone: list[float], grouped: list[float], margin: float) -> float:
    """Equivalence within +-MARGIN: two one-sided Mann-Whitney tests of a location shift (the
    grouped side moved by the margin), H0 shift <= -margin and H0 shift >= +margin; the larger p.
    Below 0.05, the shift is inside the margin at that level."""
    from scipy import stats

    lower = stats.mannwhitneyu([x + margin for x in grouped], alone, alternative="greater").pvalue
    upper = stats.mannwhitneyu([x - margin for x in grouped], alone, alternative="less").pvalue
    return float(max(lower, upper))


def compare(alone: list[dict], grouped: list[dict]) -> dict:
    """The report's tests on two sides' per-run rows: difference tests (Fisher's exact on the
    converged counts, two-sided Mann-Whitney U on frames to converge and the final success rates)
    and equivalence tests (TOST within :data:`MARGINS`)."""
    from scipy import stats

    tests: dict = {}
    if not (alone and grouped):
        return tests
    a_conv, g_conv = sum(r["converged"] for r in alone), sum(r["converged"] for r in grouped)
    tests["converged_fisher_p"] = float(stats.fisher_exact([[a_conv, len(alone) - a_conv], [g_conv, len(grouped) - g_conv]])[1])
    for key, a, g in (
        ("frames_to_converge", conv_frames(alone), conv_frames(grouped)),
        ("clean_sr", column(alone, "clean_sr"), column(grouped, "clean_sr")),
        ("poisoned_sr", column(alone, "poisoned_sr"), column(grouped, "poisoned_sr")),
    ):
        if len(a) >= 2 and len(g) >= 2:
            tests[f"{key}_mannwhitney_p"] = float(stats.mannwhitneyu(a, g, alternative="two-sided").pvalue)
            margin = MARGINS[key].get("absolute") or MARGINS[key]["relative_to_alone_median"] * statistics.median(a)
            tests[f"{key}_tost_p"] = tost_p(a, g, margin)
    a_cpu, g_cpu = column(alone, "cpu_time_s"), column(grouped, "cpu_time_s")
    if a_cpu and g_cpu:
        tests["cpu_per_model_ratio_alone_over_group"] = round(round(statistics.fmean(a_cpu), 1) / round(statistics.fmean(g_cpu), 1), 3)
    return tests


def report(args) -> dict:
    from rlbackdoors.bench.machine import machine_info
    from rlbackdoors.io import atomic_write_text

    sides, names = {}, {}
    for side in ("alone", "group"):
        paths = sorted(Path(args.out, side).glob("s*/metrics.json"))
        sides[side], names[side] = [json.loads(p.read_text()) for p in paths], [p.parent.name for p in paths]
    if args.against:  # the lone side of an earlier report (its per-run rows): same configs, same lone bytes
        earlier = json.loads(Path(args.against).read_text())["runs"]["alone"]
        known = {row["run"] for row in earlier}
        # plus this folder's lone runs of seeds the earlier report did not train (--first-seed)
        more = [(r, name) for r, name in zip(sides["alone"], names["alone"]) if name not in known]
        sides["alone"] = earlier + [r for r, _ in more]
        names["alone"] = [row["run"] for row in earlier] + [name for _, name in more]
    alone, grouped = sides["alone"], sides["group"]
    table = {}
    for side, rows in sides.items():
        cpu = column(rows, "cpu_time_s")
        table[side] = {
            "runs": len(rows),
            "converged": sum(r["converged"] for r in rows),
            "frames_to_converge_median": statistics.median(conv_frames(rows)) if conv_frames(rows) else None,
            "clean_sr_mean": round(statistics.fmean(column(rows, "clean_sr")), 4) if rows else None,
            "poisoned_sr_mean": round(statistics.fmean(column(rows, "poisoned_sr")), 4) if rows else None,
            "cpu_s_per_model": round(statistics.fmean(cpu), 1) if cpu else None,
            "trainer": sorted({r.get("trainer") or "alone" for r in rows}),
            "devices": sorted({r.get("device") or "cpu" for r in rows}),  # (runs from before the record: cpu)
        }
    tests = compare(alone, grouped)
    result = {
        "world": args.world,
        "arch": args.arch,
        "seeds": args.seeds,
        "group_size": args.group_size,
        "update_backend": args.update_backend,
        "alone_from": args.against,
        "sides": table,
        "tests": tests,
        "margins": MARGINS,
        "machine": machine_info(),
        "loadavg": [round(x, 2) for x in os.getloadavg()],
        # per run, so that a later side (another group step, another machine) can be tested against these
        "runs": {
            side: [
                {
                    key: r.get(key)
                    for key in ("seed", "converged", "converged_at_frames", "frames", "clean_sr", "poisoned_sr", "cpu_time_s", "trainer", "device", "conv")
                }
                | {"run": name}
                for r, name in zip(rows, names[side])
            ]
            for side, rows in sides.items()
        },
    }
    atomic_write_text(ROOT / "experiments" / "group_equivalence" / args.json, json.dumps(result, indent=2) + "\n")
    print("| side | runs | converged | median frames to converge | clean SR | poisoned SR | CPU-s per model |")
    print("|---|---|---|---|---|---|---|")
    for side, row in table.items():
        print(
            f"| {side} | {row['runs']} | {row['converged']} | {row['frames_to_converge_median']} | {row['clean_sr_mean']} | {row['poisoned_sr_mean']} | {row['cpu_s_per_model']} |"
        )
    print(json.dumps(tests, indent=2))
    return result


def retest(path: Path) -> dict:
    """Run :func:`compare` again on a report's per-run rows (tests added since it was written) and
    write its ``tests`` and ``margins`` back; every measured figure in it stays as it was."""
    from rlbackdoors.io import atomic_write_text

    result = json.loads(path.read_text())
    result["tests"] = compare(result["runs"]["alone"], result["runs"]["group"])
    result["margins"] = MARGINS
    atomic_write_text(path, json.dumps(result, indent=2) + "\n")
    print(f"{path.name}: {json.dumps(result['tests'])}")
    return result


def plot(reports: list[Path], out: Path) -> None:
    """One row per report, one panel per outcome: every run of each side (jittered, a fixed draw)
    with the side's median, titled with the TOST p (equivalence within its margin below 0.05)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    outcomes = (("frames_to_converge", "frames to converge (M)"), ("clean_sr", "clean SR"), ("poisoned_sr", "poisoned SR"))
    fig, axes = plt.subplots(len(reports), 3, figsize=(10, 2.3 * len(reports)), squeeze=False)
    jitter = np.random.default_rng(0)
    for row, path in zip(axes, reports):
        result = json.loads(path.read_text())
        runs, tests = result["runs"], compare(result["runs"]["alone"], result["runs"]["group"])
        for ax, (key, label) in zip(row, outcomes):
            for x, side in enumerate(("alone", "group")):
                values = [v / 1e6 for v in conv_frames(runs[side])] if key == "frames_to_converge" else column(runs[side], key)
                ax.scatter(x + jitter.uniform(-0.15, 0.15, len(values)), values, s=10, alpha=0.6, color=("tab:blue", "tab:orange")[x])
                if values:
                    ax.hlines(statistics.median(values), x - 0.3, x + 0.3, color="black", linewidth=1.5)
            ax.set_xticks([0, 1], [f"alone ({len(runs['alone'])})", f"grouped ({len(runs['group'])})"])
            ax.set_xlim(-0.6, 1.6)
            p = tests.get(f"{key}_tost_p")
            ax.set_title(f"{label}: TOST p = {p:.2g}" if p is not None else label, fontsize=9)
        row[0].set_ylabel(
            f"{result['world']} {result['arch']}\nK={result['group_size']}"
            + (f" {result['update_backend']}" if result.get("update_backend", "torch") != "torch" else ""),
            fontsize=8,
        )
    fig.suptitle("Grouped against lone training: each run's outcome, the sides' medians (lines)", fontsize=10)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    part = out.with_name(out.stem + ".part.png")
    fig.savefig(part, dpi=90)
    plt.close(fig)
    part.replace(out)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--side", choices=("alone", "group"))
    parser.add_argument("--report", action="store_true")
    parser.add_argument("--world", default="lavaworld")
    parser.add_argument("--arch", default="fc")
    parser.add_argument("--seeds", type=int, default=20, help="train seeds --first-seed .. SEEDS-1")
    parser.add_argument("--first-seed", type=int, default=0, help="a side's first seed (more seeds for an earlier report: with --against)")
    parser.add_argument("--update-backend", default="torch", choices=("torch", "jax", "compiled"), help="the group side's ppo.update_backend")
    parser.add_argument("--against", help="--report: take the lone side from this earlier report's runs")
    parser.add_argument("--group-size", type=int, default=8)
    parser.add_argument("--device", choices=("cpu", "cuda"), help="where the group side trains (default: the config's train.device)")
    parser.add_argument("--out", default=str(ROOT / "runs" / "group-equivalence"))
    parser.add_argument("--json", default="group_equivalence.json", help="--report: the file under experiments/group_equivalence/ it writes")
    parser.add_argument("--retest", nargs="+", type=Path, metavar="REPORT", help="run the tests again on these reports' per-run rows, in place")
    parser.add_argument("--plot", nargs="+", type=Path, metavar="REPORT", help="one figure of these reports' runs, a row per report (--png)")
    parser.add_argument("--png", type=Path, default=ROOT / "experiments" / "group_equivalence" / "group_equivalence_all.png", help="--plot: the figure")
    args = parser.parse_args()
    if args.plot:
        plot(args.plot, args.png)
        print(args.png)
        return 0
    if args.retest:
        for path in args.retest:
            retest(path)
        return 0
    if args.side:
        run_side(args.side, args)
    if args.report or not args.side:
        report(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
