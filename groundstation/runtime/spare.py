"""A warm spare: a worker interpreter with its imports done, waiting to replace a dead worker.

``python -m groundstation.runtime.spare MODULE`` imports ``MODULE`` (numpy, ZeroMQ, the stage's
core: most of a worker's start-up time, seconds on a loaded machine), arms the parent-death
signal and blocks reading one JSON line from stdin: ``{"argv": [...], "env": {...}}``. The
supervisor writes that line when the worker it stands in for dies; the spare then sets the
environment and runs ``MODULE.main(argv)``, so a restart costs milliseconds instead of an
interpreter start. End of input without a line (the supervisor stopping) exits 0.
"""

from __future__ import annotations

import importlib
import json
import os
import sys


def main() -> int:
    if len(sys.argv) != 2:
        print("usage: python -m groundstation.runtime.spare MODULE", file=sys.stderr)
        return 2
    from groundstation.runtime.worker import die_with_parent

    die_with_parent()
    module = importlib.import_module(sys.argv[1])
    line = sys.stdin.readline()
    if not line.strip():
        return 0
    order = json.loads(line)
    os.environ.update({str(k): str(v) for k, v in order.get("env", {}).items()})
    argv = [str(a) for a in order.get("argv", [])]
    sys.argv = [module.__file__ or sys.argv[1], *argv]
    return int(module.main(argv) or 0)


if __name__ == "__main__":
    sys.exit(main())
