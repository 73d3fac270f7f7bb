"""Where a group's time goes: by part, and on a CPU against the arithmetic it cannot avoid (issue 55).

    python benchmarks/group_breakdown.py --agents 8 --frames 400000 --json benchmarks/results/group_breakdown_epyc.json
    python benchmarks/group_breakdown.py --agents 256 --frames 10000 --device cuda   # a GPU group's wall, by part

One group of ``--agents`` runs of ``--world`` (seeds 0.., every other one poisoned, thresholds at
1.0 as ``bench zoo`` sets them, so each trains ``--frames``) in this process, one torch thread, on
``--device``. Its process CPU time and its wall time are split by the group's batched calls:
collection, update, lockstep evaluation (OPAC²: act, learn), and the rest (lone requests, plots,
folders, imports); on a GPU each call is synchronised, so the wall shares say what the GPU group
waits on. For a CPU group of LavaWorld FC, two references in the same run: the stacked network's
forward and backward on one minibatch of every agent (what the update's matrix products cost,
nothing else), and a large single matrix product (what one core's BLAS reaches). The floor is
PPO's arithmetic: per frame one forward in the rollout and ``epochs`` forwards and backwards (a
backward ~ two forwards) at the stacked rate.
"""

from __future__ import annotations

import argparse
import collections
import functools
import json
import os
import platform
import shutil
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


def top_ops(profiler, rows: int, wall_s: float) -> dict:
    """One profiled call: its wall ms, the operations' total self time on the host and the device
    and their count (what the wall leaves over is Python and the engines), and the ``rows``
    operations with the most self time on the host."""
    events = list(profiler.key_averages())
    top = sorted(events, key=lambda e: e.self_cpu_time_total, reverse=True)[:rows]
    device_ms = lambda e: getattr(e, "self_device_time_total", 0) / 1e3  # noqa: E731
    return {
        "wall_ms": round(wall_s * 1e3, 1),
        "ops": sum(e.count for e in events),
        "ops_host_ms": round(sum(e.self_cpu_time_total for e in events) / 1e3, 1),
        "ops_device_ms": round(sum(device_ms(e) for e in events), 1),
        "top": [{"op": e.key, "calls": e.count, "host_ms": round(e.self_cpu_time_total / 1e3, 2), "device_ms": round(device_ms(e), 2)} for e in top],
    }


def train_group(
    agents: int, frames: int, backend: str = "torch", world: str = "lavaworld", arch: str | None = None, device: str = "cpu", profile: int = 0
) -> dict:
    """Seconds of one group's training, by part: what the group's batched calls
    (``train.group.serve_batch``: collection, update, lockstep evaluation, OPAC²'s act and learn)
    took, process CPU time and wall time (synchronised with the device after each call, so a
    GPU's queued work counts where it was asked for), and the rest (lone requests, folders, plots).
    ``profile``: also the top operations of one steady collection, update and the first evaluation
    (torch.profiler: how many launches, and whether the host or the device is the bound)."""
    import torch

    from rlbackdoors.config import RunConfig
    from rlbackdoors.train import group as train_group_module

    cpu: collections.Counter = collections.Counter()
    wall: collections.Counter = collections.Counter()
    calls: collections.Counter = collections.Counter()
    original = train_group_module.serve_batch
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)

    profiles: dict[str, dict] = {}

    @functools.wraps(original)
    def timed(requests, *args, **kwargs):
        part = type(requests[0]).__name__.lower()  # collect, update, evaluate, draw; OPAC²'s act, learn
        profiler = None
        if profile and calls[part] == (1 if part in ("collect", "update") else 0):  # a steady cycle; the first evaluation
            profiler = torch.profiler.profile(
                activities=[torch.profiler.ProfilerActivity.CPU] + ([torch.profiler.ProfilerActivity.CUDA] if device.startswith("cuda") else [])
            )
            profiler.__enter__()
        sync()
        start, start_wall = time.process_time(), time.perf_counter()
        try:
            return original(requests, *args, **kwargs)
        finally:
            sync()
            elapsed = time.perf_counter() - start_wall
            cpu[part] += time.process_time() - start
            wall[part] += elapsed
            calls[part] += 1
            if profiler is not None:
                profiler.__exit__(None, None, None)
                profiles[part] = top_ops(profiler, profile, elapsed)

    folder = tempfile.mkdtemp(prefix="group-breakdown-")
    runs = []
    for seed in range(agents):
        train = {"seed": seed, "max_frames": frames, "clean_threshold": 1.0, "poisoned_threshold": 1.0, "video": False, "torch_threads": 1, "device": device}
        data = {"env": {"name": world}, "train": train, "poison": {"poisoned": seed % 2 == 1}, "ppo": {"update_backend": backend}}
        if arch:
            data["model"] = {"arch": arch}
        cfg = RunConfig.from_dict(data)
        runs.append((seed, cfg, f"{folder}/m{seed}"))
    train_group_module.serve_batch = timed
    start, start_wall = time.process_time(), time.perf_counter()
    try:
        train_group_module.train_group(runs, agents)
    finally:
        train_group_module.serve_batch = original
        shutil.rmtree(folder, ignore_errors=True)  # the runs' folders: only their times are wanted
    total, total_wall = time.process_time() - start, time.perf_counter() - start_wall
    parts = {**cpu, "rest": total - sum(cpu.values())}
    walls = {**wall, "rest": total_wall - sum(wall.values())}
    from rlbackdoors.envs.batched_base import thread_choices

    return {
        "engine_threads": thread_choices(),  # how a GPU group's engines stepped (serial or over numba's threads), as timed here
        "cpu_s": round(total, 2),
        "wall_s": round(total_wall, 2),
        "frames_per_s": round(agents * frames / total_wall),
        "cpu_s_per_model": {k: round(v / agents, 3) for k, v in parts.items()},
        "wall_share": {k: round(v / total_wall, 3) for k, v in walls.items()},
        "calls": dict(calls),
        **({"profile": profiles} if profile else {}),
    }


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
    parser.add_argument("--world", default="lavaworld", help="a registered world (default lavaworld)")
    parser.add_argument("--arch", help="its model (default: the world's)")
    parser.add_argument("--device", default="cpu", help="train.device: cpu or cuda (default cpu)")
    parser.add_argument("--profile", type=int, default=0, metavar="ROWS", help="also the top ROWS operations of one collection, update and evaluation")
    parser.add_argument("--json", help="write the result here")
    args = parser.parse_args()
    import torch

    from rlbackdoors.config import RunConfig

    torch.set_num_threads(1)
    before = machine()
    if args.device.startswith("cuda"):
        before["gpu"] = torch.cuda.get_device_name(0)
    trained = train_group(args.agents, args.frames, args.update_backend, args.world, args.arch, args.device, args.profile)
    result = {
        "what": f"one {args.device} group of {args.world} runs: seconds per model by part",
        "world": args.world,
        "arch": args.arch,
        "device": args.device,
        "agents": args.agents,
        "update_backend": args.update_backend,
        "frames_per_model": args.frames,
        "machine": before,
        "loadavg_after": list(os.getloadavg()),
        **trained,
    }
    if args.device == "cpu" and args.world == "lavaworld" and args.arch in (None, "fc"):
        # the arithmetic floor of the CPU group (LavaWorld FC): PPO's forwards and backwards at the stacked rate
        ppo = RunConfig.from_dict({"env": {"name": "lavaworld"}}).ppo
        assert ppo is not None
        stacked, macs = stacked_rate(args.agents, ppo.batch_size)
        forwards = 1 + 3 * ppo.epochs  # rollout forward; per epoch a forward and a backward (two forwards' work)
        floor = forwards * 2 * macs * args.frames / (stacked * 1e9)
        result |= {
            "macs_per_row_forward": macs,
            "stacked_fwd_bwd_gflops": round(stacked, 1),
            "large_gemm_gflops": round(gemm_rate(), 1),
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
