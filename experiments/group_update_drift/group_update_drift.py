"""Is the group trainer's update biased against a lone learner's, or only rounded differently?

    python experiments/group_update_drift/group_update_drift.py [--updates 1 3 6]

Two LavaWorld FC learners (seeds 0 and 1) trained alone and, from the same start, in a group (the
stacked path), on one torch thread, for 1, 3 and 6 rollouts + updates. For each agent it prints
the slope of the group's parameter change on the lone one's (1 if unbiased) and their relative
difference. A scaling bias (a learning rate, an Adam term, a clipping rule computed differently)
would show as a slope away from 1 after one update; rounding shows as a relative difference of
about 1e-6 after one update that grows (Adam moves a weight whose gradient is near zero by about
its learning rate whatever the gradient's sign) until the two sample other actions, after which
they part as two seeds do. It also prints, per rollout, how many sampled actions differ.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
from test_group import learner, step_both  # noqa: E402  (the learners the group tests compare)


def flat(model: torch.nn.Module) -> torch.Tensor:
    return torch.cat([p.detach().flatten().double() for p in model.parameters()])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--updates", type=int, nargs="+", default=[1, 3, 6])
    args = parser.parse_args()
    torch.set_num_threads(1)
    for n in args.updates:
        alone = [learner("lavaworld", "fc", seed) for seed in range(2)]
        grouped = [learner("lavaworld", "fc", seed) for seed in range(2)]
        start = [flat(a[0].model) for a in alone]
        differ = []
        for _ in range(n):
            lone_pairs, results, _ = step_both(alone, grouped)
            differ.append([int((lone_pairs[k][0].actions != results[k][0].actions).sum()) for k in range(2)])
        for k in range(2):
            lone, ours = flat(alone[k][0].model) - start[k], flat(grouped[k][0].model) - start[k]
            slope = float((lone * ours).sum() / (lone * lone).sum())
            actions = [d[k] for d in differ]
            print(
                f"{n} updates, agent {k}: slope {slope:.7f}, relative difference {float((ours - lone).norm() / lone.norm()):.2e}, actions differing per rollout {actions}"
            )


if __name__ == "__main__":
    main()
