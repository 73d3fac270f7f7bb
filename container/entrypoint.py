#!/usr/bin/env python3
"""TrojAI's entry point name for the container (detector.def's runscript): ``rlbackdoors.detect.entrypoint``."""

import sys

from rlbackdoors.detect.entrypoint import main

if __name__ == "__main__":
    sys.exit(main())
