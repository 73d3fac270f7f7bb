"""One group minibatch of LavaWorld FC (forward, PPO loss, backward, per-agent clipping and Adam)
eager against the same loss under torch.compile (inductor, dynamic shapes), alternated in one
process, one torch thread.

    python experiments/compiled_update/ab.py --agents 8

The product's group update is not changed; compile.patch is the tried ``ppo.compile`` option
(README.md).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from rlbackdoors.algos.group import FlatParameters, StackedAdam, clip_per_agent, take
from rlbackdoors.algos.ppo import ppo_loss
from rlbackdoors.config import PPOConfig
from rlbackdoors.models import build_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agents", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=6)
    args = parser.parse_args()
    torch.set_num_threads(1)
    K, N, n, cfg = args.agents, 256, 1280, PPOConfig()
    model = build_model("fc", "lavaworld")
    weights = FlatParameters({name: torch.stack([p.detach().clone() for _ in range(K)]) for name, p in model.named_parameters()})
    adam = StackedAdam([(torch.optim.Adam(model.parameters(), lr=cfg.lr), model.get_parameter) for _ in range(K)], weights)
    g = torch.Generator().manual_seed(0)
    inputs = model.stacked_input(torch.randint(0, 11, (K, n, 7, 7, 3), dtype=torch.uint8, generator=g))
    tensors = [torch.randint(0, 3, (K, n), generator=g), -torch.rand(K, n, generator=g)] + [torch.randn(K, n, generator=g) for _ in range(3)]
    rows = torch.arange(K)[:, None]

    def loss_of(params, x, *rest):
        logits, values = model.forward_stacked_input(params, x)
        loss, parts = ppo_loss(cfg, logits, values, *rest)
        return loss.sum(), parts

    def minibatch(fn) -> None:
        flat = (torch.randperm(n, generator=g)[:N].expand(K, N) + rows * n).reshape(-1)
        loss, _ = fn(weights.views, take(inputs, flat, K), *(take(t, flat, K) for t in tensors))
        grad = weights.grad(loss)
        clip_per_agent(grad, cfg.max_grad_norm)
        adam.apply(grad)

    def ms_per_minibatch(fn, repeats: int = 150) -> float:
        for _ in range(5):
            minibatch(fn)
        start = time.perf_counter()
        for _ in range(repeats):
            minibatch(fn)
        return (time.perf_counter() - start) / repeats * 1e3

    compiled = torch.compile(loss_of, dynamic=True)
    start = time.perf_counter()
    minibatch(compiled)
    print(f"compile: {time.perf_counter() - start:.1f} s")
    eager, fused = [], []
    for _ in range(args.rounds):
        eager.append(ms_per_minibatch(loss_of))
        fused.append(ms_per_minibatch(compiled))
    print(
        f"K = {K}: eager {[round(x, 2) for x in eager]} ms, compiled {[round(x, 2) for x in fused]} ms; median ratio {statistics.median(fused) / statistics.median(eager):.3f}"
    )


if __name__ == "__main__":
    main()
