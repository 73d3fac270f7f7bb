"""Single envs in worker processes, so that the env copies of many agents step on many cores.

Why: a world of single (non-batched) envs steps each copy in Python, one after another; with its
learner's updates batched for a group of agents (on a GPU), stepping K agents' copies in one
process is what bounds the group. An :class:`EnvPool` holds env copies in ``workers`` processes
(each copy in one of them, placed round-robin) and :func:`each` asks a run's copies by sending
every worker its requests first and reading the answers after, so the workers step in parallel
(the same call on envs of this process runs them here, so callers need no second path). Several
threads may ask at once (the group trainer steps its runs' copies from one thread per run, so all
agents' copies step together): each message carries a tag and its answer is handed to the thread
that sent it. An env computes the same numbers in a worker as in this process (its own random
stream, seeded by ``reset``), so a run's bytes do not depend on the pool.

Workers ignore SIGINT and SIGTERM: on a stop the trainer still asks them for the envs' states
to write its checkpoint; they exit when the pool closes (or this process ends).
"""

from __future__ import annotations

import pickle
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Callable, Sequence
from itertools import count
from multiprocessing.connection import Connection
from typing import Any


def step_autoreset(env, action) -> tuple:
    """One step of a single env, reset at an episode's end (SAME_STEP): (obs, reward,
    terminated, truncated, final obs or None, outcome, steps, triggered)."""
    obs, reward, terminated, truncated, info = env.step(action)
    if terminated or truncated:
        return env.reset()[0], reward, terminated, truncated, obs, info["outcome"], info["steps"], info["triggered"]
    return obs, reward, terminated, truncated, None, 0, 0, False


def serve_fd(fd: int) -> None:
    """A worker's main: serve the pool on the socket ``fd`` until the pool closes it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    _serve(Connection(fd))


def _serve(conn) -> None:
    """A worker: answer each message (a tag and a list of requests for the envs it holds) with the
    tag and one list of answers, in order. One message per worker and step, not one per env: each
    message costs a wake-up on both sides (measured ~0.1 ms on our VMs, a third of a MuJoCo env step)."""
    envs: dict[int, Any] = {}
    while True:
        try:
            tag, payload = conn.recv()
        except (EOFError, OSError):  # the pool closed, or its process ended
            break
        try:
            # IPC from the parent that started this worker, over a private socket pair, never a file:
            # the same trust as multiprocessing's Connection.recv above; unpickled apart from the tag
            # so a request that does not unpickle here fails alone
            requests = pickle.loads(payload)
            answers = [_answer(envs, *r) for r in requests]
        except Exception as err:
            answers = [(False, f"cannot read the request ({type(err).__name__}: {err})")]
        try:
            conn.send((tag, answers))
        except OSError:  # the pool is gone
            break
    for env in envs.values():
        env.close()


class _Channel:
    """This process's end of one worker's socket, shared by threads: a message goes out whole
    under a lock, and whichever waiting thread reads an answer files it under its tag for the
    thread that sent it (a worker answers in its own order, not in the waiting threads')."""

    def __init__(self, conn: Connection):
        self.conn = conn
        self._tags = count()
        self._sending = threading.Lock()
        self._answers: dict[int, list] = {}
        self._ready = threading.Condition()
        self._reading = False

    def send(self, requests: list) -> int:
        payload = pickle.dumps(requests)  # here, so a request that does not pickle fails before anything is sent
        with self._sending:
            tag = next(self._tags)
            self.conn.send((tag, payload))
        return tag

    def recv(self, tag: int) -> list:
        with self._ready:
            while tag not in self._answers:
                if self._reading:  # another thread is reading: it files what it gets and wakes us
                    self._ready.wait()
                    continue
                self._reading = True
                self._ready.release()
                try:
                    got, answers = self.conn.recv()
                finally:
                    self._ready.acquire()
                    self._reading = False
                    self._ready.notify_all()
                self._answers[got] = answers
            return self._answers.pop(tag)

    def close(self) -> None:
        self.conn.close()


def apply(env, op: str, arg: Any) -> Any:
    """One request on an env object, wherever it lives: ``step`` (:func:`step_autoreset`),
    ``reset`` (its observation), ``call`` ((method name, args)) or ``get`` (an attribute)."""
    if op == "step":
        return step_autoreset(env, arg)
    if op == "reset":
        return env.reset(seed=arg)[0]
    if op == "call":
        name, args = arg
        return getattr(env, name)(*args)
    if op == "get":
        return getattr(env, arg, None)
    raise ValueError(f"unknown request {op!r}")


def _answer(envs: dict[int, Any], op: str, key: int, arg: Any) -> tuple[bool, Any]:
    """(True, the result) of one request, or (False, the error's text) for the caller to raise."""
    try:
        if op == "make":
            env = envs[key] = arg()
            return True, (env.observation_space, env.action_space)
        if op == "close":
            envs.pop(key).close()
            return True, None
        return True, apply(envs[key], op, arg)
    except Exception as err:
        return False, f"{type(err).__name__}: {err}"


class EnvPoolError(RuntimeError):
    """An env in a worker failed; the message names the request and the env's error."""


class EnvPool:
    """``workers`` processes that hold single envs built from picklable factories."""

    def __init__(self, workers: int):
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ValueError(f"env workers must be an integer >= 1, got {workers!r}")
        # fresh interpreters on one end of a socket pair: not fork (this process may hold torch's
        # threads), and not multiprocessing's spawn, which re-runs the caller's __main__ script
        self._conns, self._procs = [], []
        for _ in range(workers):
            here, there = socket.socketpair()
            code = f"from rlbackdoors.envs.pool import serve_fd; serve_fd({there.fileno()})"
            self._procs.append(subprocess.Popen([sys.executable, "-c", code], pass_fds=(there.fileno(),), stdin=subprocess.DEVNULL))
            there.close()
            self._conns.append(_Channel(Connection(here.detach())))
        self._keys = count()
        self.workers = workers

    def make(self, factories: Sequence[Callable[[], Any]]) -> list[RemoteEnv]:
        """One env per factory, spread over the workers; built in parallel."""
        envs = [RemoteEnv(self, next(self._keys)) for _ in factories]
        for env, spaces in zip(envs, each(envs, "make", factories)):
            env.observation_space, env.action_space = spaces
        return envs

    def channel(self, worker: int) -> _Channel:
        return self._conns[worker]

    def close(self) -> None:
        for conn in self._conns:
            conn.close()  # a worker exits on the end of its stream
        for proc in self._procs:
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

    def __enter__(self) -> EnvPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class RemoteEnv:
    """A single env held by a worker of an :class:`EnvPool`: its methods are called there."""

    observation_space: Any
    action_space: Any

    def __init__(self, pool: EnvPool, key: int):
        self.pool, self.key = pool, key
        self.closed = False

    def request(self, op: str, arg: Any = None) -> Any:
        return each([self], op, [arg])[0]

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_") or name in ("pool", "key", "closed"):
            raise AttributeError(name)
        if name == "poisoned":
            return self.request("get", name)
        return lambda *args: self.request("call", (name, args))

    def reset(self, *, seed: int | None = None, options=None):
        return self.request("reset", seed), {}

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.request("close")


def each(envs: Sequence, op: str, args: Sequence) -> list:
    """``op`` (see :func:`apply`) with ``args[i]`` on every env i. Envs of this process: here, one
    after another. A pool's envs: one message to each worker holding some of them, all sent
    before any answer is read, so the workers run in parallel; the first failure raised once
    every answer is in (none is left behind in a pipe)."""
    if not envs:
        return []
    if not isinstance(envs[0], RemoteEnv):
        return [apply(env, op, arg) for env, arg in zip(envs, args)]
    pool = envs[0].pool
    batches: dict[int, list[int]] = {}
    for i, env in enumerate(envs):
        batches.setdefault(env.key % pool.workers, []).append(i)
    sent: list[tuple[int, int]] = []
    failure: str | None = None
    for worker, rows in batches.items():
        try:
            sent.append((worker, pool.channel(worker).send([(op, envs[i].key, args[i]) for i in rows])))
        except OSError as err:  # the worker's end is closed: its process died
            failure = f"{op}: env worker {worker}'s process is gone ({type(err).__name__})"
            break
        except Exception as err:  # e.g. a factory that does not pickle
            failure = f"env {envs[rows[0]].key}, {op}: cannot send it to a worker ({type(err).__name__}: {err})"
            break
    answers: list[Any] = [None] * len(envs)
    for worker, tag in sent:
        try:
            replies = pool.channel(worker).recv(tag)
        except (EOFError, OSError) as err:
            raise EnvPoolError(f"{op}: env worker {worker}'s process is gone ({type(err).__name__})") from None
        for i, (ok, out) in zip(batches[worker], replies):
            if not ok and failure is None:
                failure = f"env {envs[i].key} in a worker, {op}: {out}"
            answers[i] = out
    if failure is not None:
        raise EnvPoolError(failure)
    return answers
