"""Training curves and GIFs drawn by worker processes, for a group trainer whose GPU would wait on them.

Why: a curve costs about 0.2 s of matplotlib in the calling thread (text layout, then the PNG).
A GPU group that finishes 256 models together would hold the device for about 50 s on them
(measured on a CPU: 32 grid-world models of 4,096 frames in one group spent more of their wall
time drawing curves than training), and a run's clean-vs-triggered GIF (episodes played and
rendered) costs 1.5 to 2 s. Here up to N processes of their own draw them in parallel.

The runs still write their own files: a painter sends the picture back as bytes, so the model
folder's path rules hold and nothing else writes into it (nor reads from it: a GIF's weights
come over the pipe). A painter is ``python -m rlbackdoors.report.painters``: one JSON request a
line on stdin (an id and the :func:`draw` job), one JSON reply a line on stdout (the id, the
picture in base64 and the CPU seconds it took, its start-up counted in the first, or the
error). A painter ends with ``os._exit`` once its replies are flushed: Python's teardown of torch,
numba and matplotlib cost about 0.33 CPU-s a painter (15 % of its CPU on an AMD EPYC) and served
nothing. Whatever its replies could not carry (that exit, a painter killed mid-picture) the pool
reads from the kernel as it reaps each painter (``wait4``) and reports as :attr:`Painters.unreported_s`,
so the CPU a group spends on its pictures is counted whole, not by a margin that holds on one CPU. What else a library prints goes to stderr, and a line without the id is passed over.
No pickle crosses the pipe; weights are read as data (``weights_only``). A picture whose painter fails or dies is drawn in
the caller instead, so a model never goes without it; the caller's drawing raises what drawing
raises alone (a MuJoCo GIF without an offscreen GL back-end, say). Painters exit at
the end of their input, so they end with the process that started them, even after a ``kill -9``.
"""

from __future__ import annotations

import base64
import json
import os
import selectors
import signal
import subprocess
import sys
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path


@dataclass
class Drawn:
    """A picture's bytes (PNG or GIF), and the CPU seconds a painter process spent on it (0: drawn
    in the caller, whose own clock counts it)."""

    png: bytes
    cpu_s: float = 0.0


def draw(job: dict) -> bytes:
    """The picture of one request: a training curve (``kind`` "curve": ``rows``, ``title``,
    ``thresholds``, ``switch_at``, as :func:`rlbackdoors.report.curves.render_training_curve`
    takes them) or a clean-vs-triggered GIF (``kind`` "gif": the run's ``config`` dict, its
    ``model.pt`` as base64 ``weights``, read as data only, and the episode's ``seed`` and ``policy``)."""
    if job.get("kind", "curve") == "gif":
        return _gif(job)
    from rlbackdoors.report.curves import render_training_curve  # matplotlib: only where a curve is drawn

    clean, poisoned = job["thresholds"]
    return render_training_curve(job["rows"], job["title"], (clean, poisoned), job.get("switch_at"))


def _gif(job: dict) -> bytes:
    """The GIF a finishing run would render itself, from its config and weights: the same
    network, acting on one thread as the run's learner does by default."""
    import io

    import torch

    from rlbackdoors.agent import Agent, policy_from_weights
    from rlbackdoors.config import RunConfig
    from rlbackdoors.report.video import render_clean_vs_triggered

    cfg = RunConfig.from_dict(job["config"])
    if cfg.poison.trigger is None:
        raise ValueError("a clean-vs-triggered GIF needs the run's trigger (poison.trigger)")
    torch.set_num_threads(cfg.train.torch_threads)
    weights = torch.load(io.BytesIO(base64.b64decode(job["weights"])), map_location="cpu", weights_only=True)
    agent = Agent(cfg.world, cfg, policy_from_weights(cfg, weights, "the weights a painter was sent"))
    return render_clean_vs_triggered(agent, cfg.env, cfg.poison.trigger, int(job["seed"]), job["policy"])


def _plain(value):
    """JSON for numpy scalars in the rows (exact: ``item()`` gives the same float or int)."""
    if hasattr(value, "item"):
        return value.item()
    raise TypeError(f"a curve's rows hold a {type(value).__name__}, not a number")


class Painters:
    """Up to ``workers`` painter processes, started at the first batch of two or more pictures and
    kept for the next (a start costs about 0.6 s of imports); ``workers`` below 2 draws every
    picture in the caller, as a lone run does. Use as a context manager, or call :meth:`close`."""

    def __init__(self, workers: int, timeout: float = 300.0):
        self.workers = max(0, int(workers))
        self.timeout = timeout  # seconds without any reply: the busy painters are ended, their pictures drawn here
        self.procs: list[subprocess.Popen] = []
        self._reported: dict[int, float] = {}  # pid: the CPU seconds its replies carried
        self.unreported_s = 0.0  # reaped painters' CPU (the kernel's count) that no reply carried

    def __enter__(self) -> Painters:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _start(self, n: int) -> None:
        root = str(Path(__file__).resolve().parents[2])  # the folder that holds the package, as this process found it
        path = os.environ.get("PYTHONPATH")
        env = {**os.environ, "MPLBACKEND": "Agg", "OMP_NUM_THREADS": "1", "PYTHONPATH": root + (os.pathsep + path if path else "")}
        while len(self.procs) < n:
            proc = subprocess.Popen([sys.executable, "-m", "rlbackdoors.report.painters"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
            self.procs.append(proc)
            self._reported[proc.pid] = 0.0

    def render(self, jobs: list[dict], here: list[Callable[[], bytes]] | None = None) -> list[Drawn | BaseException]:
        """Each job's picture (:func:`draw`), or the exception drawing it raised, in the jobs' order;
        ``here``: how the caller draws each itself where a painter cannot (default: :func:`draw`)."""
        results: list[Drawn | BaseException | None] = [None] * len(jobs)
        if self.workers >= 2 and len(jobs) >= 2:
            self._start(min(self.workers, len(jobs)))
            self._farm(jobs, results)
        for i, job in enumerate(jobs):  # no painters, or theirs failed: here, as alone
            if results[i] is None:
                try:
                    results[i] = Drawn(here[i]() if here is not None else draw(job))
                except Exception as err:  # the run that asked gets it, the others their pictures
                    results[i] = err
        return [r for r in results if r is not None]

    def _farm(self, jobs: list[dict], results: list) -> None:
        """Hand each idle painter the next job until none is left; what fails stays None."""
        todo = deque(range(len(jobs)))
        busy: dict[int, tuple[subprocess.Popen, int]] = {}
        with selectors.DefaultSelector() as ready:

            def give(proc: subprocess.Popen) -> None:
                while todo:
                    i = todo.popleft()
                    try:
                        line = json.dumps({"id": i, "job": jobs[i]}, default=_plain).encode() + b"\n"
                    except (TypeError, ValueError):
                        continue  # drawn in the caller, which raises what is wrong with it
                    try:
                        assert proc.stdin is not None and proc.stdout is not None
                        proc.stdin.write(line)
                        proc.stdin.flush()
                    except OSError:  # a dead painter: the job goes back, the painter out
                        todo.appendleft(i)
                        self._drop(proc)
                        return
                    busy[proc.stdout.fileno()] = (proc, i)
                    ready.register(proc.stdout, selectors.EVENT_READ)
                    return

            for proc in list(self.procs):
                give(proc)
            while busy:
                events = ready.select(timeout=self.timeout)
                if not events:  # a painter hung (a GL driver, say): end the busy ones, draw their pictures here
                    for proc, _ in busy.values():
                        self._drop(proc)
                    busy.clear()
                    break
                for key, _ in events:
                    proc, i = busy.pop(key.fd)
                    ready.unregister(key.fileobj)
                    assert proc.stdout is not None
                    reply, line = None, b""
                    while reply is None:  # the reply to job i: any other line (a library's print) is passed over
                        line = proc.stdout.readline()
                        if not line:
                            break
                        try:
                            parsed = json.loads(line)
                        except ValueError:
                            continue
                        if isinstance(parsed, dict) and parsed.get("id") == i:
                            reply = parsed
                    if reply is not None and "png" in reply:
                        results[i] = Drawn(base64.b64decode(reply["png"]), float(reply["cpu_s"]))
                        self._reported[proc.pid] += float(reply["cpu_s"])
                    if not line:  # it exited: its job is drawn in the caller
                        self._drop(proc)
                        continue
                    give(proc)

    def _drop(self, proc: subprocess.Popen) -> None:
        """A painter that died, hung or cannot be written to: out of the pool, killed, its pipes closed."""
        if proc in self.procs:
            self.procs.remove(proc)
        proc.kill()
        self._reap(proc)
        for pipe in (proc.stdin, proc.stdout):
            if pipe is not None:
                try:
                    pipe.close()
                except OSError:  # a broken pipe's unflushed request
                    pass

    def close(self) -> None:
        """End every painter: the end of its input, then a kill if it has not exited in 5 s."""
        for proc in self.procs:
            try:
                assert proc.stdin is not None
                proc.stdin.close()
            except OSError:
                pass
        for proc in self.procs:
            self._reap(proc, timeout=5.0)
            if proc.stdout is not None:
                proc.stdout.close()
        self.procs = []

    def _reap(self, proc: subprocess.Popen, timeout: float | None = None) -> None:
        """Wait for a painter to exit (killed after ``timeout`` seconds) and add what its replies
        did not carry to :attr:`unreported_s`: the kernel's CPU count of the whole process (start-up,
        pictures, exit) less its replies'. ``wait4`` reaps and reads that count in one call, which
        ``Popen.wait`` (it reaps too) would lose."""
        reported = self._reported.pop(proc.pid, 0.0)
        deadline = None if timeout is None else time.monotonic() + timeout
        try:
            while True:
                pid, status, usage = os.wait4(proc.pid, os.WNOHANG if deadline is not None else 0)
                if pid:
                    break
                if deadline is not None and time.monotonic() >= deadline:
                    proc.kill()
                    deadline = None
                else:
                    time.sleep(0.005)
        except ChildProcessError:  # reaped elsewhere already: its count is gone with it
            proc.wait()
            return
        proc.returncode = os.waitstatus_to_exitcode(status)
        self.unreported_s += max(0.0, usage.ru_utime + usage.ru_stime - reported)


def main() -> int:
    """A painter: draw each request line of stdin, reply a line on stdout, exit at its end.
    Ctrl-C is the trainer's to answer (it checkpoints and stops): a painter ignores it and ends
    with its input, when the trainer exits."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    started = 0.0  # the process's clock starts with it: its start and imports count with the first curve
    # the replies get stdout's pipe to themselves: whatever else writes there (pygame's banner on
    # import, a C library) goes to stderr instead
    out = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    sys.stdout.flush()
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    sys.stdout = sys.stderr
    for line in sys.stdin.buffer:
        reply: dict = {"id": None}
        try:
            request = json.loads(line)
            reply["id"] = request["id"]
            png = draw(request["job"])
            reply.update(png=base64.b64encode(png).decode("ascii"), cpu_s=round(time.process_time() - started, 4))
        except Exception as err:  # the caller draws it again and raises it there
            reply["error"] = f"{type(err).__name__}: {err}"
        started = time.process_time()
        out.write(json.dumps(reply).encode() + b"\n")
        out.flush()
    return 0


if __name__ == "__main__":
    code = main()
    sys.stderr.flush()
    os._exit(code)  # no teardown: nothing is left to flush, and it cost more CPU than a curve
