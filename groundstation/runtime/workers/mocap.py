"""The mocap process: the one owner of the NatNet socket.

``python -m groundstation.runtime.workers.mocap --session ID --mocap natnet://HOST:PORT``

Opens the socket (datagrams queue in its receive buffer from then on), waits (XPUB ready
handshake) for ``--wait-subscribers`` subscribers on its data topics, then publishes every
datagram on ``raw.natnet`` (receive time as source and receive time; the configured NatNet
version and Motive up axis travel in the payload so that the recorder keeps them as channel
metadata), the poses
:class:`~groundstation.acquisition.decoders.NatNetStreamDecoder` makes of it on
``samples.pose``, and ``status`` every ``health_period_s``. Bad datagrams are counted and
reported in the status, never raised.

A socket that cannot be opened (a wrong host or interface, a port in use) is not a crash that
the supervisor would restart in a loop: the process stays up with state ``failed`` and the
reason in its status (upper case on the status line), and tries again every 2 s. Its status
also says how long no datagram has arrived (``silent_s``: a wrong host or port opens fine and
then stays silent), and after a restart how much mocap time it missed (``restart_gap_s``,
mocap clock, from ``mocap.state`` in the session directory). SIGINT/SIGTERM stop it cleanly
(exit 0).

Datagrams not from the NatNet server (and server info not from its command port) are dropped by
the link before they are published or recorded (:class:`firmware_bridge.natnet.peers.
NatNetPeerPolicy`); a server-info version change is logged as a warning. Status
``topics["decoder"]``: ``bad``, ``nonfinite``, ``ignored``, ``out_of_range``,
``refused_versions``, ``version_changes``, ``version``; ``topics["security"]``: ``server``,
``rejected_peers``, ``rejected_server_info``, ``rejected_from``, ``last_rejected``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Sequence

import numpy as np
import zmq

from firmware_bridge.errors import BridgeError
from firmware_bridge.frames import AxisConvention
from firmware_bridge.link import Link, open_link
from firmware_bridge.link.base import parse_uri
from groundstation.acquisition.decoders import NatNetStreamDecoder
from groundstation.config import Config
from groundstation.runtime.session import (
    Session,
    add_session_arguments,
    session_from_args,
    worker_config,
)
from groundstation.runtime.statefile import StateFile
from groundstation.runtime.worker import Worker, worker_main

DATA_TOPICS = ("raw.natnet", "samples.pose")
TOPICS = (*DATA_TOPICS, "status", "log")
_READ_TIMEOUT_S = 0.05
_REOPEN_S = 2.0
#: Longest ready handshake of a restarted mocap process (its subscribers only reconnect), s.
RESTART_WAIT_S = 1.5


class MocapProcess(Worker):
    """The loop of the mocap process (see the module docstring)."""

    def __init__(
        self,
        session: Session,
        uri: str,
        config: Config,
        *,
        name: str = "mocap",
        wait_subscribers: int = 1,
        context: zmq.Context | None = None,
        wait_samples: int | None = None,
    ) -> None:
        parse_uri(uri)  # a malformed URI is a configuration error
        super().__init__(session, config, name=name, topics=TOPICS, context=context)
        self.uri = uri
        self.settings = s = config.acquisition
        self.wait_subscribers = wait_subscribers
        self.wait_samples = wait_subscribers if wait_samples is None else wait_samples
        self.decoder = NatNetStreamDecoder(
            s.natnet_version_tuple,
            AxisConvention(s.motive_up, s.quaternion_order),
            int(s.mocap_latency_ms * 1e6),
        )
        self.link: Link | None = None
        self.open_error: str | None = None
        self.opened_ns: int | None = None
        self.last_rx_ns: int | None = None
        self.last_pose_ns: int | None = None
        self.restart_gap_s: float | None = None
        self._previous_pose_ns: int | None = None
        self._state: StateFile | None = None
        self._reported_bad = 0
        self._reopen_at = 0.0
        self.status_period_ns = int(s.health_period_s * 1e9)
        self._reported_events = 0
        self._reported_rejections = 0

    def on_datagram(self, data: bytes, recv_ns: int, sender: str) -> None:
        """Publish one datagram received at ``recv_ns`` and its poses."""
        s = self.settings
        self.last_rx_ns = recv_ns
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
            if d.topic == "samples.pose":
                self._pose(int(d.source_ns))

    def _pose(self, source_ns: int) -> None:
        if self.last_pose_ns is None and self._previous_pose_ns is not None:
            gap = (source_ns - self._previous_pose_ns) / 1e9
            if 0 <= gap < 3600:
                self.restart_gap_s = round(gap, 4)
                self.log("info" if gap < 0.05 else "warning",
                         f"mocap restart: first pose {gap:.3f} s (mocap time) after the last one "
                         "published before the restart")  # fmt: skip
        self.last_pose_ns = source_ns
        if self._state is not None:
            self._state.set(source_ns)

    # -- state across restarts -----------------------------------------------------------------
    def _load_state(self) -> None:
        try:
            self._state = StateFile(os.path.join(self.session.directory, f"{self.name}.state"), 1)
        except OSError:
            return
        last = self._state.get()[0]
        self._previous_pose_ns = last if last > 0 else None

    # -- worker hooks --------------------------------------------------------------------------
    def setup(self) -> int | None:
        self._load_state()
        self._try_open()  # first: a restart loses only the datagrams sent while no socket was bound
        limit = RESTART_WAIT_S if self.incarnation > 0 else None  # subscribers only reconnect
        if self.wait_ready(self.wait_subscribers, DATA_TOPICS, limit):
            self.wait_ready(self.wait_samples, ("samples.pose",), limit)  # monitor, detector
        return None

    def _try_open(self) -> None:
        self._reopen_at = time.monotonic() + _REOPEN_S
        try:
            self.link = open_link(self.uri)
        except BridgeError as exc:
            if self.open_error != exc.message:
                self.log("error", f"cannot open {self.uri}: {exc.message}", exc.hint)
            self.open_error = exc.message
            self.state = "failed"
            return
        if self.open_error is not None:
            self.log("info", f"opened {self.uri}")
        self.open_error = None
        self.opened_ns = time.monotonic_ns()
        self.state = "running"

    def step(self) -> None:
        if self.link is None:
            if time.monotonic() >= self._reopen_at:
                self._try_open()
            if self.link is None:
                time.sleep(0.05)
                return
        data = self.link.read(_READ_TIMEOUT_S)
        if data:
            now = time.monotonic_ns()
            src = getattr(self.link, "last_source", None)
            self.on_datagram(data, now, f"{src[0]}:{src[1]}" if src else "")

    def publish_status(self, now_ns: int | None = None) -> None:
        c = self.decoder.counters
        if c.bad > self._reported_bad:
            n_new = c.bad - self._reported_bad
            self.log("warning", f"{n_new} bad NatNet datagram(s); last: {self.decoder.last_error}")
            self._reported_bad = c.bad
        for text in self.decoder.events[self._reported_events :]:
            self.log("warning", text)
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
            self.log("warning", text)
            self._reported_rejections = rejected
        super().publish_status(now_ns)

    def status_topics(self, now_ns: int) -> dict:
        topics = self.rates.snapshot(now_ns)
        c = self.decoder.counters
        topics["decoder"] = {
            "bad": c.bad,
            "nonfinite": c.nonfinite,
            "ignored": c.ignored,
            "out_of_range": c.out_of_range,
            "refused_versions": c.refused_versions,
            "version_changes": c.version_changes,
            "version": ".".join(str(v) for v in self.decoder.version),
        }
        policy = getattr(self.link, "policy", None)
        topics["security"] = policy.counters() if policy is not None else {}
        since = self.last_rx_ns if self.last_rx_ns is not None else self.opened_ns
        topics["mocap"] = {
            "uri": self.uri,
            "open_error": self.open_error,
            "frames": self.decoder.frames,
            "silent_s": None if since is None else round((now_ns - since) / 1e9, 3),
            "heard": self.last_rx_ns is not None,
            "restart_gap_s": self.restart_gap_s,
        }
        return topics

    def status_text(self) -> str:
        if self.open_error is not None:
            return f"{self.uri}: CANNOT OPEN: {self.open_error}"
        c = self.decoder.counters
        return f"{self.uri}: {self.decoder.frames} frames, {c.bad} bad"

    def teardown(self) -> None:
        if self.link is not None:
            self.link.close()
            self.link = None
        if self._state is not None:
            self._state.close()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m groundstation.runtime.workers.mocap")
    add_session_arguments(p)
    p.add_argument(
        "--mocap", required=True, help="natnet://239.255.42.99:1511 or natnet://HOST:PORT"
    )
    p.add_argument("--name", default="mocap", help="process name (its endpoint in the session)")
    p.add_argument("--wait-subscribers", type=int, default=1, help="subscribers to wait for")
    p.add_argument("--wait-samples", type=int, default=None,
                   help="subscribers of samples.pose to wait for (default: the same)")  # fmt: skip
    p.add_argument("--max-s", type=float, default=None, help="stop after this many seconds")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (see the module docstring)."""

    def build(args: argparse.Namespace) -> MocapProcess:
        return MocapProcess(
            session_from_args(args),
            args.mocap,
            worker_config(args),
            name=args.name,
            wait_subscribers=args.wait_subscribers,
            wait_samples=args.wait_samples,
        )

    return worker_main(argv, _parser(), build)


if __name__ == "__main__":
    sys.exit(main())
