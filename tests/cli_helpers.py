"""The command line, called in the test's own process.

A process per call costs its imports (torch, numba, gymnasium): ~2 s on a 2-core AMD EPYC and ~4 s
on a 2-core Intel Xeon, which made tests that only check what a command refuses or prints take
tens of seconds. ``cli`` runs the same ``main`` a process runs and returns what the process would
have: its exit code, stdout and stderr. Tests that need a real process (signals, kills, the
entry point itself) keep ``subprocess``.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import subprocess


def cli(*args, module: str = "rlbackdoors.cli", cwd=None, check: bool = False) -> subprocess.CompletedProcess:
    """``python -m MODULE ARGS`` in this process (in ``cwd`` if given): (args, exit code, stdout,
    stderr); ``check``: a non-zero exit raises CalledProcessError, as ``subprocess.run`` does."""
    main = importlib.import_module(module).main
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), contextlib.chdir(cwd) if cwd is not None else contextlib.nullcontext():
        try:
            code = main([str(a) for a in args])
        except SystemExit as stop:  # argparse's own refusals
            code = stop.code if isinstance(stop.code, int) else 2
    done = subprocess.CompletedProcess(list(args), code, out.getvalue(), err.getvalue())
    if check:
        done.check_returncode()
    return done
