"""Running a zoo: train every planned model that is not finished, top cells up until they have
the converged models they want, and record what failed. Nothing is lost across kills.

The coordinator (one per zoo: it holds ``ZOO/.lock``) keeps no state that the folders do not:
on every start it reads the model folders, so ``rlbackdoors zoo run ZOO`` after a crash, a
``kill -9`` or a reboot simply continues.

* A complete model (metrics.json and reduced-config.json) is skipped; a started one resumes
  from its checkpoint (training does that); a folder whose lock a live process holds is
  "running elsewhere" and is waited for, never touched.
* A job that fails is retried up to ``max_retries`` times in this run, then recorded in
  ``failed.json`` (atomically) and left alone by later runs unless ``retry_failed``.
* Top-up: a group (a cell's clean or poisoned models) keeps ``wanted - converged`` models
  planned and unfinished, and plans attempt ``k`` (drawn from the master seed, never changing
  attempts before it) when one finishes without converging, up to ``max_attempts``. Which
  models a group ends with depends only on the models' outcomes, not on timing.

Back-ends: ``local`` runs each job as a child process (:func:`rlbackdoors.zoo.job.main` forked
from a server that has imported torch once, :mod:`rlbackdoors.zoo.forkserver`; one torch thread,
output in the model's ``train.log``); ``ray`` runs the same job function as Ray
tasks (:mod:`rlbackdoors.zoo.ray_backend`).
"""

from __future__ import annotations

import json
import os
import select
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Protocol, TextIO

from rlbackdoors import worlds
from rlbackdoors.config import DEVICES  # zoo run --device: where the models' math runs instead of their train.device
from rlbackdoors.io import LOCK_NAME, FolderLock, LockedError, atomic_write_text, open_beneath, refuse_links, remove_tree
from rlbackdoors.validate import ConfigError
from rlbackdoors.zoo.index import ModelState, group_counts, model_state, scan, status_table, write_metadata
from rlbackdoors.zoo.forkserver import JobProcess
from rlbackdoors.zoo.job import EXIT_BUSY, EXIT_INTERRUPTED, FAILED, LOG, is_locked
from rlbackdoors.zoo.plan import PlannedModel, Zoo, read_zoo_json

BACKENDS = ("local", "ray")
BUSY_PROBE_S = 2.0  # how often a folder running elsewhere is looked at again


def default_workers() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


class Executor(Protocol):
    """What the coordinator needs from a back-end."""

    capacity: int

    def submit(self, model: PlannedModel, folder: Path) -> None: ...

    def wait(self, timeout: float) -> list[tuple[PlannedModel, dict]]: ...

    def running(self) -> int: ...

    def stop(self) -> None: ...


@dataclass
class _Child:
    models: list[PlannedModel]
    proc: JobProcess
    result_fd: int
    log: IO[bytes]
    chunks: list[bytes] = field(default_factory=list)


class LocalExecutor:
    """Each job in its own child process, at most ``workers`` at a time.

    Children die with the coordinator: each asks for SIGTERM on its parent's death
    (:func:`rlbackdoors.zoo.job._die_with_parent`), which makes training checkpoint and stop.
    """

    def __init__(self, workers: int, group_size: int = 1, env_workers: int = 0, device: str | None = None):
        self.capacity = workers
        self.group_size = group_size
        self.env_workers = env_workers
        self.device = device
        self.children: dict[int, _Child] = {}

    def submit(self, model: PlannedModel, folder: Path) -> None:
        self.submit_group([model], [folder])

    def submit_group(self, models: list[PlannedModel], folders: list[Path], group_size: int | None = None) -> None:
        """One child for ``models``: alone (group size 1), or a group job training them
        ``group_size`` (default: the executor's) at a time (its output goes to the first model's train.log)."""
        group_size = self.group_size if group_size is None else group_size
        folder = folders[0]
        folder_fd = open_beneath(folder.parent.parent, folder)  # LinkError if a link was swapped in
        try:
            log = os.fdopen(os.open(LOG, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o666, dir_fd=folder_fd), "ab", buffering=0)
        finally:
            os.close(folder_fd)
        read_fd, write_fd = os.pipe()
        argv = (
            [*map(str, folders)]
            + (["--group-size", str(group_size)] if group_size > 1 else [])
            + (["--env-workers", str(self.env_workers)] if self.env_workers else [])
            + (["--device", self.device] if self.device is not None else [])
        )
        try:
            proc = JobProcess(argv, log.fileno(), write_fd, dict(os.environ))
        except BaseException:
            os.close(read_fd)
            log.close()
            raise
        finally:
            os.close(write_fd)
        os.set_blocking(read_fd, False)
        self.children[proc.pid] = _Child(list(models), proc, read_fd, log)

    def _drain(self, child: _Child) -> None:
        while True:
            try:
                data = os.read(child.result_fd, 65536)
            except BlockingIOError:
                return
            if not data:
                return
            child.chunks.append(data)

    def wait(self, timeout: float) -> list[tuple[PlannedModel, dict]]:
        deadline = time.monotonic() + timeout
        while True:
            done: list[tuple[PlannedModel, dict]] = []
            for pid, child in list(self.children.items()):
                self._drain(child)
                code = child.proc.poll()
                if code is None:
                    continue
                self._drain(child)
                os.close(child.result_fd)
                child.log.close()
                del self.children[pid]
                result = _child_result(code, b"".join(child.chunks))
                if result.get("status") == "group":
                    results = result.get("results") or {}
                    lost = {"status": "error", "error": "the group job gave no result for this model"}
                    done.extend((m, results.get(m.name, lost)) for m in child.models)
                else:
                    done.extend((m, result) for m in child.models)
            if done or time.monotonic() >= deadline:
                return done
            fds = [c.result_fd for c in self.children.values()]
            if fds:
                select.select(fds, [], [], min(0.2, max(0.0, deadline - time.monotonic())))
            else:
                time.sleep(min(0.2, max(0.0, deadline - time.monotonic())))

    def running(self) -> int:
        return len(self.children)

    def stop(self) -> None:
        """Ask every child to checkpoint and stop (SIGTERM), and wait for them."""
        for child in self.children.values():
            if child.proc.poll() is None:
                child.proc.send_signal(signal.SIGTERM)
        for child in self.children.values():
            try:
                child.proc.wait(timeout=600)
            except subprocess.TimeoutExpired:
                child.proc.kill()
                child.proc.wait()
            os.close(child.result_fd)
            child.log.close()
        self.children.clear()


def _child_result(code: int, data: bytes) -> dict:
    try:
        result = json.loads(data.decode("utf-8")) if data else None
    except ValueError:
        result = None
    if isinstance(result, dict) and "status" in result:
        return result
    if code == EXIT_BUSY:
        return {"status": "busy"}
    if code == EXIT_INTERRUPTED:
        return {"status": "interrupted"}
    if code < 0:
        return {"status": "error", "error": f"the job process was killed by {signal.Signals(-code).name}"}
    return {"status": "error", "error": f"the job process exited with code {code} (see train.log)"}


def make_executor(
    backend: str, workers: int | None, address: str | None, max_retries: int, group_size: int = 1, env_workers: int = 0, device: str | None = None
) -> Executor:
    if backend == "local":
        if address is not None:
            raise ConfigError("--address applies to --backend ray only")
        return LocalExecutor(workers or default_workers(), group_size, env_workers, device)
    if device is not None:
        raise ConfigError("--device applies to --backend local only (a Ray task's resources are Ray's to schedule: set train.device in the spec)")
    if group_size > 1:
        raise ConfigError("--group-size applies to --backend local only (a Ray task trains one model)")
    if env_workers:
        raise ConfigError("--env-workers applies to --backend local only (a Ray task's CPUs are Ray's to schedule)")
    if backend == "ray":
        from rlbackdoors.zoo.ray_backend import RayExecutor

        return RayExecutor(workers, address, max_retries)
    raise ConfigError(f"--backend={backend!r} is not allowed (allowed: {', '.join(BACKENDS)})")


@dataclass
class Progress:
    """Models done / running / failed / left, models per hour and an ETA, on one line."""

    out: TextIO
    interval: float
    started: float = field(default_factory=time.monotonic)
    trained: int = 0  # models finished by this run (skipped ones not counted)
    last: float = 0.0

    def line(self, states: list[ModelState], running: int) -> str:
        done = sum(s.status == "done" for s in states)
        converged = sum(s.converged for s in states)
        failed = sum(s.status == "failed" for s in states)
        left = sum(s.status in ("pending", "running") for s in states) - running
        hours = (time.monotonic() - self.started) / 3600
        rate = self.trained / hours if hours > 0 and self.trained else 0.0
        eta = _duration((left + running) / rate * 3600) if rate else "?"
        return f"zoo: {done} done ({converged} converged), {running} running, {failed} failed, {max(left, 0)} left; {rate:.1f} models/h, ETA {eta}"

    def maybe(self, states: list[ModelState], running: int, force: bool = False) -> None:
        now = time.monotonic()
        if force or now - self.last >= self.interval:
            self.last = now
            print(self.line(states, running), file=self.out, flush=True)


def _duration(seconds: float) -> str:
    seconds = int(seconds)
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def _describe(state: ModelState) -> str:
    m = state.metrics or {}
    numbers = f"clean SR {m.get('clean_sr', float('nan')):.3f}, poisoned SR {m.get('poisoned_sr', float('nan')):.3f}, {m.get('frames', 0):,} frames"
    verdict = "converged" if state.converged else f"not converged ({state.reason})"
    return f"{state.model.name} {state.model.group.key} attempt {state.model.attempt}: {verdict}; {numbers}"


def record_failure(folder: Path, error: str, tries: int) -> None:
    refuse_links(folder.parent.parent, folder)
    atomic_write_text(
        folder / FAILED,
        json.dumps({"error": error, "tries": tries, "host": socket.gethostname(), "time": time.strftime("%Y-%m-%d %H:%M:%S")}, indent=2, sort_keys=True) + "\n",
    )


def run(
    path: str | Path,
    workers: int | None = None,
    backend: str = "local",
    address: str | None = None,
    max_retries: int = 2,
    retry_failed: bool = False,
    progress_interval: float = 10.0,
    out: TextIO | None = None,
    retrain_tampered: bool = False,
    group_size: int | str = 1,
    env_workers: int = 0,
    device: str | None = None,
) -> dict:
    """Run the zoo at ``path`` to completion; return a summary. See the module docstring.
    ``env_workers``: each job steps a single-env world's copies in that many worker processes.
    ``device``: where every model's math runs instead of its planned ``train.device`` (each
    model's metrics.json records it; ``--group-size auto`` goes by it).

    The zoo is verified first (:mod:`rlbackdoors.zoo.verify`): a link anywhere is refused; a
    model that fails its checks is refused, or with ``retrain_tampered`` emptied and trained
    again from the config its plan draws (the same bytes as before it was tampered with)."""
    from rlbackdoors.folder import stack_versions

    out = out if out is not None else sys.stderr
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    if isinstance(env_workers, bool) or not isinstance(env_workers, int) or env_workers < 0:
        raise ConfigError(f"--env-workers must be an integer >= 0, got {env_workers!r}")
    if device is not None:
        if device not in DEVICES:
            raise ConfigError(f"--device={device!r} is not allowed (allowed: {', '.join(DEVICES)})")
        import torch

        if device == "cuda" and not torch.cuda.is_available():
            raise ConfigError("--device cuda: no CUDA device is available here (use cpu or auto)")
    auto = group_size == "auto"  # K per model's algorithm and device, as measured
    if auto:
        from rlbackdoors.train.group import AUTO_GROUP_SIZE

        table = "; ".join(
            f"{name} {AUTO_GROUP_SIZE[(a, 'cpu')]} on cpu, {AUTO_GROUP_SIZE[(a, 'cuda')]} on cuda" for a, name in (("ppo", "PPO"), ("opac2", "OPAC²"))
        )
        on = f"--device {device}" if device is not None else "train.device"
        print(
            f"zoo: --group-size auto: by each model's algorithm and {on} ({table}; on the compiled trainer a world's own where measured; docs/zoos.md)",
            file=out,
        )
        group_size = max(AUTO_GROUP_SIZE.values())
    if not isinstance(group_size, int) or group_size < 1:
        raise ConfigError(f"--group-size must be >= 1 or auto, got {group_size!r}")
    if max_retries < 0:
        raise ConfigError(f"--max-retries must be >= 0, got {max_retries}")
    zoo = Zoo.open(path)
    lock = zoo.lock()
    try:
        _check_before_run(zoo, retrain_tampered, out)  # a refused zoo is left as it was, METADATA.csv too
    except BaseException:
        lock.release()
        raise
    executor: Executor | None = None
    progress = Progress(out, progress_interval)
    states: list[ModelState] = []
    old_term = signal.getsignal(signal.SIGTERM)
    try:
        if threading_main():
            signal.signal(signal.SIGTERM, _raise_interrupt)
        planned = read_zoo_json(zoo.path).get("versions", {})
        now = stack_versions()
        changed = [k for k in now if planned.get(k) != now[k]]
        if changed:
            print(f"zoo: note: versions differ from the plan's ({', '.join(f'{k} {planned.get(k)} -> {now[k]}' for k in changed)})", file=out)
        # A killed plan, or a config.json a failed start removed: put every planned file back.
        for group in zoo.spec.groups:
            for attempt in range(group.wanted):
                zoo.ensure(group, attempt, verify=False)
        for model in zoo.all_planned():
            zoo.ensure(model.group, model.attempt, verify=False)
            if retry_failed:
                (zoo.folder(model) / FAILED).unlink(missing_ok=True)
        executor = make_executor(backend, workers, address, max_retries, group_size, env_workers, device)
        in_flight: dict[int, PlannedModel] = {}
        busy_until: dict[int, float] = {}
        tries: dict[int, int] = {}
        final: dict[int, ModelState] = {}
        announced: set[int] = set()  # finished inside a group job that is still running
        while True:
            states = _states(zoo, final, set(in_flight))
            _top_up(zoo, states, set(in_flight))
            states = _states(zoo, final, set(in_flight))
            for s in states:  # a group job writes each entry as its run ends: say so, count it now
                if s.model.id in in_flight and s.status == "done" and s.model.id not in announced:
                    announced.add(s.model.id)
                    progress.trained += 1
                    print(_describe(s), file=out, flush=True)
            now_t = time.monotonic()
            waiting = [s for s in states if s.status in ("pending", "running") and s.model.id not in in_flight]
            ready = sorted(
                (s for s in waiting if busy_until.get(s.model.id, 0.0) <= now_t),
                key=lambda s: (not (s.folder / "checkpoint.pt").is_file(), s.model.attempt, _affinity(s.model, s.config), s.model.group.index),
            )
            startable = []
            for s in ready:
                if s.status == "running" or is_locked(s.folder):
                    busy_until[s.model.id] = now_t + BUSY_PROBE_S
                    continue
                busy_until.pop(s.model.id, None)
                startable.append(s)
            free = executor.capacity - executor.running()
            for k, models in _by_group_size(startable, group_size, auto, device):
                for chunk in _chunks(models, free, k, like=lambda s: _affinity(s.model, s.config)):
                    if isinstance(executor, LocalExecutor):
                        executor.submit_group([s.model for s in chunk], [s.folder for s in chunk], k)
                    else:
                        executor.submit(chunk[0].model, chunk[0].folder)
                    in_flight.update((s.model.id, s.model) for s in chunk)
                    free -= 1
            if not in_flight and not waiting:
                break
            progress.maybe(states, sum(s.model.id in in_flight and s.status != "done" for s in states))
            timeout = min(progress_interval, BUSY_PROBE_S) if waiting or not in_flight else progress_interval
            for model, result in executor.wait(timeout):
                in_flight.pop(model.id, None)
                refuse_links(zoo.path, zoo.folder(model))  # swapped in while it ran: never read through
                status = result.get("status")
                if status == "done":
                    state = model_state(zoo, model, probe=False)
                    final[model.id] = state
                    if model.id in announced:  # counted as trained when first seen: correct that
                        progress.trained -= not result.get("trained")
                    else:
                        progress.trained += bool(result.get("trained"))
                        print(_describe(state), file=out, flush=True)
                elif status == "busy":
                    busy_until[model.id] = time.monotonic() + BUSY_PROBE_S
                elif status == "interrupted":
                    print(f"{model.name}: stopped by a signal (checkpoint written); it will resume", file=out, flush=True)
                    busy_until[model.id] = time.monotonic() + BUSY_PROBE_S
                else:
                    tries[model.id] = tries.get(model.id, 0) + 1
                    error = str(result.get("error", "unknown error"))
                    if tries[model.id] > max_retries:
                        record_failure(zoo.folder(model), error, tries[model.id])
                        final[model.id] = model_state(zoo, model, probe=False)
                        print(f"{model.name} {model.group.key}: failed {tries[model.id]} times, recorded in {FAILED}: {error}", file=out, flush=True)
                    else:
                        print(f"{model.name}: {error}; retrying ({tries[model.id]}/{max_retries})", file=out, flush=True)
        states = scan(zoo, probe=False)
        progress.maybe(states, 0, force=True)
    except KeyboardInterrupt:
        if executor is not None:
            executor.stop()
            executor = None
        raise
    finally:
        if threading_main():
            signal.signal(signal.SIGTERM, old_term)
        if executor is not None:
            executor.stop()
        try:
            write_metadata(zoo)
        finally:
            lock.release()
    counts = group_counts(zoo, states)
    print(status_table(zoo, states), file=out, flush=True)
    return {
        "models": len(states),
        "done": sum(s.status == "done" for s in states),
        "converged": sum(s.converged for s in states),
        "failed": sum(s.status == "failed" for s in states),
        "short": [c.group.key for c in counts if c.converged < c.group.wanted],
        "trained": progress.trained,
        "seconds": round(time.monotonic() - progress.started, 1),
    }


def _check_before_run(zoo: Zoo, retrain_tampered: bool, out: TextIO) -> None:
    """Refuse a zoo that fails verification, or empty its failing models to train them again."""
    from rlbackdoors.zoo.spec import ZooError
    from rlbackdoors.zoo.verify import ZOO_LEVEL, verify

    v = verify(zoo.path)
    for problem in v.problems.get(ZOO_LEVEL, []):
        if not v.links:
            print(f"zoo: note: {problem}; this run rewrites it", file=out, flush=True)
    bad = v.model_problems()
    if v.links or (bad and not retrain_tampered):
        flag = "" if v.links else ", or pass --retrain-tampered to empty those models and train them again"
        raise ZooError(f"{v.summary()}; {v.remedy()}{flag}")
    models = {m.name: m for m in (zoo.lookup(int(n[3:])) for n in bad if n[3:].isdigit()) if m is not None}
    foreign = sorted(set(bad) - set(models))
    if foreign:
        raise ZooError(f"zoo {str(zoo.path)!r}: {foreign[0]} {bad[foreign[0]]}; remove it (--retrain-tampered retrains only the zoo's planned models)")
    for name, model in sorted(models.items()):
        folder = zoo.folder(model)
        for attempt in range(model.attempt):  # a deleted earlier attempt: planned again
            zoo.ensure(model.group, attempt, verify=False)
        if folder.is_dir():
            lock = FolderLock(folder, "model folder")
            try:
                lock.acquire()
            except LockedError as err:
                raise ZooError(str(err)) from None
            try:
                for entry in folder.iterdir():
                    if entry.name != LOCK_NAME:
                        remove_tree(entry)
            finally:
                lock.release()
        zoo.ensure(model.group, model.attempt, verify=False)
        print(f"{name}: failed verification ({bad[name]}); emptied, it trains again", file=out, flush=True)


def threading_main() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def _raise_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def _affinity(model: PlannedModel, config: dict | None = None) -> tuple:
    """What a compiled group's program depends on, as far as the plan tells: models next to each
    other in the queue train together (a group job fills a freed slot with the next), and a group
    whose runs need other programs (other attacks) runs one call of the whole group's width per
    program, so like models are kept together (a group of 8 runs of six attacks computes six
    calls of 8 agents for 8 agents' work). With the model's planned ``config`` its own flags count
    too (attack parameters that are true, e.g. a drawn ``force_action``; evasive variants that are
    on), as a round's drawn settings make them differ within a cell. Harmless elsewhere: a run's
    bytes never depend on its group-mates."""
    cell, choice = model.group.cell, model.group.cell.attack
    if not model.group.poisoned:
        return (cell.world, cell.arch_label, "")
    poison = (config or {}).get("poison") or {}
    evasion = poison.get("evasion", choice.evasion) if config else choice.evasion
    variants = tuple(sorted(k for k, v in (evasion or {}).items() if v))  # (on or off is the program's; the numbers are data)
    flags = tuple(sorted(k for k, v in (poison.get("attack_params") or {}).items() if v is True))
    return (cell.world, cell.arch_label, choice.attack, variants, flags, choice.name)


def _by_group_size(ready: list, group_size: int, auto: bool, device: str | None = None) -> list[tuple[int, list]]:
    """The ready models by the group size they train at: ``group_size`` for all, or with
    ``--group-size auto`` the measured one of their world's algorithm on ``device`` (default:
    their ``train.device``; in the order first seen)."""
    if not auto:
        return [(group_size, ready)] if ready else []
    from rlbackdoors.train.group import auto_group_size

    out: dict[int, list] = {}
    for state in ready:
        where = device or ((state.config or {}).get("train") or {}).get("device", "cpu")
        world = worlds.get(state.model.group.cell.world)
        backend = ((state.config or {}).get("ppo") or {}).get("update_backend")
        out.setdefault(auto_group_size(world.algorithm, where, world, backend), []).append(state)
    return list(out.items())


def _chunks(ready: list, free: int, group_size: int, like=None) -> list[list]:
    """The jobs to start on ``free`` workers: one model each, or with a group size above one, the
    ready models shared out evenly, at most ``4 * group_size`` per job (a group job trains its
    share ``group_size`` at a time and fills a finished model's slot from the rest; the cap keeps
    results, top-ups and METADATA.csv coming while a large zoo trains). ``like`` (a model -> key):
    the models that start now (the first ones, in ``ready``'s order) are dealt out in its order,
    so like models share a job (a compiled group of 4 clean and 4 poisoned runs of a step-schedule
    attack ran two programs of 8 agents' width for 8 agents' work: x0.66 of the env mix's models/h)."""
    if free <= 0 or not ready:
        return []
    if group_size <= 1:
        return [[s] for s in ready[:free]]
    per = min(-(-len(ready) // free), 4 * group_size)
    chosen = ready[: per * free] if like is None else sorted(ready[: per * free], key=like)  # (stable: ready's order among like models)
    return [chosen[i : i + per] for i in range(0, len(chosen), per)]


def _states(zoo: Zoo, final: dict[int, ModelState], in_flight: set[int]) -> list[ModelState]:
    """Every planned model's state; finished ones are cached (they never change), in-flight ones
    are not probed (their lock is our own child's)."""
    out = []
    for model in zoo.all_planned():
        if model.id in final:
            out.append(final[model.id])
            continue
        state = model_state(zoo, model, probe=model.id not in in_flight)
        if state.status in ("done", "failed"):
            final[model.id] = state
        out.append(state)
    return out


def _top_up(zoo: Zoo, states: list[ModelState], in_flight: set[int]) -> int:
    """Plan new attempts where a group's unfinished models cannot reach what it wants."""
    added = 0
    for c in group_counts(zoo, states, in_flight):
        need = c.group.wanted - c.converged - c.pending - c.running
        attempt = c.planned
        while need > 0 and attempt < c.group.max_attempts:
            zoo.ensure(c.group, attempt)
            attempt += 1
            need -= 1
            added += 1
    return added


def status(path: str | Path, skip: dict[str, str] | None = None) -> str:
    """The status table; ``skip``: models that failed zoo verify, left out and named below it."""
    from rlbackdoors.zoo.verify import skipped_lines

    zoo = Zoo.open(path)
    return "\n".join([status_table(zoo, scan(zoo, skip=skip)), *skipped_lines(skip or {})])


__all__ = ["BACKENDS", "LocalExecutor", "default_workers", "run", "status"]
