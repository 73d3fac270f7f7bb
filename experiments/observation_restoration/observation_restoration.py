"""Can LavaWorld's observation trigger be restored from the model off-policy, as BIRD restores one?
(issue 57: an optimised restoration in the family's parameters)

    python experiments/observation_restoration/observation_restoration.py ZOO [--json observation_restoration.json]

For every converged model of ZOO (the issue-57 benchmark zoo): 16 clean episodes are played by the
model and their observations recorded; every member of the family ``o' = (a*o + b) mod 256`` (509:
a in 2..255, b in 1..255) is applied to them as the env applies it (its byte table) and scored by
how far it moves the policy, the mean Jensen-Shannon divergence (nats) between the action
distributions on the edited and the clean observations. Reported per model: the true trigger's rank
among the whole family and among the paper's ranges (a 10..24, b 20..200; 196 members), the rank by
a peak score (the shift less the mean of the same kind's values 4, 6 and 8 away, both sides), and
the best member in range. Why a scan and not gradient ascent on a relaxation of a and b: the family
is one integer per kind (the relaxation is exact at the integers, the env applies integers only),
and scoring all of it costs under a second a model, so the scan gives the objective's exact
optimum, which a gradient could only approach. Writes the JSON beside this file.
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent


def family():
    from rlbackdoors.triggers.observation import KINDS, ObservationTrigger

    out = []
    for kind in KINDS:
        for value in range(1, 256):
            try:
                out.append(ObservationTrigger(kind, value))
            except ValueError:
                pass
    return out


def record(agent, envs, seed: int) -> np.ndarray:
    """One clean episode per slot played by the agent; the observations of every live step."""
    obs, _ = envs.reset(seed=seed)
    generator = torch.Generator().manual_seed(seed)
    alive = np.ones(envs.num_envs, bool)
    seen = []
    while alive.any():
        seen.append(np.asarray(obs)[alive].copy())
        actions, _ = agent.act(obs, None, generator=generator)
        obs, _, terminated, truncated, _ = envs.step(actions)
        alive &= ~(terminated | truncated)
    return np.concatenate(seen)


@torch.no_grad()
def shifts(agent, observations: np.ndarray, members) -> np.ndarray:
    """Per member, the mean JS divergence between the policy on edited and on clean observations."""
    clean = torch.softmax(agent.policy(torch.from_numpy(observations))[0].double(), -1)
    out = np.empty(len(members))
    for i, member in enumerate(members):
        edited = torch.softmax(agent.policy(torch.from_numpy(member.lookup_table()[observations]))[0].double(), -1)
        mean = 0.5 * (edited + clean)

        def kl(p: torch.Tensor) -> torch.Tensor:
            return (p * (p.clamp_min(1e-12).log() - mean.clamp_min(1e-12).log())).sum(-1)

        out[i] = float((0.5 * (kl(edited) + kl(clean))).mean())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("zoo")
    parser.add_argument("--episodes", type=int, default=16)
    parser.add_argument("--seed", type=int, default=5)
    parser.add_argument("--json", default="observation_restoration.json")
    args = parser.parse_args()
    from rlbackdoors.agent import load
    from rlbackdoors.bench.machine import machine_info
    from rlbackdoors.io import atomic_write_text
    from rlbackdoors.poison.mix import make_vector_env
    from rlbackdoors.triggers.observation import PAPER_RANGES

    torch.set_num_threads(1)
    members = family()
    specs = [m.spec() for m in members]
    index = {s: i for i, s in enumerate(specs)}
    in_range = [i for i, m in enumerate(members) if PAPER_RANGES[m.kind][0] <= m.value <= PAPER_RANGES[m.kind][1]]
    rows = [r for r in csv.DictReader(open(Path(args.zoo) / "METADATA.csv")) if r["converged"] == "True"]
    out = []
    for n, r in enumerate(rows):
        agent = load(Path(args.zoo) / "models" / r["model_name"])
        envs = make_vector_env(agent.config.env, None, [False] * args.episodes)
        started = time.perf_counter()
        obs = record(agent, envs, args.seed)
        score = shifts(agent, obs, members)
        seconds = time.perf_counter() - started
        envs.close()

        def peak(i: int) -> float:
            m = members[i]
            near = [score[index[s]] for d in (-8, -6, -4, 4, 6, 8) if (s := f"{m.kind}:{m.value + d}") in index]
            return float(score[i] - np.mean(near))

        true = r["poison.trigger"]
        by_shift = sorted(range(len(members)), key=lambda i: -score[i])
        ranked_in = sorted(in_range, key=lambda i: -score[i])
        by_peak = sorted(in_range, key=lambda i: -peak(i))
        row = {
            "model": r["model_name"],
            "poisoned": r["poisoned"] == "True",
            "attack": r["attack"],
            "trigger": true,
            "states": int(len(obs)),
            "true_rank_family": by_shift.index(index[true]),
            "true_rank_in_range": ranked_in.index(index[true]),
            "true_rank_in_range_by_peak": by_peak.index(index[true]),
            "true_shift": round(float(score[index[true]]), 4),
            "best_in_range": specs[ranked_in[0]],
            "best_in_range_shift": round(float(score[ranked_in[0]]), 4),
            "seconds": round(seconds, 3),
        }
        out.append(row)
        print(f"[{n + 1}/{len(rows)}] {row}", file=sys.stderr, flush=True)
    poisoned = [r for r in out if r["poisoned"]]
    summary = {
        "models": len(out),
        "poisoned": len(poisoned),
        "family_size": len(members),
        "in_range_size": len(in_range),
        "poisoned_true_rank_in_range_median": statistics.median(r["true_rank_in_range"] for r in poisoned),
        "poisoned_true_rank_in_range_by_peak_median": statistics.median(r["true_rank_in_range_by_peak"] for r in poisoned),
        "poisoned_true_in_top5_in_range": sum(r["true_rank_in_range"] < 5 for r in poisoned),
        "poisoned_true_in_top5_by_peak": sum(r["true_rank_in_range_by_peak"] < 5 for r in poisoned),
        "seconds_per_model_median": statistics.median(r["seconds"] for r in out),
    }
    result = {"zoo": str(args.zoo), "episodes": args.episodes, "seed": args.seed, "summary": summary, "models": out, "machine": machine_info()}
    atomic_write_text(HERE / args.json, json.dumps(result, indent=1) + "\n")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
