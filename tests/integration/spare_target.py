"""A tiny worker module for the supervisor's warm-spare test: appends ``pid:incarnation`` to
the file given, then sleeps until stopped."""

from __future__ import annotations

import os
import sys
import time


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    with open(argv[0], "a") as fh:
        fh.write(f"{os.getpid()}:{os.environ.get('GS_INCARNATION')}\n")
    time.sleep(60)
    return 0


if __name__ == "__main__":
    sys.exit(main())
