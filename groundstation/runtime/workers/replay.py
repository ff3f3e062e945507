"""The replay source process: a recording's raw bytes and decoded samples on the bus.

``python -m groundstation.runtime.workers.replay --session ID --uri replay://flight.mcap?speed=X``.
Pacing and flow control are described in :mod:`groundstation.acquisition.replay`, whose pure
decoding (:func:`~groundstation.acquisition.replay.replay_decoded`) this shell publishes.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Sequence

import zmq

from groundstation.acquisition.reader import Recording, open_recording
from groundstation.acquisition.replay import (
    FINISHED,
    SAMPLE_TOPICS,
    TOPICS,
    ReplayError,
    Window,
    raw_fields,
    replay_decoded,
    window_ns,
)
from groundstation.acquisition.settings import AcquisitionSettings
from groundstation.bus.errors import BusTimeoutError
from groundstation.bus.pubsub import Publisher
from groundstation.runtime.session import (
    REPLAY_PUBLISHER,
    RateCounter,
    Session,
    StopSignals,
    add_session_arguments,
    load_settings,
    publish_log,
)


class ReplaySource:
    """Publish a recording on the bus (see the module docstring).

    Parameters
    ----------
    path : str
        Recording.
    session : Session
        Endpoints; binds as ``name``.
    speed : float
        Times real time; ``math.inf`` = as fast as the flow-controlled subscribers allow.
    start, end : float, optional
        Window, seconds from the log start.
    wait_subscribers : int
        Subscriptions to wait for before the first message (XPUB handshake).
    flow_consumers : int
        With speed=max: subscribers that registered for credit to wait for.
    """

    def __init__(
        self,
        path: str,
        session: Session,
        settings: AcquisitionSettings,
        speed: float = math.inf,
        start: float | None = None,
        end: float | None = None,
        *,
        name: str = REPLAY_PUBLISHER,
        wait_subscribers: int = 1,
        flow_consumers: int = 1,
        context: zmq.Context | None = None,
    ) -> None:
        if not speed > 0:
            raise ReplayError(f"replay speed={speed!r} must be > 0 (or max)")
        self.path, self.settings, self.speed = path, settings, speed
        self.start, self.end, self.name = start, end, name
        self.wait_subscribers, self.flow_consumers = wait_subscribers, flow_consumers
        self.ctx = context or zmq.Context()
        paced = math.isfinite(speed)
        self.pub = Publisher(
            topics=TOPICS,
            context=self.ctx,
            flow_window=None if paced else settings.replay_flow_window,
            flow_endpoint=session.flow_endpoint(name),
            flow_timeout_s=60.0,
            linger_ms=30_000,
            **session.publisher_kwargs(name),
        )
        self.rates = RateCounter()
        self.published = 0

    def _wait(self) -> None:
        timeout = self.settings.subscriber_timeout_s
        deadline = time.monotonic() + timeout
        while True:
            counts = self.pub.subscriber_counts()
            if all(counts[t] >= self.wait_subscribers for t in SAMPLE_TOPICS):
                break
            if time.monotonic() > deadline:
                raise BusTimeoutError(f"replay: subscribers {counts} after {timeout} s")
            time.sleep(0.01)
        if self.pub.flow is not None and self.flow_consumers > 0:
            self.pub.flow.wait_for_consumers(
                self.flow_consumers, max(0.0, deadline - time.monotonic())
            )

    def _status(self, state: str, text: str) -> None:
        self.pub.publish(
            "status",
            {
                "process": self.name,
                "state": state,
                "topics": self.rates.snapshot(time.monotonic_ns()),
                "text": text,
            },
        )

    def run(self, stop: StopSignals | None = None) -> int:
        """Publish the whole window; returns 0 when done (or stopped by a signal)."""
        try:
            try:
                self._wait()
            except BusTimeoutError as exc:
                publish_log(self.pub, self.name, "warning", f"starting anyway: {exc.message}")
            with open_recording(self.path) as rec:
                window = window_ns(rec, self.start, self.end)
                t0 = window.start_ns if window.start_ns is not None else rec.summary.start_ns
                self._publish_all(rec, window, t0 or 0, stop)
            return 0
        finally:
            self.pub.close()
            self.ctx.term()

    def _publish_all(self, rec: Recording, window: Window, t0: int, stop) -> None:
        pub, paced = self.pub, math.isfinite(self.speed)
        wall0 = time.monotonic_ns()
        next_status = wall0
        for msg, decoded in replay_decoded(rec, window, self.settings):
            if stop:
                break
            if paced:  # absolute deadline on the log clock
                deadline = wall0 + int((msg.log_time_ns - t0) / self.speed)
                while (delay := deadline - time.monotonic_ns()) > 0 and not stop:
                    time.sleep(min(delay / 1e9, 0.05))
            payload, arrays = raw_fields(msg)
            pub.publish(
                msg.topic, payload, arrays, source_ns=msg.publish_time_ns, recv_ns=msg.log_time_ns
            )
            self.rates.add(msg.topic)
            for d in decoded:
                pub.publish(d.topic, d.payload, d.arrays, source_ns=d.source_ns, recv_ns=d.recv_ns)
                self.rates.add(d.topic)
            self.published += 1 + len(decoded)
            now = time.monotonic_ns()
            if now >= next_status:
                self._status("running", f"{self.path} at speed {self.speed}")
                next_status = now + 1_000_000_000
        wall = (time.monotonic_ns() - wall0) / 1e9
        text = f"{FINISHED}: {self.published} messages in {wall:.3f} s wall"
        publish_log(pub, self.name, "info", text)
        self._status("finished", text)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m groundstation.runtime.workers.replay")
    add_session_arguments(p)
    p.set_defaults(publishers=REPLAY_PUBLISHER)
    p.add_argument("--uri", required=True, help="replay://flight.mcap?speed=1|X|max&start=S&end=S")
    p.add_argument("--name", default=REPLAY_PUBLISHER, help="process name (its endpoint)")
    p.add_argument("--wait-subscribers", type=int, default=1, help="subscribers to wait for")
    p.add_argument(
        "--flow-consumers", type=int, default=None, help="credit consumers (default: the same)"
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: ``python -m groundstation.runtime.workers.replay --session ID --uri replay://...``"""
    from groundstation.runtime.session import session_from_args
    from groundstation.runtime.sources import parse_replay_uri

    args = _parser().parse_args(argv)
    stop = StopSignals()
    opts = parse_replay_uri(args.uri)
    src = ReplaySource(
        opts.path,
        session_from_args(args),
        load_settings(args.config, args.set),
        opts.speed,
        opts.start_s,
        opts.end_s,
        name=args.name,
        wait_subscribers=args.wait_subscribers,
        flow_consumers=args.wait_subscribers
        if args.flow_consumers is None
        else args.flow_consumers,
    )
    return src.run(stop)


if __name__ == "__main__":
    sys.exit(main())
