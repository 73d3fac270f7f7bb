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
import json, math, sys
from pathlib import Path
import numpy as np
from sklearn.metrics import log_loss, roc_auc_score
import rlbackdoors.detect.baselines.effect as E
from rlbackdoors.detect.api import make_detector

def load(folder):
    return [json.loads(p.read_text()) | {"model": p.stem} for p in sorted(Path(folder).glob("*.json"))]

orig = E._anomaly
def make(variant):
    def an(row, reference):
        names = reference["features"]
        have = [k for k, n in enumerate(names) if n in row]
        v = np.array([float(row[names[k]]) for k in have])
        z = (v - np.asarray(reference["mean"])[have]) / np.asarray(reference["scale"])[have]
        nm = [names[k] for k in have]
        if variant == "two":
            return float(np.abs(z).max())
        if variant == "up":  # trojan side only: no down_ maxima, positive z
            keep = [i for i, n in enumerate(nm) if not n.startswith("down_")]
            return float(z[keep].max())
        if variant == "up_conc2":  # as up, concentration both ways
            keep = [i for i, n in enumerate(nm) if not n.startswith("down_") or n == "down_concentration"]
            zz = np.array([abs(z[i]) if "concentration" in nm[i] else z[i] for i in keep])
            return float(zz.max())
        if variant == "pos":
            return float(z.max())
        if variant == "nodown":  # two-sided but no down_ maxima
            keep = [i for i, n in enumerate(nm) if not n.startswith("down_")]
            return float(np.abs(z[keep]).max())
        if variant == "norobust":  # two-sided except robustness: down_shift, down_success_drop dropped; best/peak shift & drop positive
            out = []
            for i, n in enumerate(nm):
                if n in ("down_shift", "down_success_drop"): continue
                out.append(z[i] if ("shift" in n or "success_drop" in n) else abs(z[i]))
            return float(max(out))
        raise ValueError(variant)
    return an

def eff(rows):
    return [{k: v for k, v in r["features"].items() if k.startswith("effect.")} for r in rows]

train, test = load(sys.argv[1]), load(sys.argv[2])
mit = load(sys.argv[3]) if len(sys.argv) > 3 else []

def strip(r):
    return {k.split(":", 1)[1]: v for k, v in r["features"].items() if k.startswith("effect:")}

def fam(r):
    p = r["cell"].split("/")
    return p[3] if len(p) > 3 else "envmix"

ytr = np.array([r["label"] for r in train]); yte = np.array([r["label"] for r in test])
bytest = {r["model"]: r for r in test}
for variant in ("two", "up", "up_conc2", "pos", "nodown", "norobust"):
    E._anomaly = make(variant)
    det = make_detector("effect")
    det.fit_rows([strip(r) for r in train], [r["group"] for r in train], ytr)
    p = np.array([det.classify(strip(r), r["group"]) for r in test])
    fams = sorted({fam(r) for r in test if r["label"]})
    per = []
    for f in fams:
        keep = [i for i, r in enumerate(test) if not r["label"] or fam(r) == f]
        per.append(f"{f} {roc_auc_score(yte[keep], p[keep]):.3f}")
    line = f"{variant:9s} AUC {roc_auc_score(yte, p):.3f} CE {log_loss(yte, np.clip(p,1e-12,1-1e-12)):.3f} | " + ", ".join(per)
    if mit:
        pm = {r["model"]: det.classify(strip(r), r["group"]) for r in mit}
        pb = {r["model"]: float(p[i]) for i, r in enumerate(test)}
        pois = [m for m in pm if bytest[m]["label"]]
        cln = [m for m in pm if not bytest[m]["label"]]
        def auc(ms):
            y = [1]*len(ms)+[0]*len(ms); s = [pb[m] for m in ms]+[pm[m] for m in ms]
            return roc_auc_score(y, s)
        line += f" || mitigated: poisoned {np.mean([pb[m] for m in pois]):.3f}->{np.mean([pm[m] for m in pois]):.3f} AUC {auc(pois):.3f}; clean {np.mean([pb[m] for m in cln]):.3f}->{np.mean([pm[m] for m in cln]):.3f} ({len(pois)}+{len(cln)})"
    print(line)
E._anomaly = orig

# which feature carries the anomaly of mitigated models, variant norobust
E._anomaly = make("norobust")
det = make_detector("effect"); det.fit_rows([strip(r) for r in train], [r["group"] for r in train], ytr)
from collections import Counter
for label in (0, 1):
    c = Counter(); c2 = Counter()
    for r in mit:
        if bytest[r["model"]]["label"] != label: continue
        for src, cnt in ((r, c), (bytest[r["model"]], c2)):
            row = strip(src); ref = det.reference[src["group"]]
            full = {**row, **E._maxima(row, ref["candidates"])}
            s = ref["summary"]; names = s["features"]
            z = {n: (full[n]-m)/sc for n, m, sc in zip(names, s["mean"], s["scale"]) if n in full}
            top = max((v if ("shift" in n or "success_drop" in n) else abs(v), n) for n, v in z.items() if n not in ("down_shift", "down_success_drop"))
            cnt[top[1]] += 1
    print("label", label, "after:", c.most_common(), "before:", c2.most_common())
