"""Many agents in one process: K runs' loops stepped together, their learners' work batched.

Each run is the ordinary single-agent run (:func:`rlbackdoors.train.driver.train_steps`: its own
folder, lock, env mix, evaluations, checkpoints, stopping rule and finish), written as a loop
that yields what it needs from its learner (PPO: collect a rollout, update on it; OPAC²: act on
a step's observations, run the updates due). The group trainer answers those requests for all K
runs at once where they can be batched (:mod:`rlbackdoors.algos.group`: same architecture, PPO
config and env-copy count, with clean teachers for all or none; :mod:`rlbackdoors.algos.group_opac2`:
same OPAC² config) and one by one otherwise. A run that finishes
leaves the group and the next planned run takes its slot, so a group never waits on its slowest
member. Every run's folder is an ordinary model folder afterwards; a killed group resumes each
run from its own checkpoint, alone or in any group.

With an env pool (worlds of single envs), the runs of a batch go on to their next request each in
its own thread, and the requests served alone (an OPAC² run's evaluation) are served each in its
own thread too: their env steps then wait on the pool's workers together, so all K agents' copies
step at once rather than one agent's after another's (a run's numbers do not depend on it).
"""

from __future__ import annotations

import os
import sys
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from rlbackdoors.algos import group, group_opac2
from rlbackdoors.config import RunConfig
from rlbackdoors.train.driver import Draw, Evaluate, env_pool_for, eval_setup, evaluate_compiled, evaluate_runs, train_steps
from rlbackdoors.train.opac2_run import Act, Learn
from rlbackdoors.train.ppo_run import Collect, Iterate, Update
from rlbackdoors.train.stop import Interrupted, StopRequest

if TYPE_CHECKING:  # matplotlib, which rlbackdoors.report imports, only where a curve is drawn
    from rlbackdoors.report.painters import Painters


class RunCPU:
    """One run's share of the group process's CPU seconds: its own loop's time (evaluations,
    checkpoints) plus an equal share of each batch it was served in; its setup (env construction,
    the first reset) is not counted, as a lone run's is not (its RunClock starts after). What its
    metrics.json reports as ``cpu_time_s`` (the process's total would count K runs' work K times).
    ``threaded``: the run's loop goes on in a thread of its own, so its time is that thread's."""

    def __init__(self, threaded: bool = False) -> None:
        self.total = 0.0
        self.since: float | None = None
        self.clock = time.thread_time if threaded else time.process_time

    def __call__(self) -> float:
        return self.total + (self.clock() - self.since if self.since is not None else 0.0)

    def start(self) -> None:
        self.since = self.clock()

    def stop(self) -> None:
        if self.since is not None:
            self.total += self.clock() - self.since
            self.since = None


@dataclass
class _Slot:
    key: Any  # the caller's name for this run
    loop: Generator[Any, Any, Any] | None = None
    request: Any = None
    cpu: RunCPU = field(default_factory=RunCPU)
    painted_s: float = 0.0  # the painters' CPU seconds its pictures' replies carried


@dataclass
class GroupResult:
    """What became of each run: its metrics, or the exception that ended it; and ``cpu_s``, the
    CPU seconds it took of this process, its setup and finish (curve, GIF) included, with its
    pictures' painters' (their start-up and exit spread over the runs they drew for, in proportion),
    where its metrics' ``cpu_time_s`` counts its training only: what a zoo pays per model.
    ``overhead_s``: the CPU seconds of the call that no run's share carries (the group's loop and
    pools here; a painter's that drew for no run). The two add up, by construction, to the call's
    CPU: this process's and its painters' (env pool workers not counted: theirs is their own)."""

    metrics: dict[Any, dict] = field(default_factory=dict)
    errors: dict[Any, BaseException] = field(default_factory=dict)
    cpu_s: dict[Any, float] = field(default_factory=dict)
    overhead_s: float = 0.0


# ``--group-size auto``, per algorithm and device, measured (docs/results/zoos.md, `rlbackdoors bench zoo`):
# PPO on a CPU: models per hour (the feed-forward grid models) rise from K = 1 to 4 and are flat
# from 8 on. OPAC² on a CPU: a group of 2 was x0.92 (its update is arithmetic-bound, its env
# MuJoCo-bound), so its models train alone. On CUDA a group computes 64 agents at a time anyway
# (algos/group.py: group_width), so 64 costs no more than fewer; measured on an H200 (PPO), GPU
# groups were no faster than one process per CPU core and CPU groups of 8 on every core were x3.6:
# the message says so when auto picks CUDA.
AUTO_GROUP_SIZE = {("ppo", "cpu"): 8, ("opac2", "cpu"): 1, ("ppo", "cuda"): 64, ("opac2", "cuda"): 64}


def auto_group_size(algorithm: str, device: str, world: Any = None, backend: str | None = None) -> int:
    """``--group-size auto``: the measured K for a model of ``algorithm`` that trains on ``device``
    (its ``train.device``; ``auto``: CUDA where present). By the model's device, not the machine's:
    on a GPU machine a CPU model trains fastest in CPU groups (docs/results/zoos.md: GPU groups of 64 ran
    at x0.35 of CPU groups of 8 on an H200 machine's 16 cores). On the compiled trainer
    (``backend``) on a CPU, the ``world``'s own measured K where it has one
    (``World.compiled_cpu_group``)."""
    where = "cuda" if device == "cuda" or (device == "auto" and torch.cuda.is_available()) else "cpu"
    own = getattr(world, "compiled_cpu_group", None) if backend == "compiled" and where == "cpu" else None
    return own if own is not None else AUTO_GROUP_SIZE[(algorithm, where)]


def painter_count(runs: Sequence[tuple[Any, RunConfig, Any]], group_size: int, device: str | None = None) -> int:
    """Painter processes for the group's training curves and GIFs (:mod:`rlbackdoors.report.painters`):
    the host's other cores where the learners compute on a GPU, which would otherwise wait on
    matplotlib as runs finish together; none on a CPU, where they would only take a core from
    training (the group waits on the same work either way)."""
    if group_size < 2 or not torch.cuda.is_available() or not any((device or cfg.train.device) in ("cuda", "auto") for _, cfg, _ in runs):
        return 0  # (a run asking for a GPU on a machine without one fails alone, with its own message)
    return min(group_size, max(0, (os.cpu_count() or 1) - 1))


def batch_key(request, painters: bool = False) -> tuple | None:
    """Requests with the same key are answered by one batched call; None: answered alone
    (``painters``: the group draws its pictures in painter processes)."""
    if isinstance(request, Draw):
        return ("Draw",) if painters else None
    if isinstance(request, Evaluate) and request.learner is not None:  # in the compiled learners' program
        learner, cfg = request.learner, request.cfg
        conditions = tuple((name, target is not None) for name, _, _, target in eval_setup(cfg, request.episodes).conditions())
        return ("EvaluateCompiled", learner.world, learner.net, learner.hyper, request.episodes, cfg.train.eval_policy, conditions)
    if isinstance(request, Evaluate):
        policy, cfg = request.policy, request.cfg
        if not isinstance(policy, torch.nn.Module) or not group.stackable(policy) or cfg.world.vector_entry_point is None:
            return None  # OPAC²'s agents and single-env worlds are evaluated alone
        shapes = tuple((name, tuple(p.shape)) for name, p in policy.named_parameters())
        return ("Evaluate", type(policy).__name__, shapes, repr(cfg.env), request.episodes, cfg.train.eval_policy, str(next(policy.parameters()).device))
    if isinstance(request, (Act, Learn)):
        agent = request.agent
        width = len(request.obs) if isinstance(request, Act) else request.n
        return (type(request).__name__, "OPAC2", repr(agent.cfg), str(agent.device), agent.policy_obs_dim, width)
    if isinstance(request, Iterate):  # compiled learners of one program
        return ("Iterate", *request.learner.program)
    ppo = request.ppo
    if not group.stackable(ppo.model):
        return None
    width = request.envs.num_envs if isinstance(request, Collect) else request.rollout.num_frames
    return (type(request).__name__, type(ppo.model).__name__, repr(ppo.cfg), str(ppo.device), width, ppo.teacher is not None, ppo.anchor is not None)


def serve_batch(requests: list, stacked: bool = True, painters: Painters | None = None, capacity: int = 1) -> list:
    """Results for requests of one :func:`batch_key`, through the stacked learner even for one
    request (an agent's numbers do not depend on its group-mates or on K, tested, so a run
    resumed in another group gives the same bytes); ``stacked=False`` serves one request as a
    lone run (:func:`train_group` with group size 1: today's bytes); curves go to ``painters``.
    Compiled iterations run in a program of ``capacity`` agents (the group size) however many
    ask: a run's bytes depend on its config and the capacity, not on its group-mates."""
    if isinstance(requests[0], Iterate):
        from rlbackdoors.algos import compiled

        return compiled.iterate([r.learner for r in requests], capacity)
    if len(requests) == 1 and not stacked:
        return [requests[0].serve()]
    if isinstance(requests[0], Draw):
        assert painters is not None
        return painters.render([r.job() for r in requests], [r.here for r in requests])
    if isinstance(requests[0], Evaluate) and requests[0].learner is not None:
        return evaluate_compiled([r.learner for r in requests], [r.cfg for r in requests], [r.episodes for r in requests], capacity)
    if isinstance(requests[0], Evaluate):
        return evaluate_runs([r.policy for r in requests], [r.cfg for r in requests], [r.episodes for r in requests], group.stacked_act)
    if isinstance(requests[0], Act):
        return group_opac2.act([r.agent for r in requests], [r.obs for r in requests])
    if isinstance(requests[0], Learn):
        return group_opac2.update([r.agent for r in requests], [r.replay for r in requests], [r.rng for r in requests], requests[0].n)
    ppos = [r.ppo for r in requests]
    if isinstance(requests[0], Collect):
        return group.collect(ppos, [r.envs for r in requests], [r.obs for r in requests])
    assert isinstance(requests[0], Update)
    return group.update(ppos, [r.rollout for r in requests])


def train_group(
    runs: Sequence[tuple[Any, RunConfig, str | Path]],
    group_size: int,
    progress: bool = False,
    on_done: Callable[[Any, dict | None, BaseException | None], None] | None = None,
    env_workers: int = 0,
    painters: int | None = None,
    device: str | None = None,
) -> GroupResult:
    """Train ``runs`` ((key, config, folder) each) at most ``group_size`` at a time in this process.

    With ``group_size`` above 1 every batchable run trains through the stacked learner and its
    metrics.json says ``"trainer": "group"``: its bytes then depend on its config alone, not
    on which runs shared its group (group size 1 is today's lone path, today's bytes).
    A run that fails (an exception) is recorded and the others go on; Ctrl-C or SIGTERM makes
    every running run write its checkpoint and stop, then raises :class:`Interrupted`.
    ``on_done(key, metrics, error)`` is called as each run ends. ``env_workers``: the env copies
    of runs in worlds of single envs live in one pool of that many worker processes (same bytes). ``painters``:
    processes that draw the training curves and GIFs of runs finishing together (default
    :func:`painter_count`: the other cores on a GPU, none on a CPU). ``device``: where every
    run's math runs instead of its ``train.device`` (recorded in its metrics.json).
    """
    if group_size < 1:
        raise ValueError(f"group_size must be >= 1, got {group_size}")
    called = time.process_time()
    waiting = deque(runs)
    slots: list[_Slot] = []
    result = GroupResult()
    painted: dict[Any, float] = {}  # each ended run's painters' seconds, within its cpu_s
    interrupted: list[Interrupted] = []

    def step(slot: _Slot, value: Any = None, error: BaseException | None = None) -> BaseException | None:
        """Send the slot's loop its answer (in any thread); None while the run goes on, else how it ended."""
        assert slot.loop is not None
        slot.cpu.start()
        try:
            slot.request = slot.loop.throw(error) if error is not None else slot.loop.send(value)
            return None
        except BaseException as end:  # StopIteration (finished), Interrupted, a failure: settled in the main thread
            return end
        finally:
            slot.cpu.stop()

    def serve_alone(slot: _Slot) -> tuple[Any, BaseException | None]:
        """A request that is not batched, served as a lone run's learner would (in any thread)."""
        slot.cpu.start()
        try:
            return slot.request.serve(), None
        except BaseException as err:  # raised into the run's loop at its yield
            return None, err
        finally:
            slot.cpu.stop()

    def settle(slot: _Slot, end: BaseException | None) -> bool:
        """Record how a run ended (in the main thread); False once it has ended."""
        if end is None:
            return True
        result.cpu_s[slot.key] = slot.cpu()
        painted[slot.key] = slot.painted_s
        if isinstance(end, StopIteration):
            result.metrics[slot.key] = end.value
            if on_done is not None:
                on_done(slot.key, end.value, None)
        elif isinstance(end, Interrupted):
            interrupted.append(end)
            result.errors[slot.key] = end
        elif isinstance(end, Exception):  # this run failed; the group goes on
            result.errors[slot.key] = end
            if on_done is not None:
                on_done(slot.key, None, end)
        else:
            raise end
        return False

    from rlbackdoors.report.painters import Painters

    drawing = Painters(painter_count(runs, group_size, device) if painters is None else painters)
    with env_pool_for([cfg for _, cfg, _ in runs], env_workers) as pool, StopRequest() as stop, ThreadPoolExecutor(group_size) as threads, drawing:
        threaded = pool is not None and group_size > 1
        while True:
            while waiting and len(slots) < group_size and not stop.requested:
                key, cfg, folder = waiting.popleft()
                slot = _Slot(key, cpu=RunCPU(threaded))
                slot.loop = train_steps(
                    cfg, folder, stop, progress=progress, trainer="group" if group_size > 1 else None, cpu_source=slot.cpu, env_pool=pool, device=device
                )
                if settle(slot, step(slot)):
                    slots.append(slot)
            if not slots:
                break
            batches: dict[Any, list[_Slot]] = {}
            for i, slot in enumerate(slots):  # a request that cannot be batched is a batch of its own
                batches.setdefault(batch_key(slot.request, drawing.workers >= 2) or ("alone", i), []).append(slot)
            ended: set[int] = set()
            if threaded:  # requests served alone (an evaluation of single envs): each in its own thread, together
                lone = [members[0] for key, members in batches.items() if key[0] == "alone"]
                served = list(threads.map(serve_alone, lone))
                ends = list(threads.map(step, lone, [answer for answer, _ in served], [error for _, error in served]))
                ended.update(id(s) for s, end in zip(lone, ends) if not settle(s, end))
                batches = {key: members for key, members in batches.items() if key[0] != "alone"}
            for key, members in batches.items():
                started = time.process_time()
                error: BaseException | None = None
                try:
                    answers = serve_batch([s.request for s in members], stacked=group_size > 1 and key[0] != "alone", painters=drawing, capacity=group_size)
                except BaseException as err:  # raised into every member's loop at its yield
                    answers, error = [None] * len(members), err
                share = (time.process_time() - started) / len(members)
                for s, answer in zip(members, answers):
                    s.cpu.total += share + getattr(answer, "cpu_s", 0.0)  # a painter's CPU seconds for its curve
                    s.painted_s += getattr(answer, "cpu_s", 0.0)
                if threaded and len(members) > 1:
                    ends = list(threads.map(step, members, answers, [error] * len(members)))
                else:
                    ends = [step(s, a, error) for s, a in zip(members, answers)]
                alive = [settle(s, end) for s, end in zip(members, ends)]
                ended.update(id(s) for s, ok in zip(members, alive) if not ok)
            slots = [s for s in slots if id(s) not in ended]
    # the painters' CPU that no reply carried (their exit, one killed mid-picture), read as they
    # were reaped, to the runs they drew for; this process's CPU that no share carries, overhead
    unreported, drawn = drawing.unreported_s, sum(painted.values())
    for key, seconds in painted.items():
        result.cpu_s[key] += unreported * seconds / drawn if drawn > 0 else 0.0
    result.overhead_s = time.process_time() - called + drawn + unreported - sum(result.cpu_s.values())
    if interrupted:
        if progress:
            print(f"group: {len(interrupted)} runs stopped with their checkpoints; run again to resume", file=sys.stderr, flush=True)
        raise interrupted[0]
    return result
