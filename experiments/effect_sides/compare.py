"""Which side of ``effect``'s anomaly reads mitigated models as trojaned (issue 82's "scored as clean").

    python experiments/effect_sides/compare.py runs/stack-features/round-lavaworld-train \
        runs/stack-features/round-lavaworld-test runs/stack-features/mitigated-mitigated-round103

On cached member features (``experiments/stack_bound/features.py`` for the round's splits,
``features.py --mitigated`` for the mitigated test models), fits ``effect`` on the train rows with its
anomaly taken several ways (``two``: the shipped largest |z|; ``up``: the trojan side only, no
``down_`` maxima; ``norobust``: both sides but no credit for moving or losing less than clean
models, ``down_shift`` and ``down_success_drop``; ...), scores the test rows and the mitigated
ones, and prints the round's AUC and CE, per family, and the mitigated models' mean probability
before and after with the AUC of before against after. Then, for ``norobust``, which summary
feature carries each mitigated model's anomaly. The variants replace the module's ``_anomaly`` for
the study only; the detector is unchanged.
"""

from __future__ import annotations

import json
import sys
from collections import Counter
from pathlib import Path

import numpy as np
from sklearn.metrics import log_loss, roc_auc_score

import rlbackdoors.detect.baselines.effect as E
from rlbackdoors.detect.api import make_detector

VARIANTS = ("two", "up", "up_conc2", "pos", "nodown", "norobust")
ROBUST = ("down_shift", "down_success_drop")  # moving or losing less than clean models under an edit


def load(folder: str) -> list[dict]:
    return [json.loads(p.read_text()) | {"model": p.stem} for p in sorted(Path(folder).glob("*.json"))]


def trojan_side(name: str, z: float) -> float:
    """A shift or a success drop counts upward only; the rest both ways."""
    return z if ("shift" in name or "success_drop" in name) else abs(z)


def anomaly(variant: str):
    """The largest standardised excess of a row against a reference, taken ``variant``'s way."""

    def largest(row: dict, reference: dict) -> float:
        names = [n for n in reference["features"] if n in row]
        have = [k for k, n in enumerate(reference["features"]) if n in row]
        z = (np.array([float(row[n]) for n in names]) - np.asarray(reference["mean"])[have]) / np.asarray(reference["scale"])[have]
        if variant == "two":
            return float(np.abs(z).max())
        if variant == "pos":
            return float(z.max())
        if variant == "up":  # the trojan side only: no down_ maxima, positive z
            return float(max(v for n, v in zip(names, z) if not n.startswith("down_")))
        if variant == "nodown":  # both sides, no down_ maxima
            return float(max(abs(v) for n, v in zip(names, z) if not n.startswith("down_")))
        if variant == "up_conc2":  # as up, concentration both ways
            return float(max(abs(v) if "concentration" in n else v for n, v in zip(names, z) if not n.startswith("down_") or n == "down_concentration"))
        if variant == "norobust":
            return float(max(trojan_side(n, v) for n, v in zip(names, z) if n not in ROBUST))
        raise ValueError(variant)

    return largest


def effect_row(r: dict) -> dict:
    return {k.split(":", 1)[1]: v for k, v in r["features"].items() if k.startswith("effect:")}


def family(r: dict) -> str:
    parts = r["cell"].split("/")
    return parts[3] if len(parts) > 3 else "envmix"


def fitted(train: list[dict]):
    det = make_detector("effect")
    det.fit_rows([effect_row(r) for r in train], [r["group"] for r in train], np.array([r["label"] for r in train]))
    return det


def main() -> None:
    train, test = load(sys.argv[1]), load(sys.argv[2])
    mitigated = load(sys.argv[3]) if len(sys.argv) > 3 else []
    y = np.array([r["label"] for r in test])
    by_name = {r["model"]: r for r in test}
    shipped = E._anomaly
    for variant in VARIANTS:
        E._anomaly = anomaly(variant)
        det = fitted(train)
        p = np.array([det.classify(effect_row(r), r["group"]) for r in test])
        per = []
        for fam in sorted({family(r) for r in test if r["label"]}):
            keep = [i for i, r in enumerate(test) if not r["label"] or family(r) == fam]
            per.append(f"{fam} {roc_auc_score(y[keep], p[keep]):.3f}")
        line = f"{variant:9s} AUC {roc_auc_score(y, p):.3f} CE {log_loss(y, np.clip(p, 1e-12, 1 - 1e-12)):.3f} | " + ", ".join(per)
        if mitigated:
            after = {r["model"]: det.classify(effect_row(r), r["group"]) for r in mitigated}
            before = {r["model"]: float(p[i]) for i, r in enumerate(test)}
            poisoned = [m for m in after if by_name[m]["label"]]
            clean = [m for m in after if not by_name[m]["label"]]

            def auc(names: list[str]) -> float:
                return roc_auc_score([1] * len(names) + [0] * len(names), [before[m] for m in names] + [after[m] for m in names])

            line += (
                f" || mitigated: poisoned {np.mean([before[m] for m in poisoned]):.3f}->{np.mean([after[m] for m in poisoned]):.3f} AUC {auc(poisoned):.3f};"
                f" clean {np.mean([before[m] for m in clean]):.3f}->{np.mean([after[m] for m in clean]):.3f} ({len(poisoned)}+{len(clean)})"
            )
        print(line)
    # which summary feature carries each model's anomaly (norobust), after mitigation and before
    E._anomaly = anomaly("norobust")
    det = fitted(train)
    for label in (0, 1):
        counts = {"after": Counter(), "before": Counter()}
        for r in mitigated:
            if by_name[r["model"]]["label"] != label:
                continue
            for side, src in (("after", r), ("before", by_name[r["model"]])):
                row = effect_row(src)
                ref = det.reference[src["group"]]
                full = {**row, **E._maxima(row, ref["candidates"])}
                s = ref["summary"]
                z = {n: (full[n] - m) / sc for n, m, sc in zip(s["features"], s["mean"], s["scale"]) if n in full}
                counts[side][max((trojan_side(n, v), n) for n, v in z.items() if n not in ROBUST)[1]] += 1
        print("label", label, "after:", counts["after"].most_common(), "before:", counts["before"].most_common())
    E._anomaly = shipped


if __name__ == "__main__":
    main()
