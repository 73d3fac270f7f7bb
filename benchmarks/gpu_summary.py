"""Issue 55's judged table from what ``gpu_checks.sh`` wrote into OUTDIR: per world, the GPU
group's frames per second and models per hour against the best CPU setting on every core of
the same machine (the first side of each ``bench_zoo_*.json``), each with its target and
whether it is met, the time a 300-model LavaWorld round would take at the measured rate, and
what the GPU sides settle (:func:`settled`: sides that differ in one setting, against each other).

    python benchmarks/gpu_summary.py OUTDIR      # writes OUTDIR/summary.json and summary.md

A side that ran out of its world's time limit is not in the JSON; it is reported as missing, with
the most it could have done (the world's frames over the time its finished sides left, from
bench.log), never as a figure. The round's time assumes every model trains as many frames as the
median poisoned LavaWorld FC model needed to converge in the equivalence runs of 2026-11-28
(TrojAI's stopping rules; clean models converge no later) and at the measured rate, evaluations
included; that rate comes from models of far fewer frames, whose fixed costs (final evaluations,
files, curves) weigh more, so the estimate errs long, and the table says so.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import NamedTuple

ROOT = Path(__file__).resolve().parents[1]
# world/arch -> (frames/s, x models/h against CPU groups on every core, least K); None: report it
TARGETS = {
    "lavaworld/fc": (1_000_000, 5.0, 256),
    "randomized-lavaworld/cnn": (300_000, 5.0, 64),
    "colorful-memory/*": (100_000, 3.0, None),
    "safety-car-goal/*": (None, 2.0, None),
}
ROUND_MODELS, ROUND_LIMIT_S = 300, 15 * 60
EQUIVALENCE = ROOT / "experiments" / "group_equivalence" / "group_equivalence_2026-11-28.json"


def target(world: str, arch: str):
    return TARGETS.get(f"{world}/{arch}") or TARGETS.get(f"{world}/*")


class Bound(NamedTuple):
    """What bench.log says of one world's run: its size, time limit, exit status and sides planned."""

    models: int
    frames: int
    limit: int
    status: int | None
    planned: int


def limits(log: Path) -> dict[str, Bound]:
    """world/arch -> :class:`Bound` from bench.log's
    '== world arch: M models x F frames, sides: S1 S2 ... (limit T s)' and
    '== end world arch: exit X ...' lines."""
    found: dict = {}
    text = log.read_text() if log.is_file() else ""
    for m in re.finditer(r"^== (\S+) (\S+): (\d+) models x (\d+) frames(?:, sides: (.*?))? \(limit (\d+) s\)", text, re.M):
        found[f"{m[1]}/{m[2]}"] = Bound(int(m[3]), int(m[4]), int(m[6]), None, len((m[5] or "").split()))
    for m in re.finditer(r"^== end (\S+) (\S+): exit (\d+)", text, re.M):
        key = f"{m[1]}/{m[2]}"
        if key in found:
            found[key] = found[key]._replace(status=int(m[3]))
    return found


def why_missing(what: str, bound: Bound | None, spent: float = 0.0) -> str:
    """What became of a side not in the JSON: out of time (with the rate it stayed below), or
    failed. ``spent``: the wall seconds the world's finished sides took out of its limit (a side
    that did not finish had at most the rest, so its rate stayed below the frames over that)."""
    if bound is None:
        return what
    models, frames, limit, status = bound.models, bound.frames, bound.limit, bound.status
    if status == 124:
        left = limit - spent
        if left <= 0:
            return f"{what}: no time was left of its {limit} s"
        span = f"the {left:.0f} s left of its {limit} s" if spent else f"its {limit} s"
        return f"{what} within {span}: below {models * frames / left:,.0f} frames/s, evaluations included"
    return f"{what}: bench zoo exited with {status} (bench.log)"


def summarise(out: Path) -> dict:
    bounds = limits(out / "bench.log")
    rows = []
    lavaworld_rate, measured_frames, eval_share = None, None, None
    for path in sorted(out.glob("bench_zoo_*.json")):
        data = json.loads(path.read_text())
        world, arch, sides = data["world"], data["arch"], data["sides"]
        for side in sides:  # written before bench zoo counted frames (2026-11-29): its planned frames, a lower bound
            if side.get("frames_per_s") is None and side.get("wall_s"):
                side["frames_per_s"] = round(side["models"] * data["frames_per_model"] / side["wall_s"], 1)
        want = target(world, arch)
        ref = sides[0] if sides else None
        gpu = sides[1:]
        row = {
            "world": world,
            "arch": arch,
            "models": data["models"],
            "frames_per_model": data["frames_per_model"],
            "reference": {k: ref.get(k) for k in ("group_size", "device", "workers", "models_per_hour", "frames_per_s", "eval_share", "wall_s")}
            if ref
            else None,
            "sides": [
                {
                    k: s.get(k)
                    for k in (
                        "group_size",
                        "device",
                        "workers",
                        "env_workers",
                        "update_backend",
                        "engine",
                        "conv",
                        "models_per_hour",
                        "frames_per_s",
                        "env_steps_per_s",
                        "eval_share",
                        "ratio",
                        "wall_s",
                    )
                }
                for s in gpu
            ],
        }
        if want is not None:
            fps, ratio, least_k = want
            row["target"] = {"frames_per_s": fps, "ratio": ratio, "least_k": least_k}
        if gpu:
            best_at = max(range(len(gpu)), key=lambda i: gpu[i]["models_per_hour"])
            best = gpu[best_at]
            row["best"], row["best_side"] = best["group_size"], best_at  # K, and which of the GPU sides (two may share a K)
            if want is not None:
                fps, ratio, least_k = want
                row["met"] = {
                    "frames_per_s": None if fps is None else best.get("frames_per_s", 0) >= fps,
                    "ratio": best["ratio"] >= ratio,
                    "k": None if least_k is None else best["group_size"] >= least_k,
                }
            if world == "lavaworld" and arch == "fc":
                lavaworld_rate, measured_frames, eval_share = best.get("frames_per_s"), data["frames_per_model"], best.get("eval_share")
        bound = bounds.get(f"{world}/{arch}")
        spent = sum(side.get("wall_s") or 0 for side in sides)
        if not gpu:
            row["missing"] = why_missing("the GPU side did not finish", bound, spent)
        elif bound is not None and bound.planned > len(sides):  # some GPU sides ran out of the world's time
            unfinished = bound.planned - len(sides)
            row["unfinished"] = why_missing("the next GPU side did not finish", bound, spent) + (
                f"; {unfinished - 1} more did not start" if unfinished > 1 else ""
            )
        rows.append(row)
    measured = {f"{row['world']}/{row['arch']}" for row in rows}
    for name, bound in bounds.items():  # not even the reference side finished
        if name not in measured:
            world, arch = name.split("/", 1)
            rows.append(
                {
                    "world": world,
                    "arch": arch,
                    "models": bound.models,
                    "frames_per_model": bound.frames,
                    "reference": None,
                    "sides": [],
                    "missing": why_missing("no side finished", bound),
                }
            )
    result: dict = {"worlds": rows}
    result["settled"] = settled(result)
    if lavaworld_rate and EQUIVALENCE.is_file():
        per_model = json.loads(EQUIVALENCE.read_text())["sides"]["alone"]["frames_to_converge_median"]
        seconds = ROUND_MODELS * per_model / lavaworld_rate
        result["round"] = {
            "models": ROUND_MODELS,
            "frames_per_model": per_model,
            "frames_per_s": lavaworld_rate,
            "measured_frames_per_model": measured_frames,  # the rate's models: fixed costs a model (evaluations, files) weigh more the fewer frames
            "measured_eval_share": eval_share,  # of their env steps, their evaluations' (None: a bench from before it was counted)
            "estimated_s": round(seconds, 1),
            "limit_s": ROUND_LIMIT_S,
            "met": seconds <= ROUND_LIMIT_S,
        }
    return result


# the settings a world's GPU sides may differ in, and what an empty one means
SETTINGS = {"group_size": None, "workers": None, "update_backend": "torch", "engine": "numba", "conv": "each"}


def settled(result: dict) -> list[dict]:
    """What the GPU sides of each world settle: every pair of sides that differ in one setting
    alone (the group size, the processes, the update backend, the engine, the convolutions), and
    the models per hour of the second against the first, measured in the same run. This is what
    a lease is for: the defaults (``algos.group.DEVICE_ENGINE``, ``models.minigrid.STACKED_CONV``,
    ``train.group.AUTO_GROUP_SIZE``) follow these figures, not a guess."""
    found = []
    for row in result["worlds"]:
        sides = row["sides"]
        for i, a in enumerate(sides):
            for b in sides[i + 1 :]:
                differ = [key for key, empty in SETTINGS.items() if (a.get(key) or empty) != (b.get(key) or empty)]
                if len(differ) != 1 or not a.get("models_per_hour"):
                    continue
                (key,) = differ
                empty = SETTINGS[key]
                found.append(
                    {
                        "world": f"{row['world']} {row['arch']}",
                        "setting": key,
                        "first": a.get(key) or empty,
                        "second": b.get(key) or empty,
                        "ratio": round(b["models_per_hour"] / a["models_per_hour"], 3),
                    }
                )
    return found


def evaluating(side: dict) -> str:
    """ ", evaluations N % of env steps" where the side counted them (bench zoo's eval_share), else ""."""
    share = side.get("eval_share")
    return "" if share is None else f", evaluations {share:.0%} of env steps"


def markdown(result: dict) -> str:
    lines = ["| world | reference (CPU, every core) | GPU side | frames/s (target) | x models/h (target) | met |", "|---|---|---|---|---|---|"]
    for row in result["worlds"]:
        ref = row["reference"] or {}
        want = row.get("target", {})
        ref_text = (
            f"K={ref['group_size']} x {ref['workers']}: {ref.get('frames_per_s') or 0:,.0f} f/s, {ref['models_per_hour']:,.0f} models/h" + evaluating(ref)
            if ref
            else "none"
        )
        if "missing" in row:
            lines.append(f"| {row['world']} {row['arch']} | {ref_text} | {row['missing']} | | | no |")
            continue
        for i, s in enumerate(row["sides"]):
            met = row.get("met", {}) if i == row.get("best_side") else {}
            flags = [k for k, v in met.items() if v is False]
            lines.append(
                f"| {row['world']} {row['arch']} | {ref_text} | K={s['group_size']} on {s['device']}"
                + (f" x {s['workers']} processes" if (s.get("workers") or 1) > 1 else "")
                + (f", {s['update_backend']} update" if s.get("update_backend") not in (None, "torch") else "")
                + (f", {s['engine']} engine" if s.get("engine") else "")
                + (f", {s['conv']} convolutions" if s.get("conv") else "")
                + (f", {s['env_workers']} env workers" if s.get("env_workers") else "")
                + evaluating(s)
                + f" | {s.get('frames_per_s', 0):,.0f} ({want.get('frames_per_s') or 'report'}) | x{s['ratio']} ({want.get('ratio')}) | "
                + ("" if not met else ("yes" if not flags else "no: " + ", ".join(flags)))
                + " |"
            )
        if "unfinished" in row:
            lines.append(f"| {row['world']} {row['arch']} | {ref_text} | {row['unfinished']} | | | |")
    if result.get("settled"):
        lines.append("")
        lines.append("What the GPU sides settle (models/h of the second setting against the first, same run):")
        for x in result["settled"]:
            lines.append(f"- {x['world']}: {x['setting']} {x['second']} against {x['first']}: x{x['ratio']}")
    if "round" in result:
        r = result["round"]
        lines.append("")
        lines.append(
            f"300-model LavaWorld round at {r['frames_per_s']:,.0f} frames/s, {r['frames_per_model']:,.0f} frames a model: "
            f"{r['estimated_s'] / 60:.1f} min (target <= 15 min: {'met' if r['met'] else 'not met'}; the rate measured with models of "
            f"{r['measured_frames_per_model']:,} frames, whose evaluations and files weigh more than in a model of the round's"
            + (f": their evaluations were {r['measured_eval_share']:.0%} of their env steps)" if r.get("measured_eval_share") is not None else ")")
            + ". An estimate: `gpu_checks.sh OUT round` trains the round itself."
        )
    return "\n".join(lines) + "\n"


def main() -> int:
    if len(sys.argv) != 2:
        print("usage: gpu_summary.py OUTDIR", file=sys.stderr)
        return 2
    out = Path(sys.argv[1])
    result = summarise(out)
    (out / "summary.json").write_text(json.dumps(result, indent=2) + "\n")
    text = markdown(result)
    (out / "summary.md").write_text(text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
