"""A few integers that outlive a worker process: a memory-mapped file in the session directory.

Writing one is a store to shared memory (no system call), so a worker can keep its position
current at every message; the kernel keeps the page when the process is SIGKILLed, and the
restarted worker reads it back (e.g. the last vehicle sample a link published, to measure what
a restart missed; how many outputs a detector published, so that its successor does not publish
them twice).
"""

from __future__ import annotations

import mmap
import os
import struct


class StateFile:
    """``n`` signed 64-bit integers in ``path`` (created as zeros)."""

    def __init__(self, path: str, n: int) -> None:
        self._fmt = struct.Struct(f"<{n}q")
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
        try:
            if os.fstat(fd).st_size < self._fmt.size:
                os.ftruncate(fd, self._fmt.size)
            self._map = mmap.mmap(fd, self._fmt.size)
        finally:
            os.close(fd)

    def get(self) -> tuple[int, ...]:
        return self._fmt.unpack_from(self._map, 0)

    def set(self, *values: int) -> None:
        self._fmt.pack_into(self._map, 0, *values)

    def close(self) -> None:
        self._map.close()
