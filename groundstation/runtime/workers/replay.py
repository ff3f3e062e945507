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

from groundstation.acquisition.replay import (
    FINISHED,
    SAMPLE_TOPICS,
    TOPICS,
    ReplayError,
    raw_fields,
    replay_decoded,
    window_ns,
)
from groundstation.acquisition.segments import open_session
from groundstation.bus.errors import BusTimeoutError
from groundstation.config import Config
from groundstation.runtime.session import (
    REPLAY_PUBLISHER,
    Session,
    add_session_arguments,
    worker_config,
)
from groundstation.runtime.worker import Worker, worker_main


class ReplaySource(Worker):
    """Publish a recording on the bus (see the module docstring).

    Parameters
    ----------
    path : str
        Recording (its first segment or folder; every segment is replayed).
    session : Session
        Endpoints; binds as ``name``.
    config : Config
        The session's configuration (``acquisition`` drives the decoders).
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
        config: Config,
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
        paced = math.isfinite(speed)
        settings = config.acquisition
        super().__init__(
            session, config, name=name, topics=TOPICS, context=context,
            publisher_kwargs=dict(
                flow_window=None if paced else settings.replay_flow_window,
                flow_endpoint=session.flow_endpoint(name), flow_timeout_s=60.0,
                linger_ms=30_000,
            ),
        )  # fmt: skip
        self.path, self.settings, self.speed = path, settings, speed
        self.start, self.end = start, end
        self.wait_subscribers, self.flow_consumers = wait_subscribers, flow_consumers
        self.published = 0
        self._rec = None
        self._items = None
        self._done = False
        self._wall0 = 0
        self._t0 = 0

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

    def setup(self) -> int | None:
        try:
            self._wait()
        except BusTimeoutError as exc:
            self.log("warning", f"starting anyway: {exc.message}")
        self._rec = rec = open_session(self.path)
        window = window_ns(rec, self.start, self.end)
        t0 = window.start_ns if window.start_ns is not None else rec.summary.start_ns
        self._t0 = t0 or 0
        self._items = replay_decoded(rec, window, self.settings)
        self._wall0 = time.monotonic_ns()
        self.state = "running"
        return None

    def step(self) -> None:
        """Publish the next recorded message (paced: when its deadline comes)."""
        item = next(self._items, None)
        if item is None:
            self._finish()
            return
        msg, decoded = item
        if math.isfinite(self.speed):  # absolute deadline on the log clock
            deadline = self._wall0 + int((msg.log_time_ns - self._t0) / self.speed)
            while (delay := deadline - time.monotonic_ns()) > 0 and not self.stop:
                time.sleep(min(delay / 1e9, 0.05))
        payload, arrays = raw_fields(msg)
        pub = self.pub
        pub.publish(
            msg.topic, payload, arrays, source_ns=msg.publish_time_ns, recv_ns=msg.log_time_ns
        )
        self.rates.add(msg.topic)
        for d in decoded:
            pub.publish(d.topic, d.payload, d.arrays, source_ns=d.source_ns, recv_ns=d.recv_ns)
            self.rates.add(d.topic)
        self.published += 1 + len(decoded)

    def _finish(self) -> None:
        wall = (time.monotonic_ns() - self._wall0) / 1e9
        text = f"{FINISHED}: {self.published} messages in {wall:.3f} s wall"
        self.log("info", text)
        self.state = "finished"
        self.publish_status()
        self._done = True

    def finished(self) -> bool:
        return self._done

    def status_text(self) -> str:
        return f"{self.path} at speed {self.speed}"

    def teardown(self) -> None:
        if self._rec is not None:
            self._rec.close()


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

    def build(args: argparse.Namespace) -> ReplaySource:
        opts = parse_replay_uri(args.uri)
        return ReplaySource(
            opts.path,
            session_from_args(args),
            worker_config(args),
            opts.speed,
            opts.start_s,
            opts.end_s,
            name=args.name,
            wait_subscribers=args.wait_subscribers,
            flow_consumers=args.wait_subscribers
            if args.flow_consumers is None
            else args.flow_consumers,
        )

    return worker_main(argv, _parser(), build)


if __name__ == "__main__":
    sys.exit(main())
