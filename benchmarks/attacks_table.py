"""The per-attack table of docs/results/attacks.md, from benchmarks/results/recipes/attack-*.json.

    python benchmarks/attacks_table.py            # markdown on stdout

One row per recipe (world x arch x attack x trigger kind; world, arch and trigger read from the
recipe's command, the world's default trigger where it names none): converged / attempted over seeds 0-9 with the Wilson 95 %
interval (converged: clean SR >= the world's threshold and attack success >= the attack's, on the
200-episode final evaluation), the range of final clean SR and attack success, the budget the runs
spent (median share of frames poisoned), frames and CPU minutes to converge (median), and CPU minutes
against the env-mix recipe of the same world, arch and trigger kind, measured in the same session.
"""

from __future__ import annotations

import json
import shlex
import statistics
from pathlib import Path

RECIPES = Path(__file__).resolve().parent / "results" / "recipes"


def median(values: list) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


def flag(command: str, name: str, default: str) -> str:
    words = shlex.split(command)
    return words[words.index(name) + 1] if name in words[:-1] else default


def rows() -> list[dict]:
    from rlbackdoors import attacks, worlds

    out = []
    for path in sorted(RECIPES.glob("attack-*.json")):
        data = json.loads(path.read_text())
        command, runs = data["command"], data["runs"]
        world = flag(command, "--env", "lavaworld")
        base = flag(command, "--attack", attacks.DEFAULT_ATTACK)
        # attack-WORLD[-ARCH][-TRIGGER]-ATTACK[-VARIANT]: the label is the attack and its variant
        label = path.stem[path.stem.rindex(base) :] if base in path.stem else path.stem.split("-", 3)[-1]
        trigger = flag(command, "--trigger", "")
        kind = trigger or str(worlds.get(world).default_trigger)
        done = [r for r in runs if r["converged"]]
        used = [(r.get("budget_used") or {}).get("poisoned_fraction") for r in runs]
        out.append(
            {
                "world": world,
                "arch": flag(command, "--arch", worlds.get(world).arch_names[0]),
                "attack": label,
                "base": base,
                "trigger": kind,
                "converged": data["converged"],
                "attempted": data["attempted"],
                "wilson": data["wilson95"],
                "clean": (min(r["clean_sr"] for r in runs), max(r["clean_sr"] for r in runs)) if runs else None,
                "success": (min(r["poisoned_sr"] for r in runs), max(r["poisoned_sr"] for r in runs)) if runs else None,
                "poisoned_fraction": median(used),
                "frames": median([r["frames"] for r in done]),
                "cpu": median([r["cpu_minutes"] for r in done]),
                "pending": len(data["pending"]),
            }
        )
    order, world_order = list(attacks.names()), list(worlds.names())
    out.sort(
        key=lambda r: (
            world_order.index(r["world"]),
            r["arch"],
            r["trigger"] != worlds.get(r["world"]).default_trigger,
            order.index(r["base"]) if r["base"] in order else len(order),
            r["attack"],
        )
    )
    reference = {(r["world"], r["arch"], r["trigger"]): r["cpu"] for r in out if r["attack"] == attacks.DEFAULT_ATTACK}
    for r in out:
        ref = reference.get((r["world"], r["arch"], r["trigger"]))
        r["cpu_ratio"] = r["cpu"] / ref if r["cpu"] is not None and ref else None
    return out


def fmt(value, pattern: str) -> str:
    return "–" if value is None else pattern.format(value)


def main() -> None:
    print(
        "| world / arch | attack | trigger | converged / seeds | Wilson 95 % | clean SR (min–max) | attack success (min–max) | frames poisoned | frames (median) | CPU min (median) | × env mix |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows():
        seeds = f"{r['converged']} / {r['attempted']}" + (f" ({r['pending']} pending)" if r["pending"] else "")
        clean = f"{r['clean'][0]:.3f}–{r['clean'][1]:.3f}" if r["clean"] else "–"
        success = f"{r['success'][0]:.3f}–{r['success'][1]:.3f}" if r["success"] else "–"
        print(
            f"| {r['world']} {r['arch']} | {r['attack']} | {r['trigger']} | {seeds} | [{r['wilson'][0]:.2f}, {r['wilson'][1]:.2f}] | {clean} | {success} | "
            f"{fmt(r['poisoned_fraction'], '{:.2%}') if r['base'] != 'envmix' else 'the E-bar copies'} | {fmt(r['frames'], '{:,.0f}')} | {fmt(r['cpu'], '{:.2f}')} | {fmt(r['cpu_ratio'], '{:.2f}')} |"
        )


if __name__ == "__main__":
    main()
