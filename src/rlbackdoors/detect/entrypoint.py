"""TrojAI's container entry point: ``entrypoint.py infer|configure --...`` as the harness calls it.

The harness runs ``singularity run --nv detector.sif infer --model_filepath=... ...`` (or, in its
legacy mode, the infer flags with no sub-command); ``container/detector.def``'s runscript hands
every argument to ``container/entrypoint.py``, which calls :func:`main`. The arguments are
TrojAI's (``rlbackdoors detect infer|configure``, :mod:`rlbackdoors.detect.trojai`), in either
``--flag value`` or ``--flag=value`` form; errors are one ``rlbackdoors: error:`` line, exit 2.
"""

from __future__ import annotations

import sys

MODES = ("infer", "configure")


def main(argv: list[str] | None = None) -> int:
    from rlbackdoors.detect.cli import main as detect_main

    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] not in (*MODES, "-h", "--help"):
        args = ["infer", *args]  # TrojAI's legacy mode: no sub-command is inference
    return detect_main(args)


if __name__ == "__main__":
    sys.exit(main())
