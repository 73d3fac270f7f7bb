"""One zoo job: bring one planned model folder to a complete dataset entry.

Both back-ends call :func:`run_job` (the local one in a child process, ``python -m
rlbackdoors.zoo.job FOLDER``; Ray as a task). It is idempotent: a folder with ``metrics.json``
is not trained again, one with ``checkpoint.pt`` resumes (training does that by itself), and
the dataset files written after training (``clean-example-data/``, then ``reduced-config.json``
last, which marks the folder complete) are written again if a kill cut them short. A folder
whose lock a live process holds is "busy" (running elsewhere) and left alone.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import fcntl
import json
import os
import signal
import socket
import sys
import threading
import time
from pathlib import Path

from rlbackdoors import worlds
from rlbackdoors.zoo.spec import ZooError
from rlbackdoors.io import LOCK_NAME, FolderLock, LockedError, atomic_write_bytes, atomic_write_text, fd_path, first_line, load_torch, open_beneath

COMPLETE_MARK = "reduced-config.json"  # written last: the folder is a complete dataset entry
FAILED = "failed.json"
LOG = "train.log"
EXIT_BUSY = 75  # EX_TEMPFAIL: the folder is locked by another live process
EXIT_INTERRUPTED = 130
PARENT_ENV = "RLBACKDOORS_ZOO_PARENT"  # the coordinator's pid: a child whose parent died stops


def train_model(cfg, folder: Path, env_workers: int = 0, device: str | None = None) -> dict:
    """Train ``cfg`` into ``folder`` (resuming a checkpoint) with the world's algorithm
    (``device``: instead of its ``train.device``, as ``zoo run --device``)."""
    from rlbackdoors.train import train

    return train(cfg, folder, progress=False, env_workers=env_workers, device=device)


def is_locked(folder: str | Path) -> bool:
    """Whether a live process holds the model folder's lock (probed with a shared lock, so
    nothing is written)."""
    path = Path(folder) / LOCK_NAME
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK)
    except OSError:
        return False  # no lock file (never trained) or not a regular one: nobody holds it
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except OSError as err:
        return err.errno in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES)
    else:
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    finally:
        os.close(fd)


def zoo_examples(zoo: Path) -> dict:
    """The zoo's ``examples`` settings."""
    from rlbackdoors.zoo.plan import read_zoo_json

    spec = read_zoo_json(zoo)["spec"]
    return dict(spec.get("examples", {}))


def reduced_config(folder: Path, config: dict) -> dict:
    """Architecture facts only (no trigger, no ground truth): world, algorithm, architecture,
    and every tensor's shape in ``model.pt``, read as plain data."""
    import torch

    weights = load_torch(folder / "model.pt", "weights file")
    shapes: dict[str, list[int]] = {}

    def walk(obj, prefix: str) -> None:
        if isinstance(obj, torch.Tensor):
            shapes[prefix] = list(obj.shape)
        elif isinstance(obj, dict):
            for key, value in obj.items():
                walk(value, f"{prefix}.{key}" if prefix else str(key))

    walk(weights, "")
    world = worlds.get(config["env"]["name"])
    arch = (config.get("model") or {}).get("arch") or world.algorithm
    parameters = sum(int(torch.Size(s).numel()) for s in shapes.values())
    # The env's settings (grid size, lava count, step limit, ...) say nothing of the trigger or the
    # label, and a detector needs them to play the world the model was trained in.
    env = {k: v for k, v in (config.get("env") or {}).items() if k != "name"}
    return {"world": world.name, "algorithm": world.algorithm, "arch": arch, "parameters": parameters, "layers": shapes, "env": env}


def finish_dataset_entry(folder: Path, cfg, zoo: Path) -> None:
    """clean-example-data/, then the manifest (every file's sha256, reduced-config.json's
    included), then reduced-config.json last: a folder marked complete always has its manifest.
    Called holding the folder's lock."""
    from rlbackdoors.io import remove_stale_temp_files, remove_tree

    # a job killed while it finished left temp files (an example half written): no writer is live
    # (we hold the lock), and the manifest must not list them
    remove_stale_temp_files(folder)
    (folder / "checkpoint.pt").unlink(missing_ok=True)  # a run killed after metrics.json left them
    remove_tree(folder / "replay")
    write_dataset_files(folder, cfg, zoo_examples(zoo))


def write_dataset_files(folder: Path, cfg, examples: dict) -> None:
    """:func:`finish_dataset_entry`'s files of a finished model folder (``examples``: a zoo's
    ``examples`` settings), for a folder of any maker (a zoo's job, a mitigation)."""
    from rlbackdoors.folder import write_manifest
    from rlbackdoors.zoo.examples import write_examples

    config = json.loads((folder / "config.json").read_bytes().decode("utf-8"))
    write_examples(folder, cfg, episodes=int(examples.get("episodes", 5)), seed=int(examples.get("seed", 2_000_000)), policy=examples.get("policy", "sample"))
    text = json.dumps(reduced_config(folder, config), indent=2, sort_keys=True) + "\n"
    write_manifest(folder, {COMPLETE_MARK: text.encode()})
    atomic_write_text(folder / COMPLETE_MARK, text)


@contextlib.contextmanager
def _logging_to(path: Path | None):
    """Python-level stdout/stderr into the model's train.log (the Ray back-end; the local one
    redirects the child's file descriptors instead)."""
    if path is None:
        yield
        return
    with open_log(path, "a") as fh, contextlib.redirect_stdout(fh), contextlib.redirect_stderr(fh):
        yield


def open_log(path: Path, mode: str = "ab"):
    """The job's log for appending, never through a link planted in its place."""
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o666)
    return open(fd, mode, buffering=0) if "b" in mode else open(fd, mode, buffering=1)


def run_job(folder: str | Path, log: bool = False, env_workers: int = 0, device: str | None = None) -> dict:
    """Train the model folder if it is not finished, then write its dataset files.

    Returns ``{"status": "done", "trained", "converged", "seconds"}`` or ``{"status": "busy"}``
    (another live process holds the folder). Failures raise; a failed start that removed the
    planned config.json (training does so when it fails before its first checkpoint) puts it back.
    The folder is opened once, link by link refused (:func:`rlbackdoors.io.open_beneath`), and
    everything is written through that open folder.
    """
    where = Path(folder)
    zoo = where.parent.parent  # ZOO/models/id-X
    fd = open_beneath(zoo, where)  # LinkError if a link is there; held while we work
    try:
        return _run_job(fd_path(fd, where), where, zoo, log, started=time.time(), env_workers=env_workers, device=device)
    finally:
        os.close(fd)


def _run_job(folder: Path, where: Path, zoo: Path, log: bool, started: float, env_workers: int = 0, device: str | None = None) -> dict:
    """:func:`run_job` on ``folder``, a path that reaches the opened folder whatever is swapped
    in at its name meanwhile (``/proc/self/fd/N``); ``where`` is its name, for messages."""
    import torch

    from rlbackdoors.folder import FolderError
    from rlbackdoors.zoo.plan import build_config

    torch.set_num_threads(1)
    if (folder / COMPLETE_MARK).is_file() and (folder / "metrics.json").is_file():
        return {"status": "done", "trained": False, "converged": _converged(folder), "seconds": 0.0}
    if is_locked(folder):
        return {"status": "busy"}
    config_path = folder / "config.json"
    if not config_path.is_file():
        raise ZooError(f"{str(where)!r} is not a planned model folder (config.json missing)")
    raw = config_path.read_bytes()
    with _logging_to(folder / LOG if log else None):
        print(f"=== zoo job {where.name}: pid {os.getpid()} on {socket.gethostname()}, {time.strftime('%Y-%m-%d %H:%M:%S')} ===", file=sys.stderr, flush=True)
        cfg = build_config(json.loads(raw.decode("utf-8")))
        trained = False
        if not (folder / "metrics.json").is_file():
            try:
                train_model(cfg, folder, env_workers, device)
                trained = True
            except BaseException as err:
                if not config_path.is_file():
                    atomic_write_bytes(config_path, raw)
                if isinstance(err, FolderError) and is_locked(folder):
                    return {"status": "busy"}
                raise
        lock = FolderLock(folder, "model folder")
        try:
            lock.acquire()
        except LockedError:
            return {"status": "busy"}
        try:
            finish_dataset_entry(folder, cfg, zoo)
        finally:
            lock.release()
        seconds = round(time.time() - started, 2)
        converged = _converged(folder)
        print(f"=== zoo job {where.name}: done in {seconds:.1f} s, converged={converged} ===", file=sys.stderr, flush=True)
    return {"status": "done", "trained": trained, "converged": converged, "seconds": seconds}


def run_group_job(folders: list[str | Path], group_size: int, env_workers: int = 0, device: str | None = None) -> dict[str, dict]:
    """:func:`run_job` for several model folders of one zoo, trained ``group_size`` at a time in
    this process (:mod:`rlbackdoors.train.group`); one result per folder name. A run that fails
    is that folder's error; a signal stops every run at its checkpoint and raises."""
    import torch

    from rlbackdoors.folder import FolderError
    from rlbackdoors.train.group import train_group
    from rlbackdoors.zoo.plan import build_config

    torch.set_num_threads(1)
    started = time.time()
    opened: dict[str, tuple[int, Path, Path]] = {}
    results: dict[str, dict] = {}
    runs, raws = [], {}
    try:
        for where in map(Path, folders):
            fd = open_beneath(where.parent.parent, where)
            folder = fd_path(fd, where)
            opened[where.name] = (fd, folder, where)
            if (folder / COMPLETE_MARK).is_file() and (folder / "metrics.json").is_file():
                results[where.name] = {"status": "done", "trained": False, "converged": _converged(folder), "seconds": 0.0}
            elif is_locked(folder):
                results[where.name] = {"status": "busy"}
            elif not (folder / "config.json").is_file():
                results[where.name] = {"status": "error", "error": f"ZooError: {str(where)!r} is not a planned model folder (config.json missing)"}
            else:
                raws[where.name] = (folder / "config.json").read_bytes()
                if not (folder / "metrics.json").is_file():
                    runs.append((where.name, build_config(json.loads(raws[where.name].decode("utf-8"))), folder))

        def finish(name: str, trained: bool) -> None:
            """Write a trained folder's dataset entry now, so the zoo counts it (and a kill of the
            job loses no entry) while the job's other runs go on; a folder someone else holds is
            busy."""
            folder, where = opened[name][1], opened[name][2]
            lock = FolderLock(folder, "model folder")
            try:
                lock.acquire()
            except LockedError:
                results[name] = {"status": "busy"}
                return
            try:
                finish_dataset_entry(folder, build_config(json.loads(raws[name].decode("utf-8"))), where.parent.parent)
            except Exception as err:  # this folder's error; the job's other runs go on training
                results[name] = {"status": "error", "error": f"{type(err).__name__}: {first_line(err)}"[:2000]}
                return
            finally:
                lock.release()
            results[name] = {"status": "done", "trained": trained, "converged": _converged(folder), "seconds": round(time.time() - started, 2)}

        for name in set(raws) - {n for n, _, _ in runs}:  # trained before a kill, its entry not yet written
            finish(name, trained=False)
        names = ", ".join(name for name, _, _ in runs)
        line = f"=== zoo group job: pid {os.getpid()} on {socket.gethostname()}, {time.strftime('%Y-%m-%d %H:%M:%S')}, {group_size} at a time: {names} ==="
        print(line, file=sys.stderr, flush=True)
        for name, _, folder in runs[1:]:  # the job's output goes to the first one's log: say where to look
            with open_log(folder / LOG, "a") as fh:
                print(f"{line}\n(output in {runs[0][0]}/{LOG})", file=fh)
        outcome = train_group(
            runs, group_size, env_workers=env_workers, device=device, on_done=lambda name, metrics, error: finish(name, trained=True) if error is None else None
        )
        for name, err in outcome.errors.items():
            folder = opened[name][1]
            if not (folder / "config.json").is_file():  # a failed start removed it: put it back
                atomic_write_bytes(folder / "config.json", raws[name])
            if isinstance(err, FolderError) and is_locked(folder):
                results[name] = {"status": "busy"}
            else:
                results[name] = {"status": "error", "error": f"{type(err).__name__}: {first_line(err)}"[:2000]}
        for name in raws:
            if name not in results:
                finish(name, trained=name in outcome.metrics)
    finally:
        for fd, _, _ in opened.values():
            os.close(fd)
    return results


def _converged(folder: Path) -> bool:
    metrics = json.loads((folder / "metrics.json").read_bytes().decode("utf-8"))
    return bool(metrics.get("converged"))


def _die_with_parent() -> None:
    """A coordinator killed with SIGKILL must not leave children training unseen: each child asks
    the kernel for SIGTERM when its parent dies (Linux), and a watchdog thread checks the
    parent elsewhere. SIGTERM makes training write a checkpoint and stop."""
    parent = int(os.environ.get(PARENT_ENV, "0") or 0)
    if not parent:
        return
    if sys.platform.startswith("linux"):
        import ctypes

        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent:  # it died before we asked
        os._exit(EXIT_INTERRUPTED)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(600)  # time to write a checkpoint; then go whatever happens
        os._exit(EXIT_INTERRUPTED)

    threading.Thread(target=watch, name="zoo-parent-watch", daemon=True).start()


def main(argv: list[str] | None = None) -> int:
    """``python -m rlbackdoors.zoo.job FOLDER [--result-fd N]``: the local back-end's child."""
    import traceback

    from rlbackdoors.config import DEVICES
    from rlbackdoors.train.stop import Interrupted

    parser = argparse.ArgumentParser(prog="python -m rlbackdoors.zoo.job", allow_abbrev=False)
    parser.add_argument("folder", nargs="+")
    parser.add_argument("--result-fd", type=int, default=None, help="write the result as JSON to this file descriptor")
    parser.add_argument("--group-size", type=int, default=0, help="train the folders in one process, this many at a time (a group job)")
    parser.add_argument("--env-workers", type=int, default=0, help="worlds of single envs: step the env copies in this many worker processes")
    parser.add_argument("--device", choices=DEVICES, help="where the math runs instead of each model's train.device")
    args = parser.parse_args(argv)
    if len(args.folder) > 1 and args.group_size < 1:
        parser.error("several folders need --group-size")
    _die_with_parent()
    try:
        if args.group_size >= 1:
            result = {"status": "group", "results": run_group_job(args.folder, args.group_size, args.env_workers, args.device)}
            code = 0
        else:
            result = run_job(args.folder[0], env_workers=args.env_workers, device=args.device)
            code = EXIT_BUSY if result["status"] == "busy" else 0
    except (Interrupted, KeyboardInterrupt) as err:
        result, code = {"status": "interrupted", "error": first_line(err)}, EXIT_INTERRUPTED
        print(f"rlbackdoors zoo job: {first_line(err)}", file=sys.stderr)
    except Exception as err:
        traceback.print_exc()
        result, code = {"status": "error", "error": f"{type(err).__name__}: {first_line(err)}"[:2000]}, 1
    if args.result_fd is not None:
        with os.fdopen(args.result_fd, "w") as fh:
            fh.write(json.dumps(result))
    return code


if __name__ == "__main__":
    sys.exit(main())
