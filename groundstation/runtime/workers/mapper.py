"""The mapper process: observations in, refits in a child process, meshes out; never stalls.

Command line (started by the supervisor, with ``OPENBLAS_NUM_THREADS=1`` in its environment)::

    python -m groundstation.runtime.workers.mapper --session ID [--session-root /tmp]
        --publishers detector[,...]            # who publishes observations
        [--name mapper] [--recording SESSION.mcap] [--wait-subscribers 0]

Two processes, so that the shell always answers:

- **The shell** (this process, one thread) owns the SUB socket (``observations`` and ``log`` of
  every other publisher), keeps every observation received (by id), publishes, and answers
  stop signals within a loop turn (<= 50 ms): on SIGINT/SIGTERM it kills the fitting child at
  once, whatever the fit is doing (a fit is pure computation; nothing is lost by killing it).
- **The fitting child** (``runtime/workers/fitchild.py``, its own process; parent-death signal
  SIGKILL, one BLAS thread)
  holds :class:`~groundstation.mapping.mapper.Mapper`: it adds the observations the shell sends,
  asks ``due()`` on the data clock and refits with *all* observations received so far, then
  reports the fit and goes idle. The shell sends new observations only while the child is idle,
  in one batch with everything that arrived during the fit: under CPU starvation refits are
  skipped, never queued, and each mesh is the newest fit's (skip ahead). ``lag_s`` = newest data
  time received minus the fit's data time. A child that dies is started again with every
  observation held.

After each refit the shell publishes ``mesh`` (when the fit produced a new one), ``mapper.fit``
(ids, u, flags, ``reliable``, ``reasons``, ``data_ns``, ``lag_s``) and ``status`` (state
``fitting`` with the fit's running time, ``idle``, ``unreliable``). The child reports a fit as
plain data (:func:`fit_message`: numbers, strings and numpy arrays), never as the mapping core's
own objects: unpickling a ``FitResult`` made the shell import the whole mapping core (scipy,
scikit-image) on the first fit, which on a loaded machine held that first mesh back 0.8-1.2 s
after the fit had finished.

Restart (``--recording PATH``): a restarted mapper first reads every observation the session's
recording holds. From then on it repairs holes: when an observation arrives whose sequence
number skips some on its detector stream (published while the mapper was down or starting, not
yet on disk when it read the recording), the missing ones are read from the recording as soon
as the recorder has written them (it closes a chunk at least once a second), so the rebuilt map
holds every observation published while it was down (ids seen twice are ignored). What the
recording does not hold within ``REPAIR_WAIT_S`` is counted as lost (status ``catchup.lost``).

When the detector's ``log`` "detector finished ..." arrives (end of a replay), the child refits
once more on everything and the shell publishes ``log`` "mapper finished: fit N".
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import socket
import subprocess
import sys
import time
import warnings
from collections.abc import Sequence
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
import zmq

from groundstation.bus.pubsub import Subscriber
from groundstation.config import Config, to_toml
from groundstation.contact.detector import Observation
from groundstation.contact.stage import observation_from_envelope
from groundstation.runtime.catchup import GapPlan, catch_up, read_recorded
from groundstation.runtime.session import (
    Session,
    add_session_arguments,
    session_from_args,
    worker_config,
)
from groundstation.runtime.worker import Worker, worker_main
from groundstation.runtime.workers.detector import DETECTOR_FINISHED

#: The fitting child's program (``runtime/workers/fitchild.py``).
FIT_CHILD_MODULE = "groundstation.runtime.workers.fitchild"
TOPICS = ("mesh", "mapper.fit", "status", "log")
MAPPER_FINISHED = "mapper finished"
_RECV_MS = 20
_BATCH = 500
#: Seconds a hole in an observation stream is looked for in the recording before it counts as
#: lost, and how often it is looked for.
REPAIR_WAIT_S = 10.0
_REPAIR_EVERY_S = 0.5


def load_recorded_observations(path: str) -> tuple[list[Observation], int]:
    """Observations recorded on the ``observations`` channel of the session at ``path`` (every
    segment; cut ones read up to their last complete chunk); returns (observations, bad)."""
    from groundstation.acquisition.segments import open_session
    from groundstation.bus.envelope import from_bytes
    from groundstation.bus.errors import BusError

    out: list[Observation] = []
    bad = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TruncatedRecordingWarning: expected after a crash
        with open_session(path) as rec:
            for msg in rec.messages("observations"):
                try:
                    out.append(observation_from_envelope(from_bytes(msg.data)))
                except (BusError, KeyError, ValueError):
                    bad += 1
    return out, bad


# -- the fitting child -----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class FitMessage:
    """What the shell publishes of one refit (built from :func:`fit_message`'s plain data).

    ``vertices``, ``triangles`` and ``vertex_std`` are None when the fit has no mesh to publish
    (an unreliable fit keeps the last one shown; meshing off); ``vertex_std`` is zeros when the
    mesh carries none. ``timings``: where the refit's ``fit_s`` went
    (:data:`~groundstation.mapping.mapper.REFIT_STAGES`)."""

    fit_index: int
    data_ns: int
    reliable: bool
    reasons: tuple[str, ...]
    fit_s: float
    hyperparameters: dict
    flagged_events: tuple[int, ...]
    ids: np.ndarray
    u: np.ndarray
    flags: np.ndarray
    vertices: np.ndarray | None = None
    triangles: np.ndarray | None = None
    vertex_std: np.ndarray | None = None
    awaiting_events: tuple[int, ...] = ()
    timings: dict = dataclasses.field(default_factory=dict)

    @classmethod
    def from_plain(cls, plain: dict) -> FitMessage:
        return cls(**plain)


class FitChild:
    """The shell's handle on the fitting child process (``python -m`` :data:`FIT_CHILD_MODULE`,
    one end of a socket pair as a ``multiprocessing`` connection).

    Started as its own small program rather than by ``multiprocessing`` spawn, which imports the
    parent's main module in the child first (the shell's zmq, bus and catch-up, which fitting does
    not need) before the mapping core: ready in 0.5-0.7 s against 0.6-0.7 s on an idle machine,
    0.7 s against 1.1-1.2 s in the live soak, where every worker starts at once."""

    def __init__(self, config: Config) -> None:
        ours, theirs = socket.socketpair()
        self.conn = Connection(ours.detach())
        argv = [sys.executable, "-m", FIT_CHILD_MODULE, "--fd", str(theirs.fileno()),
                "--parent", str(os.getpid())]  # fmt: skip
        try:
            self.proc = subprocess.Popen(argv, pass_fds=(theirs.fileno(),))
        except BaseException:
            self.conn.close()
            raise
        finally:
            theirs.close()
        self.conn.send(("config", to_toml(config)))
        self.idle = False
        self.fitting_since: float | None = None
        self.started = time.monotonic()
        self.ready_s: float | None = None  # start to first "idle": interpreter, imports, config

    def alive(self) -> bool:
        return self.proc.poll() is None

    @property
    def exitcode(self) -> int | None:
        return self.proc.poll()

    def messages(self) -> list[tuple]:
        out = []
        try:
            while self.conn.poll(0):
                out.append(self.conn.recv())
        except (EOFError, OSError):
            pass
        return out

    def send(self, batch: list[Observation], final: bool) -> None:
        self.conn.send(("add", batch, final))
        self.idle = False

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        try:
            self.proc.wait(2.0)
        except subprocess.TimeoutExpired:
            pass
        self.conn.close()


class MapperProcess(Worker):
    """The mapper shell (see the module docstring)."""

    def __init__(
        self,
        session: Session,
        config: Config,
        *,
        name: str = "mapper",
        recording: str | None = None,
        wait_subscribers: int = 0,
        context: zmq.Context | None = None,
    ) -> None:
        super().__init__(session, config, name=name, topics=TOPICS, context=context)
        self.recording, self.wait_subscribers = recording, wait_subscribers
        self.sub: Subscriber | None = None
        self.child: FitChild | None = None
        self.held: dict[int, Observation] = {}
        self.unsent: list[Observation] = []
        self.data_ns: int | None = None
        self.bad = 0
        self.final_pending = False
        self.finished_seen = False
        self.last_fit: FitMessage | None = None
        self.fits = 0
        self.child_restarts = 0
        self.restored = 0
        self.catchup: dict = {}
        self.have: dict[int, int] = {}  # newest sequence number per detector origin
        self.holes: dict[int, set[int]] = {}  # missing sequence numbers per origin
        self.hole_since: float | None = None
        self._hole_ns = 0
        self._grow = None  # GrowingSession of the recording, for repairs
        self._next_repair = 0.0
        self.repaired = 0
        self.lost = 0

    # -- observations --------------------------------------------------------------------------
    def add(self, observations: Sequence[Observation]) -> int:
        """Keep new observations (by id) and queue them for the child; returns how many new."""
        n = 0
        for o in observations:
            if o.id in self.held:
                continue
            self.held[o.id] = o
            self.unsent.append(o)
            t = int(o.t_ns)
            self.data_ns = t if self.data_ns is None else max(self.data_ns, t)
            n += 1
        return n

    def handle(self, env, live: bool = True) -> None:
        if env.topic == "log":
            if env.payload.get("message", "").startswith(DETECTOR_FINISHED):
                self.final_pending = True
            return
        origin, seq = int(env.header.origin), int(env.header.seq)
        have = self.have.get(origin, -1)
        if live and self.recording is not None and seq > have + 1:
            self.holes.setdefault(origin, set()).update(range(have + 1, seq))
            if self.hole_since is None:
                self.hole_since, self._hole_ns = time.monotonic(), time.monotonic_ns()
        if seq > have:
            self.have[origin] = seq
        self.holes.get(origin, set()).discard(seq)
        try:
            self.add([observation_from_envelope(env)])
        except (KeyError, ValueError, TypeError):
            self.bad += 1

    def _repair(self) -> None:
        """Read the holes of the observation streams from the recording (see the module
        docstring)."""
        now = time.monotonic()
        if not any(self.holes.values()) or now < self._next_repair:
            return
        self._next_repair = now + _REPAIR_EVERY_S
        plan = GapPlan()
        for origin, missing in self.holes.items():
            if missing:
                plan.consumed[("observations", origin)] = min(missing) - 1
                plan.first_live[("observations", origin)] = max(missing) + 1
        if self._grow is None:
            from groundstation.acquisition.segments import GrowingSession

            self._grow = GrowingSession(self.recording)
        since = self._hole_ns - 60_000_000_000  # the missing ones were published just before
        try:
            found = read_recorded(self._grow, ("observations",), since, plan)
        except Exception as exc:  # noqa: BLE001 - not on disk yet, unreadable: try again
            found = []
            self.log("warning", f"cannot read {self.recording} for missed observations: {exc}")
        for env in found:
            if int(env.header.seq) in self.holes.get(int(env.header.origin), ()):
                self.handle(env, live=False)
                self.repaired += 1
        if not any(self.holes.values()):
            self.hole_since = None
        elif self.hole_since is not None and now - self.hole_since > REPAIR_WAIT_S:
            n = sum(len(v) for v in self.holes.values())
            self.lost += n
            self.log("warning", f"{n} observation(s) not in the recording after "
                     f"{REPAIR_WAIT_S:.0f} s: lost")  # fmt: skip
            self.holes, self.hole_since = {}, None

    # -- worker hooks --------------------------------------------------------------------------
    def setup(self) -> int | None:
        self.child = FitChild(self.config)
        self.sub = Subscriber(
            self.session.subscribe_endpoints(exclude=(self.name,)),
            ("observations", "log"),
            context=self.ctx,
        )
        if self.recording is not None and self.incarnation > 0:
            self._restore()
        self.wait_ready(self.wait_subscribers, ("mapper.fit",))
        self.state = "idle"
        return None

    def _restore(self) -> None:
        self.state = "catching up"
        self.publish_status()
        # one read: what is not on disk yet is repaired as a hole when the next one arrives
        res = catch_up(self.recording, ("observations",), GapPlan(), self.sub.recv,
                       stop=self.stopping, deadline_s=0.0)  # fmt: skip
        for env in res.recorded:
            self.handle(env, live=False)
        self.restored = len(self.held)
        for env in res.live:
            self.handle(env)  # a hole before them is repaired from the recording later
        self.catchup = {"recorded": len(res.recorded), "live_buffered": len(res.live),
                        "reads": res.reads, "seconds": round(res.waited_s, 3),
                        "error": res.error}  # fmt: skip
        err = f"; recording unreadable: {res.error}" if res.error else ""
        self.log("warning" if res.error else "info",
                 f"restored {self.restored} observations from {self.recording} in "
                 f"{res.waited_s:.1f} s{err}")  # fmt: skip

    def step(self) -> None:
        sub = self.sub
        env = sub.recv(_RECV_MS)
        n = 0
        while env is not None:
            self.handle(env)
            n += 1
            env = sub.recv(0) if n < _BATCH else None
        if self.recording is not None:
            self._repair()
        self._tend_child()

    def _tend_child(self) -> None:
        child = self.child
        for msg in child.messages():
            kind = msg[0]
            if kind == "idle":
                child.idle, child.fitting_since = True, None
                if child.ready_s is None:
                    child.ready_s = time.monotonic() - child.started
                    self.log("info", f"fitting process ready in {child.ready_s:.1f} s")
                if self.state == "fitting":
                    self.state = (
                        "idle"
                        if self.last_fit is None or self.last_fit.reliable
                        else ("unreliable")
                    )
            elif kind == "fitting":
                self.state, child.fitting_since = "fitting", time.monotonic()
            elif kind == "fit":
                self.publish_fit(FitMessage.from_plain(msg[1]))
            elif kind == "finished" and not self.finished_seen:
                self.finished_seen = True
                self.log("info", f"{MAPPER_FINISHED}: fit {msg[1]}")
        if not child.alive():
            self.child_restarts += 1
            self.log("warning", f"fitting process exited ({child.exitcode}); restarting it "
                     f"with the {len(self.held)} observations held")  # fmt: skip
            child.kill()
            self.child = FitChild(self.config)
            self.unsent = list(self.held.values())
            return
        if child.idle and (self.unsent or (self.final_pending and not self.finished_seen)):
            batch, self.unsent = self.unsent, []
            child.send(batch, self.final_pending)
            if self.final_pending:
                self.final_pending = False

    # -- publishing ----------------------------------------------------------------------------
    def publish_fit(self, fit: FitMessage) -> None:
        """``mesh`` (when the fit has one), ``mapper.fit`` and ``status`` for one refit."""
        self.last_fit = fit
        self.fits += 1
        lag_s = max(0, (self.data_ns or fit.data_ns) - fit.data_ns) / 1e9
        if fit.vertices is not None:
            self.pub.publish(
                "mesh",
                {"fit_index": fit.fit_index},
                {"vertices": fit.vertices, "triangles": fit.triangles,
                 "vertex_std": fit.vertex_std},
                source_ns=fit.data_ns,
            )  # fmt: skip
        self.pub.publish(
            "mapper.fit",
            {
                "fit_index": fit.fit_index,
                "reliable": fit.reliable,
                "reasons": list(fit.reasons),
                "data_ns": fit.data_ns,
                "lag_s": float(lag_s),
                "fit_s": fit.fit_s,
                "timings": dict(fit.timings),
                "hyperparameters": fit.hyperparameters,
                "flagged_events": list(fit.flagged_events),
                "awaiting_events": list(fit.awaiting_events),
            },
            {"ids": fit.ids, "u": fit.u, "flags": fit.flags},
            source_ns=fit.data_ns,
        )
        if not fit.reliable:
            text = f"fit {fit.fit_index} unreliable ({', '.join(fit.reasons)}); kept last mesh"
            self.log("warning", text)
        self.publish_status()

    def status_topics(self, now_ns: int) -> dict:
        fit, child = self.last_fit, self.child
        lag_s = 0.0 if fit is None else max(0, (self.data_ns or fit.data_ns) - fit.data_ns) / 1e9
        busy = None
        if child is not None and child.fitting_since is not None:
            busy = round(time.monotonic() - child.fitting_since, 3)
        topics: dict[str, Any] = {
            "observations": {"count": len(self.held), "bad": self.bad,
                             "pending": len(self.unsent),
                             "gaps": 0 if self.sub is None else sum(self.sub.gaps.values())},
            "mapper": {"fits": self.fits, "fit_index": None if fit is None else fit.fit_index,
                       "lag_s": round(lag_s, 3),
                       "reliable": None if fit is None else fit.reliable,
                       "fitting_s": busy, "child_restarts": self.child_restarts,
                       "child_ready_s": None if child is None or child.ready_s is None
                       else round(child.ready_s, 3),
                       "refit_period_s": self.config.mapper.refit_period_s},
        }  # fmt: skip
        if self.catchup or self.repaired or self.lost:
            topics["catchup"] = {**self.catchup, "repaired": self.repaired,
                                 "missing": sum(len(v) for v in self.holes.values()),
                                 "lost": self.lost + self.catchup.get("lost", 0)}  # fmt: skip
        return topics

    def status_text(self) -> str:
        fit = self.last_fit
        return f"{len(self.held)} observations, fit {-1 if fit is None else fit.fit_index}"

    def teardown(self) -> None:
        if self.child is not None:
            self.child.kill()  # at once: a fit in progress is only computation
        if self._grow is not None:
            self._grow.close()
        if self.sub is not None:
            self.sub.close()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m groundstation.runtime.workers.mapper")
    add_session_arguments(p)
    p.add_argument("--name", default="mapper", help="process name (its endpoint)")
    p.add_argument("--recording", default=None, help="session MCAP to restore observations from")
    p.add_argument("--wait-subscribers", type=int, default=0, help="subscribers to wait for")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (see the module docstring)."""

    def build(args: argparse.Namespace) -> MapperProcess:
        return MapperProcess(
            session_from_args(args),
            worker_config(args),
            name=args.name,
            recording=args.recording,
            wait_subscribers=args.wait_subscribers,
        )

    return worker_main(argv, _parser(), build)


if __name__ == "__main__":
    sys.exit(main())
