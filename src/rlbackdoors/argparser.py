"""argparse with the CLI's error contract, shared by ``rlbackdoors`` and ``python -m rlbackdoors.safety_cli``."""

from __future__ import annotations

import argparse
import sys


class Parser(argparse.ArgumentParser):
    """argparse with the CLI's error contract: one ``rlbackdoors: error: ...`` line, exit 2,
    and no abbreviated flags (``--max-frame`` is an error, not ``--max-frames``)."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        command = self.prog.split(" ", 1)[1] if " " in self.prog else ""
        hint = f" (see: rlbackdoors {command + ' ' if command else ''}--help)"
        print(f"rlbackdoors: error: {command + ': ' if command else ''}{message}{hint}", file=sys.stderr)
        raise SystemExit(2)
