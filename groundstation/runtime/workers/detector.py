"""The detector process: samples from the bus through :class:`ContactStage`, observations out.

Command line (started by the supervisor; ``groundstation live`` and ``replay --processes``)::

    python -m groundstation.runtime.workers.detector --session ID [--session-root /tmp]
        --publishers replay|link,mocap[,...]   # who publishes samples (subscribe endpoints)
        [--name detector] [--flow-from replay] [--wait-subscribers 1] [--first-id 0]
        [--config FILE] [--set contact.KEY=VALUE --set alignment.KEY=VALUE ...]

- Binds as ``--name`` in the session (``/tmp/gs-ID/detector.sock``) and publishes
  ``observations`` and ``contact.event`` (lossless), ``status`` (latest, every second of wall
  time: counters and the stage's ``StageStats``) and ``log``.
- Before subscribing it waits (XPUB handshake, ``acquisition.subscriber_timeout_s``) for
  ``--wait-subscribers`` subscribers of ``observations`` (the mapper, a recorder, a viewer),
  so no observation is sent before they listen.
- Subscribes to ``samples.imu``/``samples.attitude``/``samples.pose`` and ``log`` of every
  other publisher of the session; with ``--flow-from NAME`` it registers for credit with that
  publisher (a ``replay://...?speed=max`` source), acknowledging each sample once processed.
- When the replay source's last message (``log`` "replay finished ...") arrives, it flushes the
  stage and publishes ``log`` "detector finished: {json}" with its counters and the sample
  sequence gaps it saw (lossless, after every observation on the same socket), then keeps
  running until SIGINT/SIGTERM. Malformed samples are counted, never raised.
- ``--first-id N|auto``: first observation id. A restarted detector must not reuse ids (the
  mapper ignores an id it holds), so live sessions pass ``auto``: the wall clock in
  microseconds, which a later incarnation always exceeds. Replays use 0 (default), so the
  multi-process and in-process pipelines number observations alike.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence

import zmq

from groundstation.acquisition.replay import FINISHED
from groundstation.bus.errors import BusTimeoutError
from groundstation.bus.pubsub import Publisher, Subscriber
from groundstation.config import Config, load_config
from groundstation.contact.stage import INPUT_TOPICS, ContactStage
from groundstation.runtime.session import (
    RateCounter,
    Session,
    StopSignals,
    add_session_arguments,
    publish_log,
    session_from_args,
)

TOPICS = ("observations", "contact.event", "status", "log")
DETECTOR_FINISHED = "detector finished"


class DetectorProcess:
    """The loop of the detector process (see the module docstring)."""

    def __init__(
        self,
        session: Session,
        config: Config,
        *,
        name: str = "detector",
        flow_from: str | None = None,
        wait_subscribers: int = 1,
        first_id: int = 0,
        context: zmq.Context | None = None,
    ) -> None:
        self.name, self.config = name, config
        self.session, self.flow_from = session, flow_from
        self.wait_subscribers = wait_subscribers
        self.ctx = context or zmq.Context()
        self.pub = Publisher(topics=TOPICS, context=self.ctx, **session.publisher_kwargs(name))
        self.sub: Subscriber | None = None
        self.stage = ContactStage(
            config.contact, config.alignment, first_id=first_id, vehicle=config.vehicle
        )
        self.rates = RateCounter()
        self.state = "starting"
        self.finished = False

    def _connect(self) -> None:
        try:
            self.pub.wait_for_subscribers(
                self.wait_subscribers,
                ("observations",),
                self.config.acquisition.subscriber_timeout_s,
            )
        except BusTimeoutError as exc:
            publish_log(self.pub, self.name, "warning", f"starting anyway: {exc.message}")
        flow = None if self.flow_from is None else self.session.flow_endpoint(self.flow_from)
        self.sub = Subscriber(
            self.session.subscribe_endpoints(exclude=(self.name,)),
            (*INPUT_TOPICS, "log"),
            flow_endpoint=flow,
            context=self.ctx,
        )

    def _publish(self, outs) -> None:
        for env in outs:
            self.pub.publish(env.topic, env.payload, env.arrays, source_ns=env.header.source_ns)
            self.rates.add(env.topic)

    def summary(self) -> dict:
        """Counters for ``status`` and the finished line."""
        sub = self.sub
        return {
            "stage": self.stage.stats.as_dict(),
            "gaps": {} if sub is None else {t: s.gaps for t, s in sub.stats.items()},
            "received": {} if sub is None else {t: s.received for t, s in sub.stats.items()},
            "bad_messages": 0 if sub is None else sub.bad_messages,
        }

    def _status(self) -> None:
        topics = self.rates.snapshot(time.monotonic_ns())
        s = self.summary()
        topics["stage"] = s["stage"]
        topics["gaps"] = s["gaps"]
        self.pub.publish(
            "status",
            {
                "process": self.name,
                "state": self.state,
                "topics": topics,
                "text": f"{self.stage.stats.events} contacts, "
                f"{self.stage.stats.observations} observations",
            },
        )

    def step(self, timeout_ms: int = 100) -> bool:
        """Handle at most one message; False on timeout."""
        env = self.sub.recv(timeout_ms)
        if env is None:
            return False
        if env.topic == "log":
            if env.payload.get("message", "").startswith(FINISHED) and not self.finished:
                self._publish(self.stage.flush())
                self.finished = True
                self.state = "finished"
                text = f"{DETECTOR_FINISHED}: {json.dumps(self.summary(), sort_keys=True)}"
                publish_log(self.pub, self.name, "info", text)
            return True
        self._publish(self.stage.push(env))
        return True

    def run(self, stop: StopSignals | None = None) -> int:
        """Run until SIGINT/SIGTERM; returns the exit code."""
        stop = stop if stop is not None else StopSignals()
        try:
            self._connect()
            self.state = "running"
            next_status = time.monotonic()
            while not stop:
                self.step(100)
                now = time.monotonic()
                if now >= next_status:
                    self._status()
                    next_status = now + 1.0
            return 0
        finally:
            self.state = "stopped"
            try:
                self._status()
            except Exception:  # noqa: BLE001 - best effort at shutdown
                pass
            if self.sub is not None:
                self.sub.close()
            self.pub.close()
            self.ctx.term()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m groundstation.runtime.workers.detector")
    add_session_arguments(p)
    p.add_argument("--name", default="detector", help="process name (its endpoint)")
    p.add_argument("--flow-from", default=None, help="publisher to take credit from (replay)")
    p.add_argument("--wait-subscribers", type=int, default=1, help="subscribers to wait for")
    p.add_argument(
        "--first-id", type=first_id, default=0, help="first observation id, or 'auto' (clock)"
    )
    return p


def first_id(text: str) -> int:
    """``--first-id``: an integer >= 0, or ``auto`` = wall-clock microseconds (restart-safe)."""
    if text == "auto":
        return time.time_ns() // 1000
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--first-id {text!r}: an integer or 'auto'") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"--first-id {text!r} must be >= 0")
    return value


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (see the module docstring)."""
    args = _parser().parse_args(argv)
    stop = StopSignals()
    proc = DetectorProcess(
        session_from_args(args),
        load_config(args.config, args.set),
        name=args.name,
        flow_from=args.flow_from,
        wait_subscribers=args.wait_subscribers,
        first_id=args.first_id,
    )
    return proc.run(stop)


if __name__ == "__main__":
    sys.exit(main())
