"""Env steps per second of a group's engines: a call per agent, one call for the group
(``EngineGroup``), and one call over numba's threads (``parallel``: the engine half of issue 55
on a GPU machine, where the learners compute on the device and the cores are free).

    python benchmarks/engine_threads.py --agents 64 --steps 300 --json benchmarks/results/engine_threads_epyc.json

For each grid world: ``--agents`` env mixes of the world's default poisoned config (half clean:
``poison.poisoned = false``), their engines reset, then ``--steps`` steps of random actions per
side, the same actions on every side; slot-steps per second (slots = agents x copies), best of
``--repeats``. The parallel side runs at each thread count of ``--threads`` (numba.set_num_threads).
The machine and its load are recorded; the sides give the same bytes (tests/test_engine_group.py).

``--device DEV`` (LavaWorld) adds issue 55's other engine, the slots stepped by torch ops on DEV
(``envs.lavaworld_device``), on the same work: fresh engines of the same seeds handed to it, the
same actions (on DEV beforehand, where a policy would leave them), eager and under
``torch.compile`` (``--compile``, inductor's default mode), and on CUDA as one CUDA graph a step.
Beside it, the numba
side as a GPU learner would use it: each step the actions copied to the host, the engines' call
(serial or over numba's threads, as ``batched_base.ThreadChoice`` timed it here), the observations
copied to DEV. ``same_bytes`` checks the device engine's observations, rewards,
ends, outcomes and step counts at every one of 64 steps (eager, and on CUDA also as a graph)
against numba's one call from the same fresh engines.

    python benchmarks/engine_threads.py --worlds lavaworld --agents 256 --device cuda --compile --json OUT.json
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numba
import numpy as np


def engines_of(world: str, agents: int) -> list:
    from rlbackdoors.config import RunConfig
    from rlbackdoors.poison.mix import make_env_mix

    out = []
    for k in range(agents):
        cfg = RunConfig.from_dict({"env": {"name": world}, "poison": {"poisoned": k % 2 == 1}, "train": {"seed": k}})
        envs = make_env_mix(cfg.env, cfg.poison, k)
        envs = getattr(envs, "envs", envs)  # a seam's engine (the default attack has none)
        envs.reset(seed=1000 * k)
        out.append(envs)
    return out


def run(engines: list, steps: int, side: str, seed: int, threads: int = 0) -> float:
    from rlbackdoors.envs.batched_base import EngineGroup

    acts = slot_actions(engines, steps, seed)
    own = np.split(acts, np.cumsum([e.num_envs for e in engines])[:-1], axis=1)  # each engine's columns
    group = None if side == "per agent" else EngineGroup.of(engines, parallel=threads if side == "parallel" else False)
    if side != "per agent" and group is None:
        raise SystemExit(f"{type(engines[0]).__name__}: these engines cannot share a call")
    started = time.perf_counter()
    for t in range(steps):
        if group is None:
            for e, a in zip(engines, own):
                e.step(a[t])
        else:
            group.step(acts[t])
    return sum(e.num_envs for e in engines) * steps / (time.perf_counter() - started)


def slot_actions(engines: list, steps: int, seed: int) -> np.ndarray:
    """(steps, slots): ``run``'s random actions for ``seed``, every engine's slots side by side."""
    rng = np.random.default_rng(seed)
    return np.concatenate([rng.integers(0, 3, (steps, e.num_envs)) for e in engines], axis=1)


def synchronizer(device: str):
    """What waits for ``device``'s queued work before a clock is read."""
    import torch

    return torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)


def run_device(engines: list, steps: int, seed: int, device: str, compiled: bool, warm: int = 0, graph: bool = False) -> tuple[float, object]:
    """Slot-steps/s of the world's device engine over ``engines``' slots (handed over), and its last step."""
    import torch

    from rlbackdoors.envs.batched_base import EngineGroup
    from rlbackdoors.envs.grid_device import device_engine_for

    acts = torch.from_numpy(slot_actions(engines, steps, seed)).to(device)
    dev = device_engine_for(EngineGroup.of(engines) if len(engines) > 1 else engines[0], device, graph=graph)
    assert dev is not None
    if compiled:
        dev._advance = torch.compile(dev._advance, dynamic=False)  # type: ignore[method-assign]  # inductor's fused kernels
    for t in range(warm):  # compiles (and for CUDA graphs, records) before the clock
        dev.step(acts[t])
    sync = synchronizer(device)
    sync()
    started = time.perf_counter()
    for t in range(warm, steps):
        last = dev.step(acts[t])
    sync()
    return dev.num_envs * (steps - warm) / (time.perf_counter() - started), last


def run_host_for_device(engines: list, steps: int, seed: int, device: str) -> float:
    """The numba engines over the host's threads feeding learners on ``device``: actions to the host,
    one parallel call, observations to the device, each step."""
    import torch

    from rlbackdoors.envs.batched_base import EngineGroup

    acts = torch.from_numpy(slot_actions(engines, steps, seed)).to(device)
    group = EngineGroup.of(engines, parallel=True)
    assert group is not None
    sync = synchronizer(device)
    sync()
    started = time.perf_counter()
    for t in range(steps):
        obs = group.step(acts[t].cpu().numpy())[0]
        torch.from_numpy(obs).to(device, non_blocking=False)
    sync()
    return group.total * steps / (time.perf_counter() - started)


def differs(world: str, agents: int, steps: int, device: str, graph: bool) -> str | None:
    """Where the device engine first differs from numba's one call on the same fresh engines and
    actions (observations, rewards, ends, outcomes, step counts, compared at every step), or None."""
    import torch

    from rlbackdoors.envs.batched_base import EngineGroup
    from rlbackdoors.envs.grid_device import device_engine_for

    reference = EngineGroup.of(engines_of(world, agents))
    theirs = engines_of(world, agents)
    dev = device_engine_for(EngineGroup.of(theirs), device, graph=graph)
    assert reference is not None and dev is not None
    for t, acts in enumerate(slot_actions(reference.engines, steps, 0)):
        obs, reward, terminated, truncated, info = reference.step(acts)
        got = dev.step(torch.from_numpy(acts).to(device))
        for name, want, have in zip(
            ("obs", "reward", "terminated", "truncated", "outcome", "steps"), (obs, reward, terminated, truncated, info["outcome"], info["steps"]), got
        ):
            if not np.array_equal(np.asarray(want), have.cpu().numpy()):
                where = f"{world} on {device}{' (graph)' if graph else ''}: step {t}: {name} differs"
                print(where, flush=True)
                return where
    return None


def device_row(world: str, args) -> dict:
    """The device sides of ``world`` (module doc), each on fresh engines of the same seeds."""
    import torch

    row: dict = {"device": args.device, "torch": torch.__version__}
    if args.device.startswith("cuda"):
        row["gpu"] = torch.cuda.get_device_name(0)
    # the check: numba's one call and the device engine, same fresh engines and actions, every step
    graphs = (False, True) if args.device.startswith("cuda") else (False,)
    row["same_bytes"] = all(differs(world, args.agents, 64, args.device, graph) is None for graph in graphs)
    print(f"{world}: device engine on {args.device}: same bytes as numba: {row['same_bytes']}", flush=True)
    best = max(run_device(engines_of(world, args.agents), args.steps + 5, r, args.device, False, 5)[0] for r in range(args.repeats))
    row["device engine"] = round(best)
    print(f"{world}: device engine ({args.device}): {best:,.0f} slot-steps/s", flush=True)
    numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    engines = engines_of(world, args.agents)
    run_host_for_device(engines, 30, 0, args.device)  # (a GPU group's engines time their ways first: batched_base.ThreadChoice)
    best = max(run_host_for_device(engines, args.steps, r, args.device) for r in range(args.repeats))
    from rlbackdoors.envs.batched_base import thread_choices

    row["thread choice"] = thread_choices().get(f"{type(engines[0]).__name__}/{sum(e.num_envs for e in engines)}")
    name = f"numba as a GPU group steps it, with copies to {args.device}"
    row[name] = round(best)
    print(f"{world}: {name}: {best:,.0f} slot-steps/s (threads: {row['thread choice']})", flush=True)
    if args.device.startswith("cuda"):  # the step as one CUDA graph (captured at its first step, before the clock)
        try:
            best = max(run_device(engines_of(world, args.agents), args.steps + 5, r, args.device, False, 5, graph=True)[0] for r in range(args.repeats))
            row["device engine, CUDA graph"] = round(best)
            print(f"{world}: device engine, CUDA graph ({args.device}): {best:,.0f} slot-steps/s", flush=True)
        except Exception as e:  # a measurement to report, not a reason to lose the others
            row["device engine, CUDA graph"] = f"failed: {type(e).__name__}: {e}"
            print(f"{world}: device engine, CUDA graph: failed: {type(e).__name__}: {e}", flush=True)
    if args.compile:  # last: its compilation takes the longest (seconds to a minute)
        best, _ = run_device(engines_of(world, args.agents), args.steps + 20, 0, args.device, True, 20)
        row["device engine, compiled"] = round(best)
        print(f"{world}: device engine, compiled ({args.device}): {best:,.0f} slot-steps/s", flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--worlds", nargs="+", default=["lavaworld", "randomized-lavaworld", "colorful-memory"])
    parser.add_argument("--agents", type=int, default=64)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, nargs="+", default=sorted({1, numba.config.NUMBA_NUM_THREADS}))
    parser.add_argument("--device", help="also the device engine on this torch device (LavaWorld), e.g. cpu, cuda")
    parser.add_argument("--compile", action="store_true", help="with --device: also its step under torch.compile")
    parser.add_argument("--json")
    args = parser.parse_args()
    if args.device and set(args.worlds) != {"lavaworld"}:
        parser.error("--device: only LavaWorld has a device engine (envs/lavaworld_device.py); pass --worlds lavaworld")
    from rlbackdoors.bench.machine import machine_info
    from rlbackdoors.io import atomic_write_text

    results = {}
    for world in args.worlds:
        engines = engines_of(world, args.agents)
        for side in ("per agent", "one call", "parallel"):  # the first calls compile the kernels
            run(engines, 5, side, 0, max(args.threads))
        row = {"slots": sum(e.num_envs for e in engines), "steps": args.steps}
        for side, threads in [("per agent", None), ("one call", None), *(("parallel", n) for n in args.threads)]:
            best = max(run(engines, args.steps, side, r, threads or 0) for r in range(args.repeats))
            name = side if threads is None else f"parallel, {threads} threads"
            row[name] = round(best)
            print(f"{world}: {name}: {best:,.0f} slot-steps/s", flush=True)
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        if args.device:
            row.update(device_row(world, args))
        results[world] = row
    out = {"agents": args.agents, "results": results, "machine": machine_info(), "loadavg": [round(x, 2) for x in os.getloadavg()]}
    if args.json:
        atomic_write_text(args.json, json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
