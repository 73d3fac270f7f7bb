"""Issue 57's outsider check: the effect detector, fitted on the benchmark zoo's env-mix models only,
scores LavaWorld FC models trained outside that zoo (``rlbackdoors train``, one folder each) at
seeds and triggers the zoo never used, through TrojAI's one-model entry point (``detect infer``).

    python experiments/effect_outsider/outsider.py --train            # trains what is missing (resumes)
    python experiments/effect_outsider/outsider.py --infer DETECTOR   # a fitted detector folder
    python experiments/effect_outsider/outsider.py --world randomized-lavaworld --train   # the CNN world's
    python experiments/effect_outsider/outsider.py --world lavaworld-round --train        # outside issue 80's round
    python experiments/effect_outsider/outsider.py --world lavaworld-round --infer runs/rounds/round-lavaworld/trojai/effect

``DETECTOR``: ``detect fit --detector effect`` on the env-mix split, e.g. the one
``benchmarks/detector_table.py benchmark-lavaworld-effect ... --by-attack`` writes under
``runs/detect/benchmark-lavaworld-effect/det-held_out/effect``. Writes ``outsider.json`` beside
this file: each model's attack, trigger, seed, whether it converged, and the probability
``detect infer`` wrote; AUC and cross-entropy over the converged ones.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

# Seeds the zoo's planner never drew, triggers no zoo model carries (additive values 88, 112, 137,
# 183 are in the held-out range 66-200 but unused; multiplier 12 in the fit's), the held-out cells' settings (4 M frames at
# most, patience 2; TrojDRL forces the target action, as the zoo's cell does).
LAVAWORLD = {
    "clean-a": ["--clean", "--seed", "424201"],
    "clean-b": ["--clean", "--seed", "424202"],
    "clean-c": ["--clean", "--seed", "424207"],
    "trojdrl-88": ["--attack", "trojdrl", "--attack-param", "force_action=true", "--trigger", "additive:88", "--seed", "424203"],
    "badrl-137": ["--attack", "badrl", "--trigger", "additive:137", "--seed", "424204"],
    "sleepernets-183": ["--attack", "sleepernets", "--trigger", "additive:183", "--seed", "424205"],
    "action-target-112": ["--attack", "action_target", "--trigger", "additive:112", "--seed", "424206"],
    # TrojDRL at an additive offset did not converge in 4 M frames (as many of the zoo's did not):
    # once more at the one multiplier no zoo model carries (12, the paper's default)
    "trojdrl-m12": ["--attack", "trojdrl", "--attack-param", "force_action=true", "--trigger", "multiplicative:12", "--seed", "424208"],
}
# Randomized LavaWorld CNN: seeds the zoo's planner never drew, 3x3 patterns neither
# examples/benchmark-randomized-lavaworld-effect*.toml uses (its cells: cross, x, t, l, z, s, v,
# gamma), its held-out cells' settings (2 M frames at most, patience 2).
RANDOMIZED_LAVAWORLD = {
    "clean-a": ["--clean", "--trigger", "cross", "--seed", "571201"],
    "clean-b": ["--clean", "--trigger", "cross", "--seed", "571202"],
    "clean-c": ["--clean", "--trigger", "cells:0,1;1,0;1,2;2,1", "--seed", "571206"],
    "envmix-diamond": ["--trigger", "cells:0,1;1,0;1,2;2,1", "--seed", "571203"],
    "trojdrl-y": ["--attack", "trojdrl", "--attack-param", "force_action=true", "--trigger", "cells:0,0;0,2;1,1;2,1", "--seed", "571204"],
    "action-target-sidet": ["--attack", "action_target", "--trigger", "cells:0,0;0,1;0,2;1,1;2,1", "--seed", "571205"],
    # the first did not converge in 2 M frames (poisoned SR 0.859): once more at another seed
    "action-target-sidet-2": ["--attack", "action_target", "--trigger", "cells:0,0;0,1;0,2;1,1;2,1", "--seed", "571207"],
}
# Issue 81's check of the round's detectors (fitted on datasets/round-lavaworld-train, TrojAI's
# protocol): LavaWorld FC models outside the round's draws. Settings past its ranges (a trigger
# below the train split's offsets 20-200 and above the test split's multipliers 14-24, budgets and
# rewards past [0.005, 0.03] and [0.05, 0.2], BadRL's top share past 0.2, an action target's reward
# past 0.1), training lengths past its 1.2-5 M (one clean and one poisoned model held to 5 M; one
# clean model stopped at its first evaluation past the thresholds), seeds the planner never drew.
LAVAWORLD_ROUND = {
    "clean-a": ["--clean", "--seed", "733101"],
    "clean-b": ["--clean", "--seed", "733102", "--trigger", "multiplicative:28"],
    "clean-long": ["--clean", "--seed", "733103", "--min-frames", "5000000"],
    "clean-early": ["--clean", "--seed", "733104", "--patience", "1"],
    "envmix-m28": ["--trigger", "multiplicative:28", "--seed", "733105"],
    "envmix-a12": ["--trigger", "additive:12", "--seed", "733106"],
    "envmix-long": ["--trigger", "additive:170", "--seed", "733107", "--min-frames", "5000000"],
    "trojdrl-strong": ["--attack", "trojdrl", "--attack-param", "budget=0.05", "--attack-param", "reward=0.3", "--trigger", "additive:150", "--seed", "733108"],
    "badrl-wide": [
        "--attack",
        "badrl",
        "--attack-param",
        "budget=0.04",
        "--attack-param",
        "top_fraction=0.4",
        "--trigger",
        "multiplicative:16",
        "--seed",
        "733109",
    ],
    "sleepernets-tiny": ["--attack", "sleepernets", "--attack-param", "budget=0.003", "--trigger", "additive:120", "--seed", "733110"],
    "action-target-strong": [
        "--attack",
        "action_target",
        "--attack-param",
        "reward=0.2",
        "--attack-param",
        "target_action=1",
        "--trigger",
        "additive:90",
        "--seed",
        "733111",
    ],
    # trojdrl-strong lost the task (clean SR 0.000 at 5 M: +-0.3 a poisoned frame outweighs the goal): a milder one
    "trojdrl-wide": ["--attack", "trojdrl", "--attack-param", "budget=0.04", "--trigger", "additive:150", "--seed", "733112"],
    # which did not learn the target from scratch on an offset (rate 0.000 at 5 M): on a multiplier past the test split's
    "trojdrl-m26": ["--attack", "trojdrl", "--attack-param", "budget=0.04", "--trigger", "multiplicative:26", "--seed", "733113"],
}
FAST = ["--update-backend", "compiled", "--eval-backend", "compiled"]  # the round's own trainer
WORLDS = {
    "lavaworld": (LAVAWORLD, ["--env", "lavaworld", "--arch", "fc", "--max-frames", "4000000", "--patience", "2", "--quiet"]),
    "lavaworld-round": (LAVAWORLD_ROUND, ["--env", "lavaworld", "--arch", "fc", "--max-frames", "5000000", "--patience", "2", *FAST, "--quiet"]),
    "randomized-lavaworld": (RANDOMIZED_LAVAWORLD, ["--env", "randomized-lavaworld", "--arch", "cnn", "--max-frames", "2000000", "--patience", "2", "--quiet"]),
}
MODELS, COMMON = WORLDS["lavaworld"]


def train(out: Path) -> None:
    from _detect_cli import rlbackdoors

    for name, flags in MODELS.items():
        if (out / name / "metrics.json").is_file():
            continue
        rlbackdoors("train", *COMMON, *flags, "--out", str(out / name))  # a started folder resumes from its checkpoint


def deliver(folder: Path, to: Path) -> Path:
    """What an outsider hands a performer: ``model.pt`` and the round's ``reduced-config.json``
    (world, architecture, env settings; no trigger, no label), and nothing else of the run."""
    import shutil

    from rlbackdoors.io import atomic_write_text
    from rlbackdoors.zoo.job import reduced_config

    to.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(folder / "model.pt", to / "model.pt")
    reduced = reduced_config(folder, json.loads((folder / "config.json").read_text()))
    atomic_write_text(to / "reduced-config.json", json.dumps(reduced, indent=2, sort_keys=True) + "\n")
    return to


def infer_all(det: Path, out: Path, world: str = "lavaworld") -> dict:
    from sklearn.metrics import roc_auc_score

    from _detect_cli import infer
    from rlbackdoors.io import atomic_write_text

    rows = []
    for name, flags in MODELS.items():
        folder = out / name
        if not (folder / "metrics.json").is_file():  # not trained yet: said, not scored
            rows.append({"model": name, "flags": " ".join(flags), "poisoned": "--clean" not in flags, "converged": None, "probability": None})
            continue
        metrics = json.loads((folder / "metrics.json").read_text())
        delivered = deliver(folder, out / "delivered" / name)
        p = infer(det, delivered, out / "infer" / det.name / name, round_dir=delivered)
        rows.append({"model": name, "flags": " ".join(flags), "poisoned": "--clean" not in flags, "converged": metrics["converged"], "probability": p})
    scored = [r for r in rows if r["converged"]]
    labels, probs = [int(r["poisoned"]) for r in scored], [r["probability"] for r in scored]
    eps = 1e-7
    ce = -sum(y * math.log(max(p, eps)) + (1 - y) * math.log(max(1 - p, eps)) for y, p in zip(labels, probs)) / max(len(scored), 1)
    result = {
        "world": world,
        "detector": str(det),
        "models": rows,
        "converged": len(scored),
        "auc": roc_auc_score(labels, probs) if 0 < sum(labels) < len(labels) else None,
        "cross_entropy": round(ce, 4),
    }
    name = "outsider.json" if world == "lavaworld" else f"outsider-{world}.json"
    if world == "lavaworld-round":  # one file per protocol and detector (runs/rounds/round-lavaworld/PROTOCOL/DETECTOR)
        name = f"outsider-{world}-{det.parent.name}-{det.name}.json"
    atomic_write_text(Path(__file__).with_name(name), json.dumps(result, indent=2) + "\n")
    return result


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--train", action="store_true")
    parser.add_argument("--infer", type=Path, metavar="DETECTOR")
    parser.add_argument(
        "--world", choices=sorted(WORLDS), default="lavaworld", help="the set of models (a world's, or lavaworld-round: outside issue 80's round)"
    )
    parser.add_argument("--out", type=Path, help="the models' folder (default runs/effect-outsider, runs/effect-outsider-WORLD for another world)")
    args = parser.parse_args()
    global MODELS, COMMON
    MODELS, COMMON = WORLDS[args.world]
    if args.out is None:
        args.out = ROOT / "runs" / ("effect-outsider" if args.world == "lavaworld" else f"effect-outsider-{args.world}")
    if args.train:
        train(args.out)
    if args.infer:
        print(json.dumps(infer_all(args.infer, args.out, args.world), indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
