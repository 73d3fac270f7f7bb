"""Where a CPU group's time goes, against the arithmetic it cannot avoid (issue 55's 2-core bar).

    python benchmarks/group_breakdown.py --agents 8 --frames 400000 --json benchmarks/results/group_breakdown_epyc.json

One group of ``--agents`` LavaWorld FC runs (seeds 0.., every other one poisoned, thresholds at
1.0 as ``bench zoo`` sets them, so each trains ``--frames``) in this process, one torch thread. Its
process CPU time is split into the group's collection (``algos.group.collect``), its update
(``algos.group.update``) and the rest (evaluations, plots, folders, imports). In the same run, two
references: the stacked network's forward and backward on one minibatch of every agent (what the
update's matrix products cost, nothing else), and a large single matrix product (what one core's
BLAS reaches). The floor is PPO's arithmetic: per frame one forward in the rollout and ``epochs``
forwards and backwards (a backward ~ two forwards) at the stacked rate.
"""

from __future__ import annotations

import argparse
import collections
import functools
import json
import os
import platform
import tempfile
import time


def machine() -> dict:
    import torch

    cpu = ""
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), "")
    except OSError:
        pass
    return {"cpu": cpu or platform.processor(), "cores": os.cpu_count(), "torch": torch.__version__, "loadavg": list(os.getloadavg())}


def train_group(agents: int, frames: int, backend: str = "torch") -> dict:
    """CPU seconds of one group's training, by part."""
    from rlbackdoors.algos import group as algos_group
    from rlbackdoors.config import RunConfig
    from rlbackdoors.train import group as train_group_module

    spent: collections.Counter = collections.Counter()

    def timed(name: str):
        original = getattr(algos_group, name)

        @functools.wraps(original)
        def wrapper(*args, **kwargs):
            start = time.process_time()
            try:
                return original(*args, **kwargs)
            finally:
                spent[name] += time.process_time() - start

        setattr(algos_group, name, wrapper)
        return original

    originals = {name: timed(name) for name in ("collect", "update")}
    folder = tempfile.mkdtemp(prefix="group-breakdown-")
    runs = []
    for seed in range(agents):
        train = {"seed": seed, "max_frames": frames, "clean_threshold": 1.0, "poisoned_threshold": 1.0, "video": False, "torch_threads": 1}
        cfg = RunConfig.from_dict({"env": {"name": "lavaworld"}, "train": train, "poison": {"poisoned": seed % 2 == 1}, "ppo": {"update_backend": backend}})
        runs.append((seed, cfg, f"{folder}/m{seed}"))
    start, wall = time.process_time(), time.perf_counter()
    try:
        train_group_module.train_group(runs, agents)
    finally:
        for name, original in originals.items():
            setattr(algos_group, name, original)
    total = time.process_time() - start
    parts = {"collect": spent["collect"], "update": spent["update"], "rest": total - spent["collect"] - spent["update"]}
    return {"cpu_s": round(total, 2), "wall_s": round(time.perf_counter() - wall, 2), "cpu_s_per_model": {k: round(v / agents, 3) for k, v in parts.items()}}


def stacked_rate(agents: int, batch: int, repeats: int = 200) -> tuple[float, int]:
    """GFLOP/s of the stacked FC network's forward and backward on one minibatch a agent, and its
    multiply-adds per row forward."""
    import torch

    from rlbackdoors.models import build_model

    model = build_model("fc", "lavaworld")
    params = {n: torch.stack([p.detach().clone() for _ in range(agents)]).requires_grad_() for n, p in model.named_parameters()}
    macs = sum(p[0].numel() for n, p in params.items() if n.endswith("weight"))
    obs = torch.randint(0, 11, (agents, batch, 7, 7, 3), dtype=torch.uint8)
    x = model.stacked_input(obs)

    def once():
        logits, values = model.forward_stacked_input(params, x)
        torch.autograd.grad(logits.sum() + values.sum(), list(params.values()))

    for _ in range(20):
        once()
    start = time.perf_counter()
    for _ in range(repeats):
        once()
    seconds = (time.perf_counter() - start) / repeats
    return 2 * 3 * macs * agents * batch / seconds / 1e9, macs


def gemm_rate(n: int = 2048, repeats: int = 10) -> float:
    """GFLOP/s of one large fp32 matrix product on this core (the BLAS's best case)."""
    import torch

    a, b = torch.randn(n, n), torch.randn(n, n)
    a @ b
    start = time.perf_counter()
    for _ in range(repeats):
        a @ b
    return 2 * n**3 / ((time.perf_counter() - start) / repeats) / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agents", type=int, default=8)
    parser.add_argument("--frames", type=int, default=400_000)
    parser.add_argument("--update-backend", default="torch", choices=("torch", "jax"), help="ppo.update_backend")
    parser.add_argument("--json", help="write the result here")
    args = parser.parse_args()
    import torch

    from rlbackdoors.config import RunConfig

    torch.set_num_threads(1)
    before = machine()
    ppo = RunConfig.from_dict({"env": {"name": "lavaworld"}}).ppo
    assert ppo is not None
    trained = train_group(args.agents, args.frames, args.update_backend)
    stacked, macs = stacked_rate(args.agents, ppo.batch_size)
    gemm = gemm_rate()
    forwards = 1 + 3 * ppo.epochs  # rollout forward; per epoch a forward and a backward (two forwards' work)
    floor = forwards * 2 * macs * args.frames / (stacked * 1e9)
    result = {
        "what": "one CPU group of LavaWorld FC runs: CPU seconds per model by part, and the arithmetic floor",
        "agents": args.agents,
        "update_backend": args.update_backend,
        "frames_per_model": args.frames,
        "machine": before,
        "loadavg_after": list(os.getloadavg()),
        **trained,
        "macs_per_row_forward": macs,
        "stacked_fwd_bwd_gflops": round(stacked, 1),
        "large_gemm_gflops": round(gemm, 1),
        "floor_cpu_s_per_model": round(floor, 3),
        "floor_share": round(floor / (trained["cpu_s"] / args.agents), 3),
    }
    text = json.dumps(result, indent=2) + "\n"
    print(text, end="")
    if args.json:
        from rlbackdoors.io import atomic_write_text

        atomic_write_text(args.json, text)


if __name__ == "__main__":
    main()
