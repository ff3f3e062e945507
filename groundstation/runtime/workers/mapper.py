"""The mapper process: observations in (one thread), refits on the data clock (main thread).

Command line (started by the supervisor, with ``OPENBLAS_NUM_THREADS=1`` in its environment)::

    python -m groundstation.runtime.workers.mapper --session ID [--session-root /tmp]
        --publishers detector[,...]            # who publishes observations
        [--name mapper] [--recording SESSION.mcap] [--wait-subscribers 0]
        [--config FILE] [--set mapper.KEY=VALUE --set mapping.KEY=VALUE ...]

- A receiver thread owns the SUB socket (``observations`` and ``log`` of every other publisher
  of the session) and appends decoded observations to a queue; it never waits for a refit, so
  the mapper never holds back the detector or acquisition.
- The main thread drains the queue into :class:`~groundstation.mapping.mapper.Mapper`, asks
  ``due()`` and refits with *all* observations received so far: a refit slower than the
  schedule simply covers more data next time (skip ahead). After each refit it publishes
  ``mesh`` (when the fit produced a new one), ``mapper.fit`` (ids, u, flags, ``reliable``,
  ``reasons``, ``data_ns``, ``lag_s``) and ``status`` (``lag_s`` = newest data time received
  minus the fit's data time; ``state`` "fitting"/"idle"/"unreliable").
- ``--recording PATH``: on start, the ``observations`` channel of the session recording (the
  recorder's MCAP, still being written: read up to its last complete chunk) is reloaded first
  (``Mapper.restore``); ids seen again on the bus are ignored. The recorder closes a chunk at
  least every second, so what was published between the last complete chunk and this
  process subscribing is in the file a moment later: the recording is read again
  ``REFILL_AFTER_S`` after start, and every observation the mapper lacks is added. A restarted
  mapper thus loses nothing the recorder got.
- When the detector's ``log`` "detector finished ..." arrives (end of a replay), it refits
  once more on everything and publishes ``log`` "mapper finished: fit N".
- BLAS is limited to one thread (threadpoolctl) in this process.
"""

from __future__ import annotations

import argparse
import queue
import sys
import threading
import time
import warnings
from collections.abc import Sequence

import numpy as np
import zmq

from groundstation.bus.errors import BusTimeoutError
from groundstation.bus.pubsub import Publisher, Subscriber
from groundstation.config import Config, load_config
from groundstation.contact.detector import Observation
from groundstation.contact.stage import observation_from_envelope
from groundstation.mapping.mapper import FitResult, Mapper
from groundstation.runtime.session import (
    Session,
    StopSignals,
    add_session_arguments,
    publish_log,
    session_from_args,
)
from groundstation.runtime.workers.detector import DETECTOR_FINISHED

TOPICS = ("mesh", "mapper.fit", "status", "log")
MAPPER_FINISHED = "mapper finished"
#: Seconds after start at which the recording is read again (``--recording``).
REFILL_AFTER_S = (3.0, 8.0, 15.0)


def load_recorded_observations(path: str) -> tuple[list[Observation], int]:
    """Observations recorded on the ``observations`` channel of ``path`` (truncated files are
    read up to their last complete chunk); returns (observations, messages skipped as bad)."""
    from groundstation.acquisition.reader import open_recording
    from groundstation.bus.envelope import from_bytes
    from groundstation.bus.errors import BusError

    out: list[Observation] = []
    bad = 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TruncatedRecordingWarning: expected after a crash
        with open_recording(path) as rec:
            for msg in rec.messages("observations"):
                try:
                    out.append(observation_from_envelope(from_bytes(msg.data)))
                except (BusError, KeyError, ValueError):
                    bad += 1
    return out, bad


class MapperProcess:
    """The mapper process (see the module docstring)."""

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
        self.session, self.config, self.name = session, config, name
        self.recording, self.wait_subscribers = recording, wait_subscribers
        self.ctx = context or zmq.Context()
        self.pub = Publisher(topics=TOPICS, context=self.ctx, **session.publisher_kwargs(name))
        self.mapper = Mapper.from_config(config)
        self.inbox: queue.Queue = queue.Queue()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.bad = 0
        self.gaps = 0
        self.finished_seen = False
        self._end_marker = False
        self.state = "starting"
        self.last_fit: FitResult | None = None
        self.restored = 0

    # -- receiver thread -----------------------------------------------------------------------
    def _receive(self) -> None:
        sub = Subscriber(
            self.session.subscribe_endpoints(exclude=(self.name,)),
            ("observations", "log"),
            context=self.ctx,
        )
        try:
            while not self._stop.is_set():
                env = sub.recv(100)
                if env is None:
                    continue
                if env.topic == "log":
                    if env.payload.get("message", "").startswith(DETECTOR_FINISHED):
                        self.inbox.put("finished")
                    continue
                try:
                    self.inbox.put(observation_from_envelope(env))
                except (KeyError, ValueError, TypeError):
                    self.bad += 1
                self.gaps = sum(s.gaps for s in sub.stats.values())
        finally:
            sub.close()

    def _drain(self) -> bool:
        """Move queued observations into the mapper; True once the end marker was seen."""
        batch, finished = [], self._end_marker
        while True:
            try:
                item = self.inbox.get_nowait()
            except queue.Empty:
                break
            if item == "finished":
                finished = True
            else:
                batch.append(item)
        self.mapper.add(batch)
        self._end_marker = finished
        return finished

    # -- publishing ----------------------------------------------------------------------------
    def publish_fit(self, fit: FitResult) -> None:
        """``mesh`` (when new), ``mapper.fit`` and ``status`` for one refit."""
        lag_s = max(0, (self.mapper.data_ns or fit.data_ns) - fit.data_ns) / 1e9
        if fit.reliable and fit.mesh is not None:
            m = fit.mesh
            std = m.std if m.std is not None else np.zeros(len(m.vertices))
            self.pub.publish(
                "mesh",
                {"fit_index": int(fit.fit_index)},
                {
                    "vertices": np.ascontiguousarray(m.vertices, dtype=np.float32),
                    "triangles": np.ascontiguousarray(m.faces, dtype=np.int32),
                    "vertex_std": np.ascontiguousarray(std, dtype=np.float32),
                },
                source_ns=fit.data_ns,
            )
        self.pub.publish(
            "mapper.fit",
            {
                "fit_index": int(fit.fit_index),
                "reliable": bool(fit.reliable),
                "reasons": list(fit.reasons),
                "data_ns": int(fit.data_ns),
                "lag_s": float(lag_s),
                "fit_s": float(fit.timings.get("total_s", 0.0)),
                "hyperparameters": fit.hyperparameters,
                "flagged_events": [int(e) for e in fit.flagged_events],
            },
            {"ids": fit.ids.astype(np.int64), "u": fit.u.astype(np.float64), "flags": fit.flags},
            source_ns=fit.data_ns,
        )
        if not fit.reliable:
            text = f"fit {fit.fit_index} unreliable ({', '.join(fit.reasons)}); kept last mesh"
            publish_log(self.pub, self.name, "warning", text)
        self._status(lag_s)

    def _status(self, lag_s: float = 0.0) -> None:
        fit = self.last_fit
        self.pub.publish(
            "status",
            {
                "process": self.name,
                "state": self.state,
                "topics": {
                    "observations": {
                        "count": len(self.mapper),
                        "gaps": self.gaps,
                        "bad": self.bad,
                        "pending": self.mapper.pending,
                    },
                    "mapper": {
                        "fits": self.mapper.fit_index + 1,
                        "lag_s": round(lag_s, 3),
                        "reliable": None if fit is None else fit.reliable,
                    },
                },  # fmt: skip
                "text": f"{len(self.mapper)} observations, fit {self.mapper.fit_index}, "
                f"lag {lag_s:.2f} s",
            },
        )

    def refit(self) -> FitResult:
        self.state = "fitting"
        fit = self.mapper.refit()
        self.last_fit = fit
        self._drain()  # what arrived meanwhile counts towards the lag
        self.state = "idle" if fit.reliable else "unreliable"
        self.publish_fit(fit)
        return fit

    def restore(self, first: bool) -> int:
        """Add the recording's observations the mapper lacks; returns how many were new."""
        try:
            obs, bad = load_recorded_observations(self.recording)
        except Exception as exc:  # noqa: BLE001 - a bad recording must not stop us
            publish_log(self.pub, self.name, "warning", f"cannot restore: {exc}")
            return 0
        new = self.mapper.add(obs)
        if first or new:
            what = "restored" if first else "recovered"
            text = f"{what} {new} observations from {self.recording} ({bad} bad)"
            publish_log(self.pub, self.name, "info", text)
        self.restored += new
        return new

    # -- main loop -----------------------------------------------------------------------------
    def run(self, stop: StopSignals | None = None) -> int:
        """Run until SIGINT/SIGTERM; returns the exit code."""
        stop = stop if stop is not None else StopSignals()
        from threadpoolctl import threadpool_limits

        limits = threadpool_limits(1)
        start = time.monotonic()
        refills = list(REFILL_AFTER_S) if self.recording else []
        try:
            if self.recording:
                self.restore(first=True)
            self._thread = threading.Thread(target=self._receive, name="mapper-rx", daemon=True)
            self._thread.start()
            if self.wait_subscribers > 0:
                try:
                    self.pub.wait_for_subscribers(
                        self.wait_subscribers,
                        ("mapper.fit",),
                        self.config.acquisition.subscriber_timeout_s,
                    )
                except BusTimeoutError as exc:
                    publish_log(self.pub, self.name, "warning", f"starting anyway: {exc.message}")
            self.state = "idle"
            next_status = time.monotonic()
            while not stop:
                if refills and time.monotonic() - start >= refills[0]:
                    refills.pop(0)
                    self.restore(first=False)
                finished = self._drain()
                if self.mapper.due():
                    self.refit()
                if finished and not self.finished_seen:
                    self.finished_seen = True
                    if self.mapper.pending and self.mapper.ready():
                        self.refit()
                    publish_log(
                        self.pub, self.name, "info",
                        f"{MAPPER_FINISHED}: fit {self.mapper.fit_index}",
                    )  # fmt: skip
                now = time.monotonic()
                if now >= next_status:
                    self._status()
                    next_status = now + 1.0
                time.sleep(0.02)
            return 0
        finally:
            self._stop.set()
            if self._thread is not None:
                self._thread.join(5)
            limits.restore_original_limits()
            self.state = "stopped"
            try:
                self._status()
            except Exception:  # noqa: BLE001 - best effort at shutdown
                pass
            self.pub.close()
            self.ctx.term()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m groundstation.runtime.workers.mapper")
    add_session_arguments(p)
    p.add_argument("--name", default="mapper", help="process name (its endpoint)")
    p.add_argument("--recording", default=None, help="session MCAP to restore observations from")
    p.add_argument("--wait-subscribers", type=int, default=0, help="subscribers to wait for")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (see the module docstring)."""
    args = _parser().parse_args(argv)
    stop = StopSignals()
    proc = MapperProcess(
        session_from_args(args),
        load_config(args.config, args.set),
        name=args.name,
        recording=args.recording,
        wait_subscribers=args.wait_subscribers,
    )
    return proc.run(stop)


if __name__ == "__main__":
    sys.exit(main())
