"""PPO's group update by torch against ``ppo.update_backend = "jax"`` (then rlbackdoors.algos.jax_update, now rlbackdoors.algos.compiled.update):
the same LavaWorld FC learners and rollouts, updated alternately by each backend in one process,
one torch thread; CPU seconds and wall seconds an update (4 epochs x 5 minibatches of 256 a agent).

    python experiments/jax_update/ab.py --agents 8 --json experiments/jax_update/ab_epyc.json

The rollouts are synthetic (random observations, actions and advantages of a real rollout's
shapes): the arithmetic is the same whatever the numbers.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from rlbackdoors.algos import group
from rlbackdoors.algos.ppo import PPO, Rollout
from rlbackdoors.bench.machine import machine_info
from rlbackdoors.config import RunConfig
from rlbackdoors.models import build_model


def learners(agents: int, backend: str) -> list[PPO]:
    out = []
    for seed in range(agents):
        cfg = RunConfig.from_dict({"env": {"name": "lavaworld"}, "train": {"seed": seed}, "ppo": {"update_backend": backend}})
        torch.manual_seed(seed)
        assert cfg.ppo is not None
        out.append(PPO(build_model("fc", "lavaworld"), cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(seed)))
    return out


def rollout(seed: int, n: int = 1280) -> Rollout:
    g = torch.Generator().manual_seed(seed)
    return Rollout(
        obs=torch.randint(0, 11, (n, 7, 7, 3), generator=g, dtype=torch.uint8),
        actions=torch.randint(0, 3, (n,), generator=g),
        logprobs=-torch.rand(n, generator=g),
        values=torch.randn(n, generator=g),
        advantages=torch.randn(n, generator=g),
        returns=torch.randn(n, generator=g),
        rewards=None,
        dones=None,
        outcomes=None,
        steps=None,
        num_envs=10,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agents", type=int, default=8)
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--updates", type=int, default=10, help="updates a round and backend")
    parser.add_argument("--json")
    args = parser.parse_args()
    torch.set_num_threads(1)
    sides = {backend: learners(args.agents, backend) for backend in ("torch", "jax")}
    rollouts = [rollout(s) for s in range(args.agents)]
    start = time.perf_counter()
    group.update(sides["jax"], rollouts)  # JAX's start-up and compile, timed apart
    first = time.perf_counter() - start
    group.update(sides["torch"], rollouts)
    times: dict[str, dict[str, list[float]]] = {b: {"cpu_ms": [], "wall_ms": []} for b in sides}
    for _ in range(args.rounds):
        for backend, ppos in sides.items():
            cpu, wall = time.process_time(), time.perf_counter()
            for _ in range(args.updates):
                group.update(ppos, rollouts)
            times[backend]["cpu_ms"].append((time.process_time() - cpu) / args.updates * 1e3)
            times[backend]["wall_ms"].append((time.perf_counter() - wall) / args.updates * 1e3)
    medians = {b: {k: round(statistics.median(v), 2) for k, v in t.items()} for b, t in times.items()}
    result = {
        "what": "one group update (LavaWorld FC, 1,280 frames a agent, 4 epochs x 5 minibatches) by each backend, alternated",
        "command": f"python experiments/jax_update/ab.py --agents {args.agents} --rounds {args.rounds} --updates {args.updates}",
        "agents": args.agents,
        "first_jax_update_s": round(first, 2),
        "median": medians,
        "jax_over_torch_cpu": round(medians["jax"]["cpu_ms"] / medians["torch"]["cpu_ms"], 3),
        "rounds": {b: {k: [round(x, 2) for x in v] for k, v in t.items()} for b, t in times.items()},
        "machine": machine_info(),
    }
    text = json.dumps(result, indent=2) + "\n"
    print(text, end="")
    if args.json:
        from rlbackdoors.io import atomic_write_text

        atomic_write_text(args.json, text)


if __name__ == "__main__":
    main()
