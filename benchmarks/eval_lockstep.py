"""Where a group's lockstep evaluation spends its time: the batched forward (``act``), the engine
call, and the bookkeeping around them (per-episode tallies, observations, the live set), which is
host Python that a GPU group waits on while the device idles (issue 55: "evaluations count").

    python benchmarks/eval_lockstep.py --agents 256 --episodes 100 --json out.json
    git worktree add /tmp/old OLD_COMMIT && python benchmarks/eval_lockstep.py --reference /tmp/old/src

``--agents`` untrained models of a grid world's default poisoned config (seeds 0..K-1, half clean)
are evaluated as a training group does (``evaluate_runs`` with ``stacked_act``: one forward a
step for the live agents), on the CPU, one torch thread, each measurement in a fresh process; the
figures are the best of ``--repeats``, and with ``--reference`` another checkout is measured
alternately with this one, in the same run (``same_numbers``: every measurement scored the same). The bookkeeping share is what the GPU would not hide; the forward's arithmetic
it would. The machine and its load are recorded.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import time
from pathlib import Path


class Clock:
    """Seconds spent inside the wrapped callables (not re-entrant: nothing here nests them)."""

    def __init__(self):
        self.seconds, self.calls = 0.0, 0

    def wrap(self, fn):
        def timed(*args, **kwargs):
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - start
                self.calls += 1

        return timed


def measure(world: str, agents: int, episodes: int) -> dict:
    import torch

    from rlbackdoors.algos import group
    from rlbackdoors.config import RunConfig
    from rlbackdoors.envs.batched_base import BatchedGridEnv, EngineGroup
    from rlbackdoors.models import build_model
    from rlbackdoors.train.driver import evaluate_runs

    cfgs = [RunConfig.from_dict({"env": {"name": world}, "poison": {"poisoned": k % 2 == 1}, "train": {"seed": k}}) for k in range(agents)]
    models = []
    for cfg in cfgs:
        torch.manual_seed(cfg.train.seed)
        models.append(build_model(cfg.model.arch, world))
    acting, engines = Clock(), Clock()

    def stacked(members: list):
        return acting.wrap(group.stacked_act(members))

    saved = EngineGroup.step, BatchedGridEnv.step
    EngineGroup.step, BatchedGridEnv.step = engines.wrap(EngineGroup.step), engines.wrap(BatchedGridEnv.step)
    try:
        start = time.perf_counter()
        results = evaluate_runs(models, cfgs, [episodes] * agents, stacked)
        wall = time.perf_counter() - start
    finally:
        EngineGroup.step, BatchedGridEnv.step = saved
    import rlbackdoors

    steps = sum(r.clean_mean_steps + r.poisoned_mean_steps for r in results) * episodes  # agent-episode steps played
    return {
        "package": str(Path(rlbackdoors.__file__).parent),  # which checkout was measured
        "wall_s": round(wall, 3),
        "act_s": round(acting.seconds, 3),
        "engine_s": round(engines.seconds, 3),
        "bookkeeping_s": round(wall - acting.seconds - engines.seconds, 3),
        "episode_steps": int(steps),
        "lockstep_steps": acting.calls,
        "bookkeeping_ms_per_step": round(1e3 * (wall - acting.seconds - engines.seconds) / max(acting.calls, 1), 3),
        "digest": hashlib.sha256(json.dumps([r.to_dict() for r in results], sort_keys=True).encode()).hexdigest()[:16],  # same numbers across versions
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="lavaworld")
    parser.add_argument("--agents", type=int, default=256)
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--reference", help="another checkout's src/ (e.g. a git worktree of an older commit), measured alternately in the same run")
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)  # one measurement, as JSON on stdout
    parser.add_argument("--json")
    args = parser.parse_args(argv)

    if args.one:
        import torch

        torch.set_num_threads(1)
        print(json.dumps(measure(args.world, args.agents, args.episodes)))
        return 0
    from _reference import alternate, finish

    load = os.getloadavg()
    runs = alternate(__file__, ["--world", args.world, "--agents", str(args.agents), "--episodes", str(args.episodes)], args.reference, args.repeats)
    best = {name: min(rs, key=lambda r: r["wall_s"]) for name, rs in runs.items()}
    out = {"world": args.world, "agents": args.agents, "episodes": args.episodes, "best": best, "runs": runs}
    finish(out, runs, load, ("ratio_wall", best["reference"]["wall_s"] / best["this checkout"]["wall_s"]) if args.reference else None, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
