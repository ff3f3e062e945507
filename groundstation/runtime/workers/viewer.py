"""The viewer's bus shell (the *controller*): subscribe, feed the :class:`ViewModel`, drive a sink.

The viewer is a pure subscriber of ``mesh``, ``mapper.fit``, ``observations`` and
``samples.pose``; it publishes nothing that another process waits for. ZeroMQ's I/O thread keeps
reading the sockets while a frame renders, so a slow, stalled or crashed viewer never blocks a
publisher (a PUB socket never blocks; a dead subscriber's queue is freed with its connection).

Loop, one thread (the Open3D context belongs to the thread that created it):

1. pump: receive what is queued (waiting at most until the next frame is due), ingest it;
   malformed messages are counted and reported once per topic, never raised;
2. window sink: ~``fps`` frames per second, each uploading only what changed;
   headless sink: after each new mesh (every ``every``-th), write PNG + PLY files. Headless
   pumping stops after a mesh, so each mesh received is drawn with the state it arrived in
   (the ``mesh`` topic's small high-water mark bounds any backlog);
3. sink failures are logged to stderr; a window that fails ``max_sink_failures`` times in a row
   (or is closed by the user) ends the viewer alone, with exit status 1 (0 when closed).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from groundstation.viewer.scene import ViewerInputError, ViewModel, ViewSettings

VIEW_TOPICS = ("mesh", "mapper.fit", "observations", "samples.pose", "contact.event")


class _Stop(Protocol):
    def __bool__(self) -> bool: ...


def _stderr(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


class ViewerProcess:
    """Subscriber -> :class:`ViewModel` -> sink loop (see the module docstring).

    Parameters
    ----------
    endpoints : sequence of str
        Publisher endpoints to connect to (every publisher of the session, both policies).
    sink : WindowSink or HeadlessSink
        ``step(scene) -> bool`` (window) or ``write(scene) -> list`` (headless).
    settings : ViewSettings
    every : int
        Headless: write files for every ``every``-th mesh (the first one always).
    fps : float
        Window frame rate.
    max_snapshots : int, optional
        Headless: stop after this many snapshot sets (None: run until stopped).
    settle_s : float
        Headless: after a mesh, wait up to this long for its ``mapper.fit`` and the points
        that fit lists (they travel on other sockets) so the files show one consistent fit.
    stop : object with ``__bool__``
        Stop flag checked every loop (e.g. ``StopSignals``).
    log : callable
        One-line messages (default stderr).
    server_public_key : bytes, optional
        CURVE public key of keyed publishers.
    context : zmq.Context, optional
    """

    def __init__(
        self,
        endpoints: Sequence[str],
        sink: Any,
        *,
        settings: ViewSettings | None = None,
        every: int = 1,
        fps: float = 25.0,
        max_snapshots: int | None = None,
        stop: _Stop | None = None,
        log: Callable[[str], None] = _stderr,
        server_public_key: bytes | None = None,
        context: Any = None,
        clock: Callable[[], int] = time.monotonic_ns,
        max_sink_failures: int = 5,
        settle_s: float = 2.0,
    ):
        from groundstation.bus.pubsub import Subscriber

        self.headless = hasattr(sink, "write")
        self.sink = sink
        self.model = ViewModel(settings)
        self.every = max(1, int(every))
        self.frame_ns = int(1e9 / max(1.0, float(fps)))
        self.max_snapshots = max_snapshots
        self.stop: Any = stop if stop is not None else False
        self.log = log
        self.clock = clock
        self.max_sink_failures = max_sink_failures
        self.settle_ns = int(max(0.0, float(settle_s)) * 1e9)
        self._pending_since: int | None = None
        self.sub = Subscriber(
            list(endpoints), VIEW_TOPICS, server_public_key=server_public_key, context=context
        )
        self.messages = 0
        self.bad_messages = 0
        self.snapshots = 0
        self.sink_failures = 0
        self._reported: set[str] = set()
        self._seen_mesh_version = 0
        self._written_mesh_version = 0
        self._closed = False
        self._next_frame = clock()
        self.status = 0

    # -- bus -----------------------------------------------------------------------------------
    def pump(self, timeout_ms: int, budget: int = 2000) -> int:
        """Receive and ingest queued messages (the first wait up to ``timeout_ms``).

        Returns the number ingested; headless mode returns right after a mesh.
        """
        n = 0
        wait = max(0, int(timeout_ms))
        while n < budget:
            env = self.sub.recv(timeout_ms=wait)
            if env is None:
                break
            wait = 0
            n += 1
            self.messages += 1
            try:
                self.model.ingest_message(
                    env.topic,
                    env.payload,
                    env.arrays,
                    source_ns=env.header.source_ns,
                    recv_ns=env.header.recv_ns,
                )
            except Exception as exc:  # noqa: BLE001 - bad input is skipped and counted
                if not isinstance(exc, ViewerInputError):
                    self.model.rejected[env.topic] = self.model.rejected.get(env.topic, 0) + 1
                self.bad_messages += 1
                if env.topic not in self._reported:
                    self._reported.add(env.topic)
                    self.log(f"viewer: skipping bad {env.topic} message ({exc}); counting more")
                continue
            if self.headless and env.topic == "mesh":
                break
        return n

    # -- sinks ---------------------------------------------------------------------------------
    def _due_for_files(self) -> bool:
        v = self.model.mesh_version
        if v == self._seen_mesh_version:
            return False
        self._seen_mesh_version = v
        return (self.model.meshes_received - 1) % self.every == 0

    @property
    def settling(self) -> bool:
        """Headless: a due mesh waits for its fit and points (see ``settle_s``)."""
        return self._pending_since is not None

    def _settled(self) -> bool:
        """A due mesh may be written: its fit and points are in, or ``settle_s`` has passed."""
        mesh = self.model.mesh
        if mesh is None or self._pending_since is None:
            return True
        if self.model.fit_covers(mesh.fit_index):
            return True
        return self.clock() - self._pending_since >= self.settle_ns

    def _write(self) -> None:
        self._pending_since = None
        try:
            self.sink.write(self.model.scene(self.clock()))
            self.snapshots += 1
            self._written_mesh_version = self.model.mesh_version
            self._seen_mesh_version = self.model.mesh_version
            self.sink_failures = 0
        except Exception as exc:  # noqa: BLE001 - a sink failure must not end the loop
            self.sink_failures += 1
            self.log(f"viewer: could not write files for mesh {self.model.mesh}: {exc!r}")

    def _frame(self) -> bool:
        try:
            alive = bool(self.sink.step(self.model.scene(self.clock())))
            self.sink_failures = 0
            return alive
        except Exception as exc:  # noqa: BLE001 - counted; too many in a row end the viewer
            self.sink_failures += 1
            self.log(f"viewer: frame failed ({exc!r}) [{self.sink_failures} in a row]")
            return True

    def step(self) -> bool:
        """One loop iteration (pump, then files or a frame); False when the loop should end."""
        if self.headless:
            self.pump(timeout_ms=20 if self._pending_since is not None else 100)
            if self._pending_since is None and self._due_for_files():
                self._pending_since = self.clock()
            if self._pending_since is not None and self._settled():
                self._write()
                if self.max_snapshots and self.snapshots >= self.max_snapshots:
                    return False
            return True
        wait_ms = max(0, (self._next_frame - self.clock()) // 1_000_000)
        self.pump(timeout_ms=wait_ms)
        if self.clock() >= self._next_frame:
            self._next_frame = max(self._next_frame + self.frame_ns, self.clock())
            if not self._frame():
                self.log("viewer: window closed")
                return False
        if self.sink_failures >= self.max_sink_failures:
            self.log(f"viewer: giving up after {self.sink_failures} failed frames")
            self.status = 1
            return False
        return True

    def flush(self) -> None:
        """Headless: write the latest mesh if ``every`` skipped it (called when stopping)."""
        if (
            self.headless
            and self.model.mesh is not None
            and self._written_mesh_version != self.model.mesh_version
            and not (self.max_snapshots and self.snapshots >= self.max_snapshots)
        ):
            self._write()

    def run(self) -> int:
        """Loop until stopped, the window is closed or ``max_snapshots`` is reached, then
        :meth:`flush` and :meth:`close`.

        Returns
        -------
        int
            0 on a clean stop, 1 when the sink kept failing.
        """
        try:
            while not self.stop and self.step():
                pass
            self.flush()
        finally:
            self.close()
        return self.status

    def summary(self) -> str:
        """One line of counters for the end of a run."""
        gaps = {k: v for k, v in self.sub.gaps.items() if v}
        m = self.model
        return (
            f"viewer: {self.messages} messages ({self.bad_messages} bad), "
            f"{m.meshes_received} meshes, {self.snapshots} snapshot sets, "
            f"{m.observations_total} observations ({m.observations_dropped} not kept), "
            f"gaps {gaps or 0}"
        )

    def close(self) -> None:
        """Close the sink and the subscriber (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.sink.close()
        except Exception as exc:  # noqa: BLE001 - shutting down anyway
            self.log(f"viewer: closing the sink failed: {exc!r}")
        self.sub.close()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the viewer as a session worker: ``groundstation view`` (same options)
    under the shared lifecycle (parent-death signal, orphan watch)."""
    import os
    import signal

    from groundstation.cli import main as cli_main
    from groundstation.runtime.worker import OrphanWatch, die_with_parent, supervisor_pid

    die_with_parent()
    if supervisor_pid() is not None:
        OrphanWatch(lambda: os.kill(os.getpid(), signal.SIGTERM)).start()
    return cli_main(["view", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
