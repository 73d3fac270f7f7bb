"""Zoo jobs forked from a server that has already imported torch and the package.

Why: a fresh interpreter spends about 2.5 s of CPU importing what a job needs (torch, the
``torch._dynamo`` that every ``torch.optim`` optimiser imports, numba, matplotlib, the worlds)
before it trains anything, and a short model (a tiny zoo's, or one that converges early) trains
in a few seconds. The server (``python -m rlbackdoors.zoo.forkserver``, one per coordinator)
imports them once; each job is then a fork of it running :func:`rlbackdoors.zoo.job.main` with
the argv a ``python -m rlbackdoors.zoo.job`` child gets. It is still a process of its own:
SIGTERM makes it checkpoint, ``kill -9`` kills it alone, its exit code or signal comes back as
before, and its stdout and stderr go to the model's ``train.log``.

Not :mod:`multiprocessing`'s forkserver: that one re-imports the coordinator's ``__main__``
script in every child (a user's script without a ``__main__`` guard would run again per job).

What the fork changes, and why it does not matter:

* The server is started with the job environment (one OpenMP/MKL thread, matplotlib's Agg
  backend), so what torch, numba and matplotlib read when imported is what a child would read;
  each job then gets the coordinator's environment and working directory as they are when the
  job starts (a coordinator that changed directory since the server started still means its
  relative folders).
* A job's parent is the server, not the coordinator. When the coordinator dies (its end of the
  socket closes) the server sends every running job SIGTERM and exits at once, and each job also
  asks for SIGTERM on its parent's death (:func:`rlbackdoors.zoo.job._die_with_parent`), so a
  ``kill -9`` of the coordinator still stops every job at a checkpoint.
* Training seeds its generators and sets its threads from its config, so a model's bytes are
  those of a fresh process (the zoo tests compare them with lone runs).

Protocol, over a Unix stream socket: the coordinator sends a 4-byte length and a JSON request
(argv, environment, working directory) with three descriptors (the log, the result pipe's write end, a status
pipe's write end); the server forks, closes its copies, and writes the child's pid (8 bytes) and
later its exit code (8 bytes, negative for a signal, as :class:`subprocess.Popen`) to the status
pipe.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import select
import signal
import socket
import struct
import subprocess
import sys
import time
import traceback

# What a job imports before it trains, imported once in the server. MuJoCo is left out: it reads
# MUJOCO_GL when imported, and the world that needs it trains for tens of minutes a model anyway.
PRELOAD = (
    "numpy",
    "torch",
    "torch.optim",
    "torch._dynamo",  # imported by the first optimiser built, not by torch.optim
    "numba",
    "matplotlib.pyplot",
    "rlbackdoors.zoo.job",
    "rlbackdoors.zoo.plan",
    "rlbackdoors.zoo.examples",
    "rlbackdoors.folder",
    "rlbackdoors.train",
    "rlbackdoors.train.group",
)
# The environment a job process has always had: read by OpenMP, MKL and matplotlib when they
# load, so the server is started with it.
JOB_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
_STATUS = struct.Struct("<q")
_LENGTH = struct.Struct("<I")


class _Server:
    """The coordinator's handle on its server: the process and its end of the socket."""

    def __init__(self) -> None:
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "rlbackdoors.zoo.forkserver", str(theirs.fileno())],
                pass_fds=(theirs.fileno(),),
                stdin=subprocess.DEVNULL,
                env={**os.environ, **JOB_ENV},
            )
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
        self.sock = ours

    def alive(self) -> bool:
        return self.proc.poll() is None

    def fork(self, argv: list[str], environ: dict[str, str], fds: list[int]) -> None:
        data = json.dumps({"argv": argv, "environ": environ, "cwd": os.getcwd()}).encode()
        socket.send_fds(self.sock, [_LENGTH.pack(len(data))], fds)
        self.sock.sendall(data)


_server: _Server | None = None


def _the_server() -> _Server:
    global _server
    if _server is None or not _server.alive():
        if _server is not None:
            _server.sock.close()
        _server = _Server()
    return _server


class JobProcess:
    """A forked job, with the part of :class:`subprocess.Popen`'s interface the coordinator uses."""

    def __init__(self, argv: list[str], log_fd: int, result_fd: int, environ: dict[str, str]):
        status_r, status_w = os.pipe()
        try:
            try:
                _the_server().fork(argv, environ, [log_fd, result_fd, status_w])
            finally:
                os.close(status_w)
            self.returncode: int | None = None
            self._status = status_r
            self._buffer = b""
            self._eof = False
            pid = self._read(blocking=True)
        except BaseException:
            os.close(status_r)
            raise
        if pid is None:
            os.close(status_r)
            raise OSError("the zoo's fork server stopped before it started the job")
        self.pid = pid
        os.set_blocking(status_r, False)

    def _read(self, blocking: bool) -> int | None:
        """The next status number, or None if it has not come yet (or never will: then
        ``self._eof`` is set)."""
        size = _STATUS.size
        while len(self._buffer) < size:
            try:
                chunk = os.read(self._status, size - len(self._buffer))
            except BlockingIOError:
                return None
            if not chunk:
                self._eof = True
                return None
            self._buffer += chunk
            if not blocking and len(self._buffer) < size:
                return None
        value = _STATUS.unpack(self._buffer[:size])[0]
        self._buffer = self._buffer[size:]
        return value

    def poll(self) -> int | None:
        """The exit code (negative: killed by that signal), or None while it runs."""
        if self.returncode is None:
            code = self._read(blocking=False)
            if code is None and self._eof:
                code = 1  # the server died before it saw the job end (the job stops on its parent's death)
            if code is not None:
                self.returncode = code
                os.close(self._status)
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            os.kill(self.pid, sig)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)

    def wait(self, timeout: float | None = None) -> int:
        deadline = None if timeout is None else time.monotonic() + timeout
        while self.poll() is None:
            left = None if deadline is None else deadline - time.monotonic()
            if left is not None and left <= 0:
                raise subprocess.TimeoutExpired(f"zoo job {self.pid}", timeout or 0.0)
            select.select([self._status], [], [], left)
        return self.returncode  # type: ignore[return-value]


# --- the server ---------------------------------------------------------------------------------


def _recv_exact(sock: socket.socket, size: int) -> bytes:
    data = b""
    while len(data) < size:
        chunk = sock.recv(size - len(data))
        if not chunk:
            raise EOFError
        data += chunk
    return data


def _child(sock: socket.socket, request: dict, log: int, result: int, others: list[int]) -> None:
    """The forked job: never returns. ``others``: the server's descriptors it must not keep (other
    jobs' status pipes, the server's wake-up pipe)."""
    code = 1
    try:
        sock.close()
        signal.set_wakeup_fd(-1)
        for fd in others:
            os.close(fd)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        os.dup2(log, 1)
        os.dup2(log, 2)
        os.close(log)
        os.environ.clear()
        os.environ.update(request["environ"])
        os.chdir(request["cwd"])  # the coordinator's, now: relative folders mean what they mean there
        from rlbackdoors.zoo.job import PARENT_ENV, main

        os.environ[PARENT_ENV] = str(os.getppid())
        code = main([*request["argv"], "--result-fd", str(result)])
    except SystemExit as err:
        code = err.code if isinstance(err.code, int) else 1
    except BaseException:
        traceback.print_exc()
    finally:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)


def _warm_numba() -> None:
    """Compile one trivial kernel: numba loads its typing and lowering machinery on the first
    compile (or cache load) a process makes, about half a second, which every job would repeat."""
    import numba
    import numpy as np

    numba.njit(lambda a: a.sum() + 1)(np.zeros(2, np.int64))


def serve(fd: int) -> None:
    """Import :data:`PRELOAD`, then fork a job per request until the coordinator goes."""
    for name in PRELOAD:
        importlib.import_module(name)
    _warm_numba()
    sock = socket.socket(fileno=fd)
    status: dict[int, int] = {}  # running child's pid -> its status pipe
    # a job's end wakes the loop: SIGCHLD writes a byte to this pipe (the handler itself does nothing)
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_r, False)
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)
    while True:
        readable, _, _ = select.select([sock.fileno(), wake_r], [], [])
        if wake_r in readable:
            with contextlib.suppress(BlockingIOError):  # drain it
                while os.read(wake_r, 4096):
                    pass
            while status:
                pid, wait_status = os.waitpid(-1, os.WNOHANG)
                if not pid:
                    break
                if pid in status:
                    os.write(status[pid], _STATUS.pack(os.waitstatus_to_exitcode(wait_status)))
                    os.close(status.pop(pid))
        if sock.fileno() not in readable:
            continue
        try:
            header, fds, _, _ = socket.recv_fds(sock, _LENGTH.size, 3)
            if not header:
                raise EOFError
            header += _recv_exact(sock, _LENGTH.size - len(header))
            request = json.loads(_recv_exact(sock, _LENGTH.unpack(header)[0]))
        except EOFError:  # the coordinator closed its end or died: every running job checkpoints and stops
            for pid in status:
                os.kill(pid, signal.SIGTERM)
            os._exit(0)  # now, not after the interpreter's teardown (a tiny job could finish meanwhile)
        log, result, fd_w = fds
        pid = os.fork()
        if pid == 0:
            _child(sock, request, log, result, [*status.values(), fd_w, wake_r, wake_w])
        os.close(log)
        os.close(result)
        os.write(fd_w, _STATUS.pack(pid))
        status[pid] = fd_w


if __name__ == "__main__":
    serve(int(sys.argv[1]))
