"""The mocap process: the one owner of the NatNet socket.

``python -m groundstation.runtime.workers.mocap --session ID --mocap natnet://HOST:PORT``

Waits (XPUB ready handshake) for ``--wait-subscribers`` subscribers on its data topics, opens the
socket, then publishes every datagram on ``raw.natnet`` (receive time as source and receive
time; the configured NatNet version and Motive up axis travel in the payload so that the
recorder keeps them as channel metadata), the poses
:class:`~groundstation.acquisition.decoders.NatNetStreamDecoder` makes of it on
``samples.pose``, and ``status`` every ``health_period_s``. Bad datagrams are counted and
reported in the status, never raised. SIGINT/SIGTERM stop it cleanly (exit 0).

Datagrams not from the NatNet server (and server info not from its command port) are dropped by
the link before they are published or recorded (:class:`firmware_bridge.natnet.peers.
NatNetPeerPolicy`); a server-info version change is logged as a warning. Status
``topics["decoder"]``: ``bad``, ``nonfinite``, ``ignored``, ``out_of_range``,
``refused_versions``, ``version_changes``, ``version``; ``topics["security"]``: ``server``,
``rejected_peers``, ``rejected_server_info``, ``rejected_from``, ``last_rejected``.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

import numpy as np
import zmq

from firmware_bridge.errors import BridgeError
from firmware_bridge.frames import AxisConvention
from firmware_bridge.link import Link, open_link
from groundstation.acquisition.decoders import NatNetStreamDecoder
from groundstation.acquisition.settings import AcquisitionSettings
from groundstation.bus.errors import BusTimeoutError
from groundstation.bus.pubsub import Publisher
from groundstation.runtime.session import (
    RateCounter,
    Session,
    StopSignals,
    add_session_arguments,
    load_settings,
    publish_log,
    session_from_args,
)

DATA_TOPICS = ("raw.natnet", "samples.pose")
TOPICS = (*DATA_TOPICS, "status", "log")
_READ_TIMEOUT_S = 0.05


class MocapProcess:
    """The loop of the mocap process (see the module docstring)."""

    def __init__(
        self,
        session: Session,
        uri: str,
        settings: AcquisitionSettings,
        *,
        name: str = "mocap",
        wait_subscribers: int = 1,
        context: zmq.Context | None = None,
    ) -> None:
        self.session, self.uri, self.settings, self.name = session, uri, settings, name
        self.wait_subscribers = wait_subscribers
        self.ctx = context or zmq.Context()
        self.pub = Publisher(topics=TOPICS, context=self.ctx, **session.publisher_kwargs(name))
        self.decoder = NatNetStreamDecoder(
            settings.natnet_version_tuple,
            AxisConvention(settings.motive_up, settings.quaternion_order),
            int(settings.mocap_latency_ms * 1e6),
        )
        self.link: Link | None = None
        self.rates = RateCounter()
        self.state = "starting"
        self._reported_bad = 0
        self._reported_events = 0
        self._reported_rejections = 0

    def on_datagram(self, data: bytes, recv_ns: int, sender: str) -> None:
        """Publish one datagram received at ``recv_ns`` and its poses."""
        s = self.settings
        self.pub.publish(
            "raw.natnet",
            {"sender": sender, "natnet_version": s.natnet_version, "motive_up": s.motive_up},
            {"data": np.frombuffer(data, np.uint8)},
            source_ns=recv_ns,
            recv_ns=recv_ns,
        )
        self.rates.add("raw.natnet")
        for d in self.decoder.feed(data, recv_ns):
            self.pub.publish(d.topic, d.payload, d.arrays, source_ns=d.source_ns, recv_ns=d.recv_ns)
            self.rates.add(d.topic)

    def _status(self, now_ns: int) -> None:
        c = self.decoder.counters
        if c.bad > self._reported_bad:
            n_new = c.bad - self._reported_bad
            text = f"{n_new} bad NatNet datagram(s); last: {self.decoder.last_error}"
            publish_log(self.pub, self.name, "warning", text)
            self._reported_bad = c.bad
        for text in self.decoder.events[self._reported_events :]:
            publish_log(self.pub, self.name, "warning", text)
        self._reported_events = len(self.decoder.events)
        policy = getattr(self.link, "policy", None)
        security = policy.counters() if policy is not None else {}
        rejected = int(security.get("rejected_peers", 0)) + int(
            security.get("rejected_server_info", 0)
        )
        if rejected > self._reported_rejections:
            text = (
                f"{rejected - self._reported_rejections} NatNet datagram(s) rejected; "
                f"last: {security.get('last_rejected')}"
            )
            publish_log(self.pub, self.name, "warning", text)
            self._reported_rejections = rejected
        topics = self.rates.snapshot(now_ns)
        topics["decoder"] = {
            "bad": c.bad,
            "nonfinite": c.nonfinite,
            "ignored": c.ignored,
            "out_of_range": c.out_of_range,
            "refused_versions": c.refused_versions,
            "version_changes": c.version_changes,
            "version": ".".join(str(v) for v in self.decoder.version),
        }
        topics["security"] = security
        self.pub.publish(
            "status",
            {
                "process": self.name,
                "state": self.state,
                "topics": topics,
                "text": f"{self.uri}: {self.decoder.frames} frames, {c.bad} bad",
            },
        )

    def run(self, stop: StopSignals | None = None, max_s: float | None = None) -> int:
        """Run until SIGINT/SIGTERM (or ``max_s`` seconds); returns the exit code."""
        stop = stop if stop is not None else StopSignals()
        try:
            try:
                self.pub.wait_for_subscribers(
                    self.wait_subscribers, DATA_TOPICS, self.settings.subscriber_timeout_s
                )
            except BusTimeoutError as exc:
                publish_log(self.pub, self.name, "warning", f"starting anyway: {exc.message}")
            try:
                self.link = open_link(self.uri)
            except BridgeError as exc:
                self.state = "failed"
                publish_log(self.pub, self.name, "error", exc.message, exc.hint)
                return 3
            self.state = "running"
            period = int(self.settings.health_period_s * 1e9)
            now = time.monotonic_ns()
            end = None if max_s is None else now + int(max_s * 1e9)
            next_status = now
            while not stop and (end is None or now < end):
                data = self.link.read(_READ_TIMEOUT_S)
                now = time.monotonic_ns()
                if data:
                    src = getattr(self.link, "last_source", None)
                    self.on_datagram(data, now, f"{src[0]}:{src[1]}" if src else "")
                if now >= next_status:
                    self._status(now)
                    next_status = max(next_status + period, now)
            return 0
        finally:
            if self.link is not None:
                self.link.close()
            self.state = "stopped"
            try:
                self._status(time.monotonic_ns())
            except Exception:  # noqa: BLE001 - best effort at shutdown
                pass
            self.pub.close()
            self.ctx.term()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m groundstation.runtime.workers.mocap")
    add_session_arguments(p)
    p.add_argument(
        "--mocap", required=True, help="natnet://239.255.42.99:1511 or natnet://HOST:PORT"
    )
    p.add_argument("--name", default="mocap", help="process name (its endpoint in the session)")
    p.add_argument("--wait-subscribers", type=int, default=1, help="subscribers to wait for")
    p.add_argument("--max-s", type=float, default=None, help="stop after this many seconds")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (see the module docstring)."""
    args = _parser().parse_args(argv)
    stop = StopSignals()
    proc = MocapProcess(
        session_from_args(args),
        args.mocap,
        load_settings(args.config, args.set),
        name=args.name,
        wait_subscribers=args.wait_subscribers,
    )
    return proc.run(stop, args.max_s)


if __name__ == "__main__":
    sys.exit(main())
