"""The Rerun viewer's bus shell: subscribe and feed a ``viewer.rerun_sink.RerunLogger``.

Started by ``groundstation view --viewer rerun`` (and so by ``live --viewer rerun``, whose viewer
worker is that command). A pure subscriber like the Open3D viewer: it publishes nothing anyone
waits for, so a slow browser or a dead Rerun server never blocks the pipeline; malformed
messages are counted and skipped by the logger. The signal needs the IMU and attitude samples
(200 Hz each), so this subscribes to them too; transforms are thinned to ``pose_rate_hz``.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

RERUN_TOPICS = (
    "mesh", "mapper.fit", "observations", "samples.pose", "samples.imu", "samples.attitude",
    "contact.event", "log",
)  # fmt: skip


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


class RerunViewerProcess:
    """Subscriber -> RerunLogger loop.

    Parameters
    ----------
    endpoints : sequence of str
        Publisher endpoints of the session.
    logger : RerunLogger
    stop : object with ``__bool__``
        Checked every loop (e.g. ``StopSignals``).
    flush_every_s : float
        Send buffered signal samples at least this often (wall clock of the loop).
    """

    def __init__(
        self,
        endpoints: Sequence[str],
        logger: Any,
        *,
        stop: Any = False,
        server_public_key: bytes | None = None,
        log: Callable[[str], None] = _stderr,
        flush_every_s: float = 0.25,
    ) -> None:
        from groundstation.bus.pubsub import Subscriber

        self.logger = logger
        self.stop = stop
        self.log = log
        self.flush_every_s = flush_every_s
        self.sub = Subscriber(list(endpoints), RERUN_TOPICS, server_public_key=server_public_key)

    def run(self, max_s: float | None = None) -> int:
        """Loop until stopped (or ``max_s``); 0 on a clean stop."""
        end = None if max_s is None else time.monotonic() + max_s
        next_flush = time.monotonic()
        try:
            while not self.stop and (end is None or time.monotonic() < end):
                env = self.sub.recv(100)
                if env is not None:
                    self.logger.ingest_envelope(env)
                if time.monotonic() >= next_flush:
                    self.logger.flush_signal()
                    next_flush = time.monotonic() + self.flush_every_s
            self.logger.finish()
        finally:
            self.sub.close()
        return 0

    def summary(self) -> str:
        gaps = {k: v for k, v in self.sub.gaps.items() if v}
        return (
            f"rerun viewer: {self.logger.messages} messages ({self.logger.bad} bad), "
            f"gaps {gaps or 0}"
        )
