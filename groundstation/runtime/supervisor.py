"""Start worker processes, notice when one dies, restart it, and shut everything down cleanly.

The supervisor owns no device and no socket: each worker is a separate OS process (its own
interpreter, so a crash, a hung BLAS call or a leaked ZeroMQ context stays inside it). Workers
are started with :mod:`subprocess`, watched with ``Popen.poll`` from :meth:`Supervisor.poll`
(the caller's loop decides how often), restarted with a bounded backoff, and stopped in order
SIGINT → SIGTERM → SIGKILL with timeouts.

Time is passed in by the caller (``now`` in seconds, monotonic), so the restart policy is testable
without sleeping.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
import time
from collections.abc import Sequence


@dataclasses.dataclass(frozen=True)
class WorkerSpec:
    """How to run one worker.

    Attributes
    ----------
    name : str
        Short name shown in the status line ("link", "mocap", "mapper", ...).
    argv : tuple of str
        Command line; ``python -m groundstation.<...>`` style commands are usual.
    restart : bool
        Restart after an unexpected exit.
    max_restarts : int
        Give up (and report) after this many restarts within ``restart_window_s``.
    restart_window_s : float
        Window over which restarts are counted.
    backoff_s : float
        Delay before the first restart; doubles on each further restart in the window (max 5 s).
    env : tuple of (str, str)
        Extra environment variables (e.g. ``OPENBLAS_NUM_THREADS=1`` for the mapper).
    """

    name: str
    argv: tuple[str, ...]
    restart: bool = True
    max_restarts: int = 5
    restart_window_s: float = 60.0
    backoff_s: float = 0.2
    env: tuple[tuple[str, str], ...] = ()


@dataclasses.dataclass(frozen=True)
class WorkerEvent:
    """Something that happened to a worker: kind is started|exited|restarting|gave_up|stopped."""

    name: str
    kind: str
    returncode: int | None = None
    detail: str = ""


@dataclasses.dataclass
class _Worker:
    spec: WorkerSpec
    proc: subprocess.Popen | None = None
    restarts: list[float] = dataclasses.field(default_factory=list)
    restart_at: float | None = None
    gave_up: bool = False


def python_module(module: str, *args: str) -> tuple[str, ...]:
    """argv that runs ``python -m module args...`` with this interpreter."""
    return (sys.executable, "-m", module, *args)


class Supervisor:
    """Run and watch a set of workers.

    Parameters
    ----------
    specs : sequence of WorkerSpec
        Workers, started in this order and stopped in reverse order.
    stdout, stderr : file or None
        Where worker output goes (inherited by default, so their errors reach the terminal).
    """

    def __init__(self, specs: Sequence[WorkerSpec], stdout=None, stderr=None):
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise ValueError(f"worker names must be unique, got {names}")
        self._workers = {s.name: _Worker(s) for s in specs}
        self._stdout = stdout
        self._stderr = stderr
        self._stopping = False

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> list[WorkerEvent]:
        return [self._spawn(w) for w in self._workers.values()]

    def _spawn(self, w: _Worker) -> WorkerEvent:
        env = dict(os.environ)
        env.update(dict(w.spec.env))
        w.proc = subprocess.Popen(
            list(w.spec.argv),
            env=env,
            stdout=self._stdout,
            stderr=self._stderr,
            stdin=subprocess.DEVNULL,
            start_new_session=True,  # Ctrl-C in the terminal reaches the supervisor only
        )
        w.restart_at = None
        return WorkerEvent(w.spec.name, "started", detail=f"pid {w.proc.pid}")

    def poll(self, now: float | None = None) -> list[WorkerEvent]:
        """Check every worker once; restart the ones whose backoff has elapsed."""
        now = time.monotonic() if now is None else now
        events: list[WorkerEvent] = []
        for w in self._workers.values():
            if w.proc is not None and w.restart_at is None and not w.gave_up:
                rc = w.proc.poll()
                if rc is None:
                    continue
                events.append(WorkerEvent(w.spec.name, "exited", rc))
                if self._stopping or not w.spec.restart or rc == 0:
                    w.gave_up = True
                    continue
                w.restarts = [t for t in w.restarts if now - t < w.spec.restart_window_s]
                if len(w.restarts) >= w.spec.max_restarts:
                    w.gave_up = True
                    events.append(
                        WorkerEvent(
                            w.spec.name,
                            "gave_up",
                            rc,
                            f"{len(w.restarts)} restarts in {w.spec.restart_window_s:.0f} s",
                        )
                    )
                    continue
                delay = min(5.0, w.spec.backoff_s * (2 ** len(w.restarts)))
                w.restarts.append(now)
                w.restart_at = now + delay
                events.append(WorkerEvent(w.spec.name, "restarting", rc, f"in {delay:.1f} s"))
            elif w.restart_at is not None and now >= w.restart_at and not self._stopping:
                events.append(self._spawn(w))
        return events

    def alive(self) -> dict[str, bool]:
        return {n: w.proc is not None and w.proc.poll() is None for n, w in self._workers.items()}

    def pid(self, name: str) -> int | None:
        w = self._workers[name]
        return None if w.proc is None else w.proc.pid

    def stop(self, timeout_s: float = 5.0) -> list[WorkerEvent]:
        """Stop workers in reverse start order: SIGINT, then SIGTERM, then SIGKILL."""
        self._stopping = True
        events: list[WorkerEvent] = []
        for w in reversed(list(self._workers.values())):
            p = w.proc
            if p is None or p.poll() is not None:
                continue
            for sig, wait in (
                (signal.SIGINT, timeout_s),
                (signal.SIGTERM, 2.0),
                (signal.SIGKILL, 2.0),
            ):
                try:
                    p.send_signal(sig)
                except ProcessLookupError:
                    break
                try:
                    p.wait(wait)
                    break
                except subprocess.TimeoutExpired:
                    continue
            events.append(WorkerEvent(w.spec.name, "stopped", p.returncode, signal_name(p)))
        return events


def signal_name(p: subprocess.Popen) -> str:
    rc = p.returncode
    if rc is not None and rc < 0:
        try:
            return signal.Signals(-rc).name
        except ValueError:
            return f"signal {-rc}"
    return f"exit {rc}"
