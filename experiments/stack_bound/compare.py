"""The stack with and without the bound on its members' logits, on cached features (features.py).

    python experiments/stack_bound/compare.py runs/stack-features/round-lavaworld-train runs/stack-features/round-lavaworld-test

Fits ``stack`` (effect, weights, behaviour) on the train folder's rows with ``logit_bound`` none
and cv and the meta model ``logistic`` (before) and ``platt``, scores the test folder's rows, and prints AUC and cross-entropy, the bound chosen and the
meta model's cross-validated log loss per bound (what ``cv`` chooses by: the train split alone).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
from sklearn.metrics import log_loss, roc_auc_score

from rlbackdoors.detect.api import make_detector
from rlbackdoors.detect.baselines.stack import BOUNDS
from rlbackdoors.detect.classifier import fit_platt


def family(row: dict) -> str:
    parts = row["cell"].split("/")
    return parts[3] if len(parts) > 3 else "envmix"


def load(folder: Path) -> list[dict]:
    return [json.loads(p.read_text()) | {"model": p.stem} for p in sorted(folder.glob("*.json"))]


def main() -> None:
    train, test = load(Path(sys.argv[1])), load(Path(sys.argv[2]))
    y_train = np.array([r["label"] for r in train])
    y_test = np.array([r["label"] for r in test])
    print(f"train {len(train)} ({int(y_train.sum())} poisoned), test {len(test)} ({int(y_test.sum())} poisoned)")
    for mode, meta in (("none", "logistic"), ("none", "platt"), ("cv", "platt")):
        stack = make_detector("stack", members="effect,weights,behaviour", logit_bound=mode, meta=meta)
        stack.fit_rows([r["features"] for r in train], [r["group"] for r in train], y_train)
        if mode == "cv":
            for b in BOUNDS:
                rows = [stack._meta_row(stack.oof_logits[i], b) for i in range(len(train))]
                print(f"  bound {b}: meta cv log loss {fit_platt(rows, y_train, 'mean_logit').cv_log_loss:.4f}")
        p = np.array([stack.predict_row(r["features"], r["group"])[0] for r in test])
        worst = sorted(
            ((-math.log(max(1e-12, pi if yi else 1 - pi)), r["model"], r["cell"], round(float(pi), 3)) for pi, yi, r in zip(p, y_test, test)), reverse=True
        )[:5]
        print(f"{mode}/{meta}: bound {stack.bound}, AUC {roc_auc_score(y_test, p):.4f}, CE {log_loss(y_test, np.clip(p, 1e-12, 1 - 1e-12)):.4f}; worst {worst}")
        fams = sorted({family(r) for r in test if r["label"]})
        for fam in fams:
            keep = [i for i, r in enumerate(test) if not r["label"] or family(r) == fam]
            print(
                f"   {fam}: AUC {roc_auc_score(y_test[keep], p[keep]):.3f} CE {log_loss(y_test[keep], np.clip(p[keep], 1e-12, 1 - 1e-12), labels=[0, 1]):.3f}"
            )


if __name__ == "__main__":
    main()
