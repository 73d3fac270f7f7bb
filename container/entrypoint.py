#!/usr/bin/env python3
"""TrojAI's entry point name for the container (detector.def's runscript): ``rlbackdoors.detect.entrypoint``.

Detector files of one's own (``container/build.sh ... --plugin FILE``) lie in ``plugins/`` beside
this file in the image (``/plugins``) and are loaded first, so that a detector they register can
be read back from the learned parameters; outside an image there is no such folder."""

import sys
from pathlib import Path

from rlbackdoors.detect.entrypoint import main

PLUGINS = Path(__file__).resolve().parent / "plugins"


def load_plugins() -> int:
    from rlbackdoors.detect.api import load_plugin
    from rlbackdoors.detect.handle import DetectError

    for file in sorted(PLUGINS.glob("*.py")) if PLUGINS.is_dir() else []:
        try:
            load_plugin(file)
        except DetectError as err:
            print(f"rlbackdoors: error: {err}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    sys.exit(load_plugins() or main())
