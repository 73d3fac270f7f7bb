"""How far do the group tests' numbers move with the CPU's kernels alone?

    python experiments/kernel_spread/kernel_spread.py [--json experiments/kernel_spread/kernel_spread.json]

The group tests (tests/test_group.py) compare a group's update with lone learners' "to float
rounding". Rounding is not one number: an update is 4 epochs of Adam steps, and Adam moves a weight
whose gradient is near zero by about its learning rate whatever the gradient's sign, so a 1e-7
difference in one step can become a 1e-3 one two updates later. On another CPU (AVX-512 against
AVX2, oneDNN and MKL picking other kernels) both sides round differently again.

This script measures that spread on one machine, emulating other CPUs by capping the vector unit
that ATen, oneDNN and MKL may use (``ATEN_CPU_CAPABILITY``, ``ONEDNN_MAX_CPU_ISA``,
``MKL_ENABLE_INSTRUCTIONS``: avx512, avx2, and no SIMD at all). For each case of the tests and each
kernel set it runs the test's own learners (lone and grouped, one torch thread) for two rollouts
and updates, and reports per update the largest relative difference of each statistic
(``grad_norm``, ``teacher_kl``, ``aux_memory_loss``, ``anchor_distance``) and the largest absolute
difference of the rollout's log-probabilities (``logprobs_max_abs``, group vs lone), and after the
last update the largest weight difference, group vs lone, in units of the learning rate, and of
Adam's moments on the scale of each tensor's largest moment:

- ``group_vs_lone``: the group against the lone learners under the same kernels (what a test sees);
- ``lone_across_kernels``: the lone learners against themselves under the other kernel sets (what
  changing the CPU alone does, with no group involved).

The tests' tolerances are set from these figures (and say so).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
KERNELS = {
    "native": {},
    "avx2": {"ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2", "MKL_ENABLE_INSTRUCTIONS": "AVX2"},
    "no-simd": {"ATEN_CPU_CAPABILITY": "default", "ONEDNN_MAX_CPU_ISA": "SSE41", "MKL_ENABLE_INSTRUCTIONS": "SSE4_2"},
}
CASES = ("plain-lavaworld", "recurrent-colorful-memory", "teachers-lavaworld", "teachers-colorful-memory")
STATS = ("grad_norm", "teacher_kl", "aux_memory_loss", "anchor_distance")


def run_case(case: str, updates: int) -> dict:
    """The per-update statistics of the case's lone and grouped learners, in this process."""
    import torch

    sys.path.insert(0, str(ROOT / "tests"))
    import test_group as tg

    torch.set_num_threads(1)
    if case == "plain-lavaworld":
        poisons = [None, {"trigger": "additive:135", "attack": "trojdrl", "attack_params": {"budget": 0.05}}, None]
        pair = [[tg.learner("lavaworld", "fc", s, p) for s, p in enumerate(poisons)] for _ in range(2)]
    elif case == "recurrent-colorful-memory":
        pair = [[tg.cm_learner(s) for s in range(3)] for _ in range(2)]
    else:
        world = case.split("-", 1)[1]
        poisons = [{"trigger": t, "attack": "trojdrl", "attack_params": {"budget": 0.2}} for t in ("additive:135", "multiplicative:12", "additive:60")]

        def make(k):
            return tg.learner("lavaworld", "fc", k, poisons[k]) if world == "lavaworld" else tg.cm_learner(k, {"attack": "action_target"})

        pair = [tg.with_anchors(tg.with_teachers([make(k) for k in range(3)], [0.1, 1.0, 0.5]), [0.05, 0.2, 0.1]) for _ in range(2)]
    out = []
    for _ in range(updates):
        lone, results, stats = tg.step_both(*pair)
        logp = max(float((r.logprobs - ours.logprobs).abs().max()) for (r, _), (ours, _) in zip(lone, results))
        out.append(
            {
                "lone": [{k: v for k, v in s.items() if k in STATS} for _, s in lone],
                "group": [{k: v for k, v in s.items() if k in STATS} for s in stats],
                "logprobs_max_abs_difference": logp,  # this update's rollout, group vs lone
            }
        )
    weights = max(
        float((a - b).abs().max()) / lone_ppo.cfg.lr
        for (lone_ppo, _, _), (ppo, _, _) in zip(*pair)
        for a, b in zip(lone_ppo.model.parameters(), ppo.model.parameters())
    )
    moments = {
        moment: max(
            float((lone_ppo.optimizer.state[a][moment] - ppo.optimizer.state[b][moment]).abs().max())
            / max(float(lone_ppo.optimizer.state[a][moment].abs().max()), 1e-30)
            for (lone_ppo, _, _), (ppo, _, _) in zip(*pair)
            for a, b in zip(lone_ppo.model.parameters(), ppo.model.parameters())
        )
        for moment in ("exp_avg", "exp_avg_sq")
    }
    return {"capability": torch.backends.cpu.get_cpu_capability(), "updates": out, "weights_max_abs_difference_in_lr": weights, "adam_moments": moments}


def rel(a: float, b: float) -> float:
    return abs(a - b) / max(abs(a), abs(b), 1e-12)


def spread(runs: dict, updates: int) -> dict:
    """Largest relative differences per update and statistic (module doc)."""
    result: dict = {"group_vs_lone": [], "lone_across_kernels": []}
    for u in range(updates):
        within: dict = {}
        across: dict = {}
        for name, run in runs.items():
            for lone, group in zip(run["updates"][u]["lone"], run["updates"][u]["group"]):
                for key in lone:
                    within[key] = max(within.get(key, 0.0), rel(lone[key], group[key]))
            for other in runs.values():
                for a, b in zip(run["updates"][u]["lone"], other["updates"][u]["lone"]):
                    for key in a:
                        across[key] = max(across.get(key, 0.0), rel(a[key], b[key]))
        within["logprobs_max_abs"] = max(run["updates"][u]["logprobs_max_abs_difference"] for run in runs.values())
        result["group_vs_lone"].append(within)
        result["lone_across_kernels"].append(across)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", default=None, help="write the figures here")
    parser.add_argument("--updates", type=int, default=2)
    parser.add_argument("--case", default=None, help=argparse.SUPPRESS)  # a child process: one case, printed as JSON
    args = parser.parse_args()
    if args.case:
        print(json.dumps(run_case(args.case, args.updates)))
        return
    started = time.time()
    result: dict = {
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "cpu": next((line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name")), "?"),
        "load_before": os.getloadavg()[0],
        "updates": args.updates,
        "kernels": KERNELS,
        "cases": {},
    }
    for case in CASES:
        runs = {}
        for name, env in KERNELS.items():
            child = subprocess.run(
                [sys.executable, __file__, "--case", case, "--updates", str(args.updates)],
                env={**os.environ, **env, "OMP_NUM_THREADS": "1"},
                capture_output=True,
                text=True,
                check=True,
            )
            runs[name] = json.loads(child.stdout.strip().splitlines()[-1])
        weights = max(r["weights_max_abs_difference_in_lr"] for r in runs.values())
        result["cases"][case] = {
            "capabilities": {n: r["capability"] for n, r in runs.items()},
            **spread(runs, args.updates),
            "weights_max_abs_difference_in_lr": weights,  # group vs lone after the last update, in learning rates
            "runs": runs,
        }
        moments = {m: max(r["adam_moments"][m] for r in runs.values()) for m in ("exp_avg", "exp_avg_sq")}
        result["cases"][case]["adam_moments_max_difference_on_their_scale"] = moments
        print(
            f"{case:28s} after {args.updates} updates, group vs lone: weights {weights:.2f} learning rates, Adam moments "
            + ", ".join(f"{m} {v:.1e}" for m, v in moments.items())
            + " of each tensor's largest"
        )
        for u in range(args.updates):
            g = result["cases"][case]["group_vs_lone"][u]
            a = result["cases"][case]["lone_across_kernels"][u]
            print(
                f"{case:28s} update {u + 1}: group vs lone "
                + ", ".join(f"{k} {v:.1e}" for k, v in g.items())
                + " | lone across kernels "
                + ", ".join(f"{k} {v:.1e}" for k, v in a.items())
            )
    result["seconds"] = round(time.time() - started, 1)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
