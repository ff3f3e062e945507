"""Start worker processes, notice when one dies, restart it, and shut everything down cleanly.

The supervisor owns no device and no socket: each worker is a separate OS process (its own
interpreter, so a crash, a hung BLAS call or a leaked ZeroMQ context stays inside it). Workers
are started with :mod:`subprocess`, watched with ``Popen.poll`` from :meth:`Supervisor.poll`
(the caller's loop decides how often), restarted with a bounded backoff, and stopped in order
SIGINT -> SIGTERM -> SIGKILL with timeouts.

No orphans: every worker runs in **one process group owned by the supervisor** (the first
worker leads it; later workers and restarts join it), apart from the terminal's group so that
Ctrl-C reaches the supervisor alone and it stops the workers in order. Each worker also arms a
parent-death signal (:func:`~groundstation.runtime.worker.die_with_parent`, given the
supervisor's pid in ``GS_SUPERVISOR_PID``), so a SIGKILLed supervisor takes its workers with
it; :meth:`Supervisor.stop` ends by killing whatever is left of the group.

Fast restarts: a worker spec marked ``warm`` keeps a spare interpreter
(:mod:`~groundstation.runtime.spare`) with its imports done; when the worker dies the spare
takes its place at once (no interpreter start), and a new spare is started later.

Time is passed in by the caller (``now`` in seconds, monotonic), so the restart policy is testable
without sleeping.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Sequence

from groundstation.runtime.worker import INCARNATION_ENV, NAME_ENV, PARENT_ENV, PRIORITY_ENV

SPARE_MODULE = "groundstation.runtime.spare"


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
        Delay before the second restart in the window; doubles on each further restart (max
        5 s). The first restart in the window is immediate.
    env : tuple of (str, str)
        Extra environment variables (e.g. ``OPENBLAS_NUM_THREADS=1`` for the mapper).
    warm : bool
        Keep a warm spare for fast restarts (``argv`` must be ``python -m MODULE ...``).
    group : str
        Workers of one non-empty group are stopped together (e.g. an active/standby pair:
        stopping one first would hand its work to the other).
    stop_timeout_s : float, optional
        How long to wait after SIGINT before SIGTERM (default: :meth:`Supervisor.stop`'s);
        a recorder gets longer to write what it still holds.
    nice : int
        Priority change the worker asks for at start (``GS_NICE``; negative = more CPU share;
        without the privilege it runs at the default priority and says so).
    """

    name: str
    argv: tuple[str, ...]
    restart: bool = True
    max_restarts: int = 5
    restart_window_s: float = 60.0
    backoff_s: float = 0.2
    env: tuple[tuple[str, str], ...] = ()
    warm: bool = False
    group: str = ""
    stop_timeout_s: float | None = None
    nice: int = 0

    @property
    def module(self) -> str | None:
        """The module of a ``python -m MODULE`` command line, else None."""
        a = self.argv
        return a[2] if len(a) >= 3 and a[1] == "-m" else None


@dataclasses.dataclass(frozen=True)
class WorkerEvent:
    """Something that happened to a worker: kind is started|exited|restarting|gave_up|stopped.

    ``restarts`` counts the worker's restarts so far (over the whole session)."""

    name: str
    kind: str
    returncode: int | None = None
    detail: str = ""
    restarts: int = 0


@dataclasses.dataclass
class _Worker:
    spec: WorkerSpec
    proc: subprocess.Popen | None = None
    restarts: list[float] = dataclasses.field(default_factory=list)
    restart_at: float | None = None
    gave_up: bool = False
    starts: int = 0
    spare: subprocess.Popen | None = None
    spare_at: float | None = None


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
    spare_delay_s : float
        A warm spare is started this long after the worker it stands in for (start-up first).
    spare_stagger_s : float
        At :meth:`start`, the spares follow one another at this interval (in start order)
        instead of all importing at once while the session is still starting: in two of about
        twelve live soaks on a 2-core machine the mapper's fitting child, at the spares'
        priority, was ready only 7-8 s after start (0.8-2 s otherwise).
    """

    def __init__(self, specs: Sequence[WorkerSpec], stdout=None, stderr=None,
                 spare_delay_s: float = 3.0, spare_stagger_s: float = 1.5):  # fmt: skip
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise ValueError(f"worker names must be unique, got {names}")
        self._workers = {s.name: _Worker(s) for s in specs}
        self._stdout = stdout
        self._stderr = stderr
        self._stopping = False
        self.spare_delay_s, self.spare_stagger_s = spare_delay_s, spare_stagger_s
        self.pgid: int | None = None
        self._lock = threading.RLock()  # poll() may run in a watcher thread (cli/live.py)

    # -- processes -----------------------------------------------------------------------------
    def _env(self, w: _Worker) -> dict[str, str]:
        env = dict(os.environ)
        env.update(dict(w.spec.env))
        env[PARENT_ENV] = str(os.getpid())
        env[NAME_ENV] = w.spec.name
        env[INCARNATION_ENV] = str(w.starts)
        if w.spec.nice:
            env[PRIORITY_ENV] = str(w.spec.nice)
        return env

    def _popen(self, argv: Sequence[str], env: dict[str, str], stdin) -> subprocess.Popen:
        """Start a process in the supervisor's group (created by the first one)."""
        kw = dict(env=env, stdout=self._stdout, stderr=self._stderr, stdin=stdin)
        if self.pgid is not None:
            try:
                return subprocess.Popen(list(argv), process_group=self.pgid, **kw)
            except (PermissionError, ProcessLookupError, OSError):
                self.pgid = None  # every member died: the group is gone, lead a new one
        proc = subprocess.Popen(list(argv), process_group=0, **kw)
        self.pgid = proc.pid
        return proc

    def _spawn(self, w: _Worker, spare_after_s: float = 0.0) -> WorkerEvent:
        spare, w.spare = w.spare, None
        how = ""
        if spare is not None and spare.poll() is None:
            order = {"argv": list(w.spec.argv[3:]),
                     "env": {INCARNATION_ENV: str(w.starts)}}  # fmt: skip
            try:
                spare.stdin.write((json.dumps(order) + "\n").encode())
                spare.stdin.close()
                w.proc, how = spare, ", warm spare"
            except (BrokenPipeError, OSError):
                w.proc = None
        else:
            w.proc = None
        if w.proc is None:
            w.proc = self._popen(w.spec.argv, self._env(w), subprocess.DEVNULL)
        w.starts += 1
        w.restart_at = None
        if w.spec.warm and w.spec.module:
            w.spare_at = time.monotonic() + self.spare_delay_s + spare_after_s
        return WorkerEvent(w.spec.name, "started", detail=f"pid {w.proc.pid}{how}",
                           restarts=w.starts - 1)  # fmt: skip

    def _spawn_spare(self, w: _Worker) -> None:
        w.spare_at = None
        argv = (sys.executable, "-m", SPARE_MODULE, str(w.spec.module))
        w.spare = self._popen(argv, self._env(w), subprocess.PIPE)

    # -- lifecycle ---------------------------------------------------------------------------
    def start(self) -> list[WorkerEvent]:
        with self._lock:
            warm = [w.spec.warm and w.spec.module is not None for w in self._workers.values()]
            k = [sum(warm[:i]) for i in range(len(warm))]  # spares before this one
            return [self._spawn(w, k[i] * self.spare_stagger_s)
                    for i, w in enumerate(self._workers.values())]  # fmt: skip

    def poll(self, now: float | None = None) -> list[WorkerEvent]:
        """Check every worker once; restart the ones whose backoff has elapsed.

        Note: Linux sends a worker its parent-death signal when the *thread* that started it
        ends; call this from a thread that outlives the workers."""
        with self._lock:
            return self._poll(time.monotonic() if now is None else now)

    def _poll(self, now: float) -> list[WorkerEvent]:
        events: list[WorkerEvent] = []
        for w in self._workers.values():
            if w.proc is not None and w.restart_at is None and not w.gave_up:
                rc = w.proc.poll()
                if rc is None:
                    self._tend_spare(w, now)
                    continue
                n = w.starts - 1
                events.append(WorkerEvent(w.spec.name, "exited", rc, restarts=n))
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
                            restarts=n,
                        )
                    )
                    continue
                k = len(w.restarts)
                delay = 0.0 if k == 0 else min(5.0, w.spec.backoff_s * (2 ** (k - 1)))
                w.restarts.append(now)
                w.restart_at = now + delay
                events.append(
                    WorkerEvent(w.spec.name, "restarting", rc, f"in {delay:.1f} s", restarts=n)
                )
            if w.restart_at is not None and now >= w.restart_at and not self._stopping:
                events.append(self._spawn(w))
        return events

    def _tend_spare(self, w: _Worker, now: float) -> None:
        if self._stopping or not w.spec.warm or w.spec.module is None:
            return
        if w.spare is not None and w.spare.poll() is not None:  # a spare died: replace it
            w.spare = None
            w.spare_at = now + self.spare_delay_s
        if w.spare is None and w.spare_at is not None and now >= w.spare_at:
            self._spawn_spare(w)

    def alive(self) -> dict[str, bool]:
        return {n: w.proc is not None and w.proc.poll() is None for n, w in self._workers.items()}

    def pid(self, name: str) -> int | None:
        w = self._workers[name]
        return None if w.proc is None else w.proc.pid

    def restarts(self) -> dict[str, int]:
        """Restarts per worker so far."""
        return {n: max(0, w.starts - 1) for n, w in self._workers.items()}

    def pids(self) -> list[int]:
        """Pids of every process the supervisor started that may still run (workers, spares)."""
        out = []
        for w in self._workers.values():
            for p in (w.proc, w.spare):
                if p is not None and p.poll() is None:
                    out.append(p.pid)
        return out

    def stop(self, timeout_s: float = 5.0) -> list[WorkerEvent]:
        """Stop workers in reverse start order: SIGINT, then SIGTERM, then SIGKILL; then kill
        whatever is left in the group (spares, a worker's own children)."""
        with self._lock:
            self._stopping = True
        return self._stop(timeout_s)

    def _stop(self, timeout_s: float) -> list[WorkerEvent]:
        events: list[WorkerEvent] = []
        for w in self._workers.values():
            if w.spare is not None:
                _kill(w.spare)
                w.spare = None
        batches: list[list[_Worker]] = []
        for w in reversed(list(self._workers.values())):
            if batches and w.spec.group and batches[-1][0].spec.group == w.spec.group:
                batches[-1].append(w)
            else:
                batches.append([w])
        for batch in batches:
            procs = [(w, w.proc) for w in batch if w.proc is not None and w.proc.poll() is None]
            first = max((w.spec.stop_timeout_s or timeout_s for w in batch), default=timeout_s)
            for sig, wait in (
                (signal.SIGINT, first),
                (signal.SIGTERM, 2.0),
                (signal.SIGKILL, 2.0),
            ):
                live = [(w, p) for w, p in procs if p.poll() is None]
                if not live:
                    break
                for _, p in live:
                    try:
                        p.send_signal(sig)
                    except ProcessLookupError:
                        pass
                deadline = time.monotonic() + wait
                for _, p in live:
                    try:
                        p.wait(max(0.0, deadline - time.monotonic()))
                    except subprocess.TimeoutExpired:
                        pass
            for w, p in procs:
                events.append(
                    WorkerEvent(
                        w.spec.name,
                        "stopped",
                        p.returncode,
                        signal_name(p),
                        restarts=max(0, w.starts - 1),
                    )  # fmt: skip
                )
        if self.pgid is not None:
            try:
                os.killpg(self.pgid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass
        return events


def _kill(p: subprocess.Popen) -> None:
    try:
        p.kill()
        p.wait(2.0)
    except (ProcessLookupError, subprocess.TimeoutExpired):
        pass
    if p.stdin is not None:
        try:
            p.stdin.close()
        except OSError:
            pass


def signal_name(p: subprocess.Popen) -> str:
    rc = p.returncode
    if rc is not None and rc < 0:
        try:
            return signal.Signals(-rc).name
        except ValueError:
            return f"signal {-rc}"
    return f"exit {rc}"
