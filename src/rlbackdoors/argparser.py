"""argparse with the CLI's error contract, shared by ``rlbackdoors`` and its sub-CLIs (``python -m rlbackdoors.zoo.cli``)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable


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


def report_errors(run: Callable[[], int]) -> int:
    """``run()`` with the CLI's error contract: every user-facing failure is one
    ``rlbackdoors: error: ...`` line and exit 2; an interrupted run says so and exits 130."""
    from rlbackdoors.io import UnsafeFileError
    from rlbackdoors.folder import FolderError
    from rlbackdoors.train.stop import Interrupted
    from rlbackdoors.validate import ConfigError

    try:
        return run()
    except (ConfigError, FolderError, UnsafeFileError, FileNotFoundError, ValueError, ImportError) as err:
        print(f"rlbackdoors: error: {' '.join(str(err).split()) or type(err).__name__}", file=sys.stderr)
        return 2
    except OSError as err:  # a folder that cannot be written, a full disk, ...
        where = f" {err.filename!r}" if err.filename else ""
        print(f"rlbackdoors: error: cannot use{where}: {err.strerror or err}", file=sys.stderr)
        return 2
    except Interrupted as err:
        print(f"rlbackdoors: {err}", file=sys.stderr)
        return 130
    except KeyboardInterrupt:
        print("rlbackdoors: interrupted; run the same command again to resume from the last checkpoint", file=sys.stderr)
        return 130


def sub_cli_main(prog: str, description: str, add_commands: Callable[[argparse.ArgumentParser], None], argv: list[str] | None = None) -> int:
    """A command group (``zoo``, ``detect``) run on its own (``python -m rlbackdoors.zoo.cli``),
    with the same parser and error contract as under ``rlbackdoors``."""
    parser = Parser(prog=prog, description=description)
    add_commands(parser)
    args = parser.parse_args(argv)
    return report_errors(lambda: args.func(args))
