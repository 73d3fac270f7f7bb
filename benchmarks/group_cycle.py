"""One training group's rollout-and-update cycle: host seconds and the device work it launches.

    python benchmarks/group_cycle.py --agents 64 --json out.json
    git worktree add /tmp/old OLD_COMMIT && python benchmarks/group_cycle.py --reference /tmp/old/src

``--agents`` LavaWorld FC learners (``--world``, ``--arch``), every other one poisoned through the
attack seam (``--poison``, default TrojDRL: forced actions, at ``--budget``; ``env-mix``: the engine's
own E-bar copies, no seam), run ``--cycles`` rollouts and updates of the group (``algos.group.collect`` and
``update``) after one that fills their Adam state, on the CPU, one torch thread, each measurement
in a fresh process. Reported: CPU seconds a cycle (collect, update; of them the hand-off: the
learners' weights and Adam state stacked for the group and written back), frames a second, and the
ATen operations a cycle runs that are not views (on a GPU each is a kernel launch or a host op,
whatever its size: what a GPU group pays per cycle before any arithmetic), with how many of them
one more agent adds (a second count at K + 1). With ``--reference`` another checkout is measured
alternately with this one in the same run (``same_numbers``: both trained the same weights). The
machine and its load are recorded.
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import json
import os
import time
from pathlib import Path

POISONS = {
    "trojdrl": {"trigger": "additive:135", "attack": "trojdrl"},  # at --budget
    "env-mix": {"poisoned": True},
}


def learners(world: str, arch: str, agents: int, poison: str, budget: float = 0.05) -> tuple[list, list, list]:
    import torch

    from rlbackdoors.algos.ppo import PPO
    from rlbackdoors.config import RunConfig
    from rlbackdoors.models import build_model
    from rlbackdoors.poison.mix import make_env_mix

    ppos, envs, obs = [], [], []
    poisoned = {**POISONS[poison], **({"attack_params": {"budget": budget}} if "attack" in POISONS[poison] else {})}
    for seed in range(agents):
        cfg = RunConfig.from_dict(
            {"env": {"name": world}, "model": {"arch": arch}, "train": {"seed": seed}, "poison": poisoned if seed % 2 else {"poisoned": False}}
        )
        torch.manual_seed(seed)
        ppos.append(PPO(build_model(cfg.model.arch, world), cfg.ppo, torch.device("cpu"), torch.Generator().manual_seed(seed)))
        envs.append(make_env_mix(cfg.env, cfg.poison, seed))
        obs.append(envs[-1].reset(seed=seed * 1000)[0])
    return ppos, envs, obs


def kernel_ops(world: str, arch: str, agents: int, poison: str, budget: float) -> int:
    """Non-view ATen operations of a group's second cycle (the first fills the Adam state)."""
    from torch.utils._python_dispatch import TorchDispatchMode

    from rlbackdoors.algos import group

    class Count(TorchDispatchMode):
        def __init__(self) -> None:
            super().__init__()
            self.ops: collections.Counter = collections.Counter()

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            if not func.is_view and str(func.overloadpacket) not in ("aten.lift_fresh", "aten.detach"):
                self.ops[str(func.overloadpacket)] += 1
            return func(*args, **(kwargs or {}))

    ppos, envs, obs = learners(world, arch, agents, poison, budget)
    for _ in range(2):
        with Count() as count:
            results = group.collect(ppos, envs, obs)
            group.update(ppos, [r for r, _ in results])
        obs = [o for _, o in results]
    return sum(count.ops.values())


def measure(world: str, arch: str, agents: int, poison: str, cycles: int, budget: float) -> dict:
    import torch

    from rlbackdoors.algos import group

    ppos, envs, obs = learners(world, arch, agents, poison, budget)
    handoff = [0.0]  # the learners' weights and Adam state into the group's stacks and back

    def timed(fn):
        def wrapper(*args, **kwargs):
            start = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                handoff[0] += time.process_time() - start

        return wrapper

    group.stacked_parameters = timed(group.stacked_parameters)
    group.StackedAdam.__init__ = timed(group.StackedAdam.__init__)  # type: ignore[method-assign]
    group.StackedAdam.write_back = timed(group.StackedAdam.write_back)  # type: ignore[method-assign]
    collect_s = update_s = 0.0
    frames = 0
    for cycle in range(cycles + 1):
        start = time.process_time()
        results = group.collect(ppos, envs, obs)
        middle = time.process_time()
        group.update(ppos, [r for r, _ in results])
        end = time.process_time()
        obs = [o for _, o in results]
        if cycle:  # the first fills the Adam state
            collect_s, update_s = collect_s + middle - start, update_s + end - middle
            frames += sum(r.num_frames for r, _ in results)
        else:
            handoff[0] = 0.0
    digest = hashlib.sha256(b"".join(p.detach().numpy().tobytes() for ppo in ppos for p in ppo.model.parameters())).hexdigest()[:16]
    ops, more = kernel_ops(world, arch, agents, poison, budget), kernel_ops(world, arch, agents + 1, poison, budget)
    import rlbackdoors

    return {
        "package": str(Path(rlbackdoors.__file__).parent),  # which checkout was measured
        "torch": torch.__version__,
        "collect_cpu_s_per_cycle": round(collect_s / cycles, 4),
        "update_cpu_s_per_cycle": round(update_s / cycles, 4),
        "handoff_cpu_s_per_cycle": round(handoff[0] / cycles, 4),
        "frames_per_cpu_s": round(frames / (collect_s + update_s)),
        "kernel_ops_per_cycle": ops,
        "kernel_ops_per_added_agent": more - ops,
        "digest": digest,  # the group's weights after the cycles: same numbers across versions
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="lavaworld")
    parser.add_argument("--arch", default="fc")
    parser.add_argument("--agents", type=int, default=64)
    parser.add_argument("--poison", default="trojdrl", choices=sorted(POISONS))
    parser.add_argument("--budget", type=float, default=0.05, help="TrojDRL's budget (its default is 0.01; 0.05 here, as the first results)")
    parser.add_argument("--cycles", type=int, default=3)
    parser.add_argument(
        "--conv", choices=("each", "gemm", "grouped"), help="a CNN group's convolutions on this CPU (models.minigrid.STACKED_CONV; default: the CPU's, each)"
    )
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--reference", help="another checkout's src/ (e.g. a git worktree of an older commit), measured alternately in the same run")
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)  # one measurement, as JSON on stdout
    parser.add_argument("--json")
    args = parser.parse_args(argv)
    what = [
        "--world",
        args.world,
        "--arch",
        args.arch,
        "--agents",
        str(args.agents),
        "--poison",
        args.poison,
        "--cycles",
        str(args.cycles),
        "--budget",
        str(args.budget),
    ]
    what += ["--conv", args.conv] if args.conv else []
    if args.one:
        import torch

        torch.set_num_threads(1)
        if args.conv:
            from rlbackdoors.models import minigrid

            minigrid.STACKED_CONV["cpu"] = args.conv
        print(json.dumps(measure(args.world, args.arch, args.agents, args.poison, args.cycles, args.budget)))
        return 0
    from _reference import alternate, finish

    load = os.getloadavg()
    runs = alternate(__file__, what, args.reference, args.repeats)
    cpu = {name: min(r["collect_cpu_s_per_cycle"] + r["update_cpu_s_per_cycle"] for r in rs) for name, rs in runs.items()}
    best = {name: min(rs, key=lambda r: r["collect_cpu_s_per_cycle"] + r["update_cpu_s_per_cycle"]) for name, rs in runs.items()}
    out = {
        "world": args.world,
        "arch": args.arch,
        "agents": args.agents,
        "poison": args.poison,
        "budget": args.budget if args.poison == "trojdrl" else None,
        "cycles": args.cycles,
        "conv": args.conv,
        "best": best,
        "runs": runs,
    }
    finish(out, runs, load, ("ratio_cpu", cpu["reference"] / cpu["this checkout"]) if args.reference else None, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
