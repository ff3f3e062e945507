"""The one process shell every worker runs on: signals, parent death, ready handshake, status,
shutdown.

A worker (link, mocap, recorder, replay, detector, mapper, pilot) subclasses :class:`Worker` and
fills in hooks; the base owns the lifecycle that used to be copied across the shells:

1. **Parent death.** :func:`die_with_parent` asks the kernel (``prctl(PR_SET_PDEATHSIG)``) to
   SIGKILL the worker when the supervisor dies, and exits at once if it already has. A worker
   with something to save (the recorder: :attr:`Worker.parent_death_signal`) asks for SIGTERM
   instead, and :class:`OrphanWatch` gives it :data:`ORPHAN_GRACE_S` to close its file before it
   exits hard, so a SIGKILLed ``live`` leaves no worker behind after 2 s.
2. **Signals.** SIGINT/SIGTERM set a stop flag (:class:`~groundstation.runtime.session.
   StopSignals`) checked between steps; every ``step`` blocks for at most ~100 ms.
3. **Ready handshake.** :meth:`Worker.wait_ready`: the XPUB subscriber count, with a warning on
   ``log`` instead of a failure when it times out.
4. **Status.** :meth:`Worker.publish_status` once a second (and on demand): ``process``,
   ``state``, per-topic counters from :meth:`Worker.status_topics` and a ``process`` entry (pid,
   incarnation = how many times the supervisor started this worker before, uptime).
5. **Shutdown.** :meth:`Worker.teardown`, a final ``stopped`` status, sockets and context closed.

Hooks: :meth:`setup` (may return an exit code to stop at once), :meth:`step` (one bounded
iteration), :meth:`finished` (the loop ends by itself, e.g. a replay at its end),
:meth:`status_topics`, :meth:`status_text`, :meth:`teardown`. :func:`worker_main` is the entry
point every worker module's ``main`` calls.
"""

from __future__ import annotations

import argparse
import ctypes
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import zmq

from firmware_bridge.errors import BridgeError
from groundstation.bus.errors import BusTimeoutError
from groundstation.bus.pubsub import Publisher
from groundstation.config import Config
from groundstation.errors import GroundstationError
from groundstation.runtime.session import RateCounter, Session, StopSignals, publish_log

#: Environment set by the supervisor: its pid (the parent a worker dies with), the worker's
#: name, and how many times it was started before (0 on the first start).
PARENT_ENV = "GS_SUPERVISOR_PID"
NAME_ENV = "GS_WORKER_NAME"
INCARNATION_ENV = "GS_INCARNATION"
#: Nice value increment asked for a worker (negative: more CPU share than the rest of the
#: machine; needs the privilege, else the worker runs at the default priority and says so).
PRIORITY_ENV = "GS_NICE"
#: Seconds an orphaned worker gets to shut down cleanly before it exits hard.
ORPHAN_GRACE_S = 0.8
_PR_SET_PDEATHSIG = 1
_STATUS_PERIOD_NS = 1_000_000_000


def supervisor_pid() -> int | None:
    """The supervisor's pid from the environment (None when started by hand)."""
    raw = os.environ.get(PARENT_ENV)
    try:
        return int(raw) if raw else None
    except ValueError:
        return None


def incarnation() -> int:
    """How many times the supervisor started this worker before this process (0 = first)."""
    try:
        return int(os.environ.get(INCARNATION_ENV, "0"))
    except ValueError:
        return 0


def die_with_parent(sig: int = signal.SIGKILL) -> bool:
    """Have the kernel send ``sig`` to this process when its supervisor dies (Linux
    ``PR_SET_PDEATHSIG``); exit at once when the supervisor is already gone.

    Returns True when the parent-death signal is armed (False: not supervised, or not Linux).
    """
    parent = supervisor_pid()
    if parent is None:
        return False
    armed = False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        armed = libc.prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    except (OSError, AttributeError):
        armed = False
    if os.getppid() != parent:  # the supervisor died before the signal was armed
        os._exit(75)
    return armed


def request_stop(stop: Any, reason: str) -> None:
    """Set a stop flag: :class:`StopSignals` (with a reason) or a :class:`threading.Event`."""
    setter = getattr(stop, "set", None)
    if not callable(setter):
        return
    try:
        setter(reason)
    except TypeError:
        setter()


def apply_priority() -> str | None:
    """Apply ``GS_NICE`` to this process; returns a note when it could not (no privilege)."""
    raw = os.environ.get(PRIORITY_ENV)
    if not raw:
        return None
    try:
        delta = int(raw)
        os.setpriority(os.PRIO_PROCESS, 0, os.getpriority(os.PRIO_PROCESS, 0) + delta)
    except (ValueError, PermissionError, OSError) as exc:
        return f"runs at the default priority: cannot apply nice {raw} ({exc})"
    return None


def orphan_deadline(grace_s: float = ORPHAN_GRACE_S) -> None:
    """End this process ``grace_s`` from now whatever it is doing: a real-time timer whose
    SIGALRM (default action: terminate) the kernel delivers even to a worker stuck in C code
    or starved of CPU by a loaded machine. Called once a worker knows it is orphaned."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGALRM, signal.SIG_DFL)  # (Python leaves it so; make sure)
    signal.setitimer(signal.ITIMER_REAL, grace_s)


class OrphanWatch(threading.Thread):
    """Notices that the supervisor is gone (parent pid changed), sets ``stop`` and arms
    :func:`orphan_deadline` (and, as a last resort, ``os._exit`` after ``grace_s``)."""

    def __init__(self, stop: Callable[[], None], grace_s: float = ORPHAN_GRACE_S):
        super().__init__(name="orphan-watch", daemon=True)
        self.parent = supervisor_pid()
        self._stop_fn, self.grace_s = stop, grace_s
        self.orphaned = threading.Event()

    def run(self) -> None:
        if self.parent is None:
            return
        while os.getppid() == self.parent:
            time.sleep(0.05)
        self.orphaned.set()
        orphan_deadline(self.grace_s)
        self._stop_fn()
        time.sleep(self.grace_s + 0.2)
        os._exit(70)


class Worker:
    """Base of every worker process (see the module docstring).

    Parameters
    ----------
    session : Session
        Endpoints; the worker binds ``name``.
    config : Config
        The session's configuration (read once by :func:`worker_main`).
    name : str
        Process name (its endpoint in the session, ``process`` in its status).
    topics : sequence of str
        Topics this worker publishes (``status`` and ``log`` are added); empty: no publisher.
    context : zmq.Context, optional
        Shared context (tests); default a private one, terminated at shutdown.
    publisher_kwargs : dict, optional
        Extra :class:`~groundstation.bus.pubsub.Publisher` options (flow control, linger).
    """

    status_period_ns = _STATUS_PERIOD_NS
    #: Signal the kernel sends this worker when the supervisor dies: SIGKILL (nothing to save),
    #: SIGTERM for a worker that must close something first (with :class:`OrphanWatch` as the
    #: deadline).
    parent_death_signal = signal.SIGKILL

    def __init__(
        self,
        session: Session,
        config: Config,
        *,
        name: str,
        topics: Sequence[str] = (),
        context: zmq.Context | None = None,
        publisher_kwargs: dict[str, Any] | None = None,
    ) -> None:
        self.session, self.config, self.name = session, config, name
        self._own_ctx = context is None
        self.ctx = context or zmq.Context()
        names = list(dict.fromkeys([*topics, "status", "log"]))
        self.pub = Publisher(
            topics=names,
            context=self.ctx,
            **session.publisher_kwargs(name),
            **(publisher_kwargs or {}),
        )
        self.rates = RateCounter()
        self.state = "starting"
        self.exit_code = 0
        self.incarnation = incarnation()
        self.started_ns = time.monotonic_ns()
        self.setup_s: float | None = None
        self.stop: Any = None
        self.watch: OrphanWatch | None = None
        self._next_status = 0
        self._closed = False

    # -- hooks ---------------------------------------------------------------------------------
    def setup(self) -> int | None:
        """Before the loop (ready handshake, devices); return an exit code to stop at once."""
        return None

    def step(self) -> None:
        """One iteration of the loop; must block for at most ~100 ms."""
        raise NotImplementedError

    def finished(self) -> bool:
        """True when the work is done and the loop should end by itself."""
        return False

    def status_topics(self, now_ns: int) -> dict[str, Any]:
        """Per-topic counters of the status message (default: publish rates)."""
        return self.rates.snapshot(now_ns)

    def status_text(self) -> str:
        """One human line for the status message."""
        return self.state

    def teardown(self) -> None:
        """After the loop (close devices, files, threads); runs even after an exception."""

    # -- helpers -------------------------------------------------------------------------------
    def log(self, level: str, message: str, hint: str | None = None) -> None:
        """``log`` topic and stderr (never raises)."""
        publish_log(self.pub, self.name, level, message, hint)

    def wait_ready(self, n: int, topics: Sequence[str], timeout_s: float | None = None) -> bool:
        """Wait until ``n`` subscribers hold ``topics`` (XPUB handshake); False (and a warning
        on ``log``) when they did not come within ``timeout_s`` (default
        ``acquisition.subscriber_timeout_s``) or a stop was asked for meanwhile."""
        if n <= 0:
            return True
        timeout = self.config.acquisition.subscriber_timeout_s if timeout_s is None else timeout_s
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            try:
                self.pub.wait_for_subscribers(n, tuple(topics), max(0.0, min(0.2, left)))
                return True
            except BusTimeoutError as exc:
                if self.stop or left <= 0.2:
                    if not self.stop:
                        self.log("warning", f"starting anyway: {exc.message}")
                    return False

    def publish_status(self, now_ns: int | None = None) -> None:
        """Publish ``status`` now (and schedule the next one a period later)."""
        now_ns = time.monotonic_ns() if now_ns is None else now_ns
        topics = dict(self.status_topics(now_ns))
        topics["process"] = {
            "pid": os.getpid(),
            "incarnation": self.incarnation,
            "uptime_s": round((now_ns - self.started_ns) / 1e9, 3),
            "setup_s": None if self.setup_s is None else round(self.setup_s, 3),
        }
        self.pub.publish(
            "status",
            {"process": self.name, "state": self.state, "topics": topics,
             "text": self.status_text()},
        )  # fmt: skip
        self._next_status = now_ns + self.status_period_ns

    def _on_parent_signal(self, signum: int, _frame: object) -> None:
        """SIGTERM: stop; when it is the parent-death signal, with a kernel deadline."""
        request_stop(self.stop, signal.Signals(signum).name)
        parent = supervisor_pid()
        if parent is not None and os.getppid() != parent:
            orphan_deadline()

    def stopping(self) -> bool:
        """True once a stop was asked for (signal, orphaned, ``max_s``)."""
        return bool(self.stop)

    # -- lifecycle -----------------------------------------------------------------------------
    def run(self, stop: Any = None, max_s: float | None = None) -> int:
        """Run until a stop signal, :meth:`finished` or ``max_s`` seconds; returns the exit
        code."""
        self.stop = stop if stop is not None else StopSignals()
        if supervisor_pid() is not None and self.parent_death_signal != signal.SIGKILL:
            die_with_parent(self.parent_death_signal)
            if threading.current_thread() is threading.main_thread():
                signal.signal(signal.SIGTERM, self._on_parent_signal)
            self.watch = OrphanWatch(lambda: request_stop(self.stop, "ORPHANED"))
            self.watch.start()
        end = None if max_s is None else time.monotonic_ns() + int(max_s * 1e9)
        try:
            code = self.setup()
            self.setup_s = (time.monotonic_ns() - self.started_ns) / 1e9
            if code is not None:
                self.exit_code = int(code)
                return self.exit_code
            if self.incarnation > 0:
                self.log("info", f"restarted (incarnation {self.incarnation}): ready "
                         f"{self.setup_s:.2f} s after its start")  # fmt: skip
            if self.state == "starting":
                self.state = "running"
            self.publish_status()
            while not self.stop and not self.finished():
                self.step()
                now = time.monotonic_ns()
                if now >= self._next_status:
                    self.publish_status(now)
                if end is not None and now >= end:
                    break
            return self.exit_code
        finally:
            self.shutdown()

    def shutdown(self) -> None:
        """Teardown, a final status, sockets closed (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.teardown()
        finally:
            if self.state not in ("failed",):
                self.state = "stopped"
            try:
                self.publish_status()
            except Exception:  # noqa: BLE001 - best effort at shutdown
                pass
            self.pub.close()
            if self._own_ctx:
                self.ctx.term()


def worker_main(
    argv: Sequence[str] | None,
    parser: argparse.ArgumentParser,
    build: Callable[[argparse.Namespace], Worker],
) -> int:
    """Entry point of a worker module: arm the parent-death signal, parse, build, run.

    A :class:`~groundstation.errors.GroundstationError` or ``BridgeError`` while building (bad
    setting, bad URI) prints ``error:``/``hint:`` and returns 2, like the command line.
    """
    die_with_parent()
    note = apply_priority()
    if note:
        print(f"[{parser.prog.rsplit('.', 1)[-1]}] {note}", file=sys.stderr, flush=True)
    args = parser.parse_args(argv)
    stop = StopSignals()
    try:
        worker = build(args)
    except (GroundstationError, BridgeError) as exc:
        prog = parser.prog.rsplit(".", 1)[-1]
        print(f"[{prog}] error: {exc.message}", file=sys.stderr, flush=True)
        if exc.hint:
            print(f"[{prog}] hint: {exc.hint}", file=sys.stderr, flush=True)
        return 2
    return worker.run(stop, getattr(args, "max_s", None))
