"""The detector process: samples from the bus through :class:`ContactStage`, observations out.

Command line (started by the supervisor; ``groundstation live`` and ``replay --processes``)::

    python -m groundstation.runtime.workers.detector --session ID [--session-root /tmp]
        --publishers replay|link,mocap[,...]   # who publishes samples (subscribe endpoints)
        [--name detector] [--flow-from replay] [--wait-subscribers 1] [--first-id 0]
        [--recording SESSION.mcap]

- Binds as ``--name`` in the session (``/tmp/gs-ID/detector.sock``) and publishes
  ``observations`` and ``contact.event`` (lossless), ``status`` (latest, every second of wall
  time: counters, the stage's ``StageStats`` and, live, ``lag_s``: the longest a sample
  waited since the last status between its publisher's stamp and the stage; the status line
  shows ``DETECTOR BEHIND``) and ``log``.
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

Catch-up after a restart (``--recording``, live sessions)
-----------------------------------------------------------
The stage is pure and deterministic, so a restarted detector can continue exactly where the
killed one stood. About once a second the detector checkpoints ``detector.ckpt`` in the session
directory: the pickled stage and, per sample stream (topic, publisher origin), the last
sequence number it consumed. Every output it publishes also advances a small memory-mapped
counter file (``detector.published``: how many observations and contact events of the stage's
numbering are out). A restarted detector loads the checkpoint (none: a fresh stage from the
start of the session), subscribes, reads from the recording every sample between the
checkpoint and the first one it receives live (:mod:`groundstation.runtime.catchup`), runs them
through the stage, and publishes the outputs beyond the counter, with the ids a detector that
never died would have given. An output counted as published may still have been in the killed
process's ZeroMQ send queue, delivered to one subscriber and not to another, so the last
``RESEND`` outputs of each topic below the counter are published again (the checkpoint keeps
those from before it; the catch-up re-derives those after it). Every contact event and
observation therefore comes out at least once and never goes missing; the recorder keeps the
first copy of each (topic, id, state) and the mapper ignores a repeated id.
Samples that neither the recording nor the live stream hold are counted (``catchup.lost``).
Ids therefore start at ``--first-id`` (0) in every live session as in a replay; ``auto`` (the
wall clock) remains for a detector without recording.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import sys
import time
from collections import deque
from collections.abc import Sequence

import zmq

from groundstation.acquisition.replay import FINISHED
from groundstation.bus.envelope import Envelope
from groundstation.bus.errors import EnvelopeError
from groundstation.bus.pubsub import Subscriber
from groundstation.config import Config
from groundstation.contact.stage import INPUT_TOPICS, ContactStage
from groundstation.runtime.catchup import GapPlan, catch_up, stream_key
from groundstation.runtime.session import (
    Session,
    add_session_arguments,
    session_from_args,
    worker_config,
)
from groundstation.runtime.statefile import StateFile
from groundstation.runtime.worker import Worker, worker_main

TOPICS = ("observations", "contact.event", "status", "log")
DETECTOR_FINISHED = "detector finished"
CHECKPOINT_FILE = "detector.ckpt"
PUBLISHED_FILE = "detector.published"
_CHECKPOINT_NS = 1_000_000_000
# outputs per topic published again after a restart: far more than can sit in a send queue in
# the moments before a SIGKILL (the CI failure lost the single last one)
RESEND = 64


class PublishedCounter:
    """How many outputs of the stage's numbering are published, per output topic, in a
    :class:`~groundstation.runtime.statefile.StateFile` that outlives the process."""

    TOPICS = ("observations", "contact.event")

    def __init__(self, path: str) -> None:
        self._file = StateFile(path, len(self.TOPICS))

    def get(self) -> dict[str, int]:
        return dict(zip(self.TOPICS, self._file.get(), strict=True))

    def advance(self, topic: str, seq: int) -> None:
        """Output number ``seq`` of ``topic`` is out."""
        values = list(self._file.get())
        k = self.TOPICS.index(topic)
        values[k] = max(values[k], seq + 1)
        self._file.set(*values)

    def close(self) -> None:
        self._file.close()


class OutputWindow:
    """Which stage outputs a detector publishes, given how many of each topic an earlier
    incarnation counted as published (``limit``; zero for a first start).

    Outputs below ``limit - size`` were out long before the previous incarnation died and are
    skipped; the last ``size`` below it may have died in its send queue and go out again
    (consumers keep the first copy); outputs from ``limit`` on are new. The window also keeps the
    last ``size`` outputs of each topic it let out, which a checkpoint stores so that a restart
    can send again those it will not re-derive. Pure: no I/O."""

    def __init__(self, limit: dict[str, int] | None = None, size: int = RESEND) -> None:
        self.limit = dict(limit or {})
        self.size = size
        self.suppressed = 0
        self.resent = 0
        self._recent: dict[str, deque[Envelope]] = {}

    def admit(self, env: Envelope) -> bool:
        """Whether ``env`` goes out now (counted as skipped or re-sent when it went before)."""
        limit, seq = self.limit.get(env.topic, 0), int(env.header.seq)
        if seq >= limit:
            return True
        if seq < limit - self.size:
            self.suppressed += 1  # the previous incarnation published it long ago
            return False
        self.resent += 1
        return True

    def sent(self, env: Envelope) -> None:
        """``env`` went out: remember it among the recent ones."""
        self._recent.setdefault(env.topic, deque(maxlen=self.size)).append(env)

    def recent(self) -> dict[str, list[Envelope]]:
        """The last ``size`` outputs let out, per topic (for the checkpoint)."""
        return {t: list(q) for t, q in self._recent.items()}


class DetectorProcess(Worker):
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
        recording: str | None = None,
        context: zmq.Context | None = None,
    ) -> None:
        super().__init__(session, config, name=name, topics=TOPICS, context=context)
        self.flow_from, self.recording = flow_from, recording
        self.wait_subscribers = wait_subscribers
        self.sub: Subscriber | None = None
        self.first_id = first_id
        self.stage = ContactStage(
            config.contact, config.alignment, first_id=first_id, vehicle=config.vehicle
        )
        self.finished_replay = False
        self.consumed: dict[tuple[str, int], int] = {}
        self.last_recv_ns: int | None = None
        self.catchup: dict = {}
        self.window = OutputWindow()
        self._published: PublishedCounter | None = None
        self._next_checkpoint = 0
        self._dirty = False
        self._consistent = True
        self.unpublishable = 0
        self._lag_max = 0  # ns, since the last status

    # -- files ---------------------------------------------------------------------------------
    def _path(self, filename: str) -> str:
        return os.path.join(self.session.directory, f"{self.name}.{filename.split('.', 1)[1]}")

    def _load_checkpoint(self) -> dict | None:
        try:
            with open(self._path(CHECKPOINT_FILE), "rb") as fh:
                ck = pickle.load(fh)
            if not isinstance(ck.get("stage"), ContactStage):
                raise TypeError("not a detector checkpoint")
            return ck
        except FileNotFoundError:
            return None
        except Exception as exc:  # noqa: BLE001 - unreadable: start from the recording's start
            self.log("warning", f"checkpoint unreadable ({exc}); catching up from the start")
            return None

    def checkpoint(self) -> None:
        """Write the stage and the consumed positions (atomically)."""
        if self.recording is None or not self._dirty or not self._consistent:
            return
        path = self._path(CHECKPOINT_FILE)
        state = {
            "stage": self.stage,
            "consumed": self.consumed,
            "recv_ns": self.last_recv_ns,
            "recent": self.window.recent(),
        }
        try:
            with open(path + ".tmp", "wb") as fh:
                pickle.dump(state, fh, protocol=pickle.HIGHEST_PROTOCOL)
            os.replace(path + ".tmp", path)
            self._dirty = False
        except (OSError, pickle.PicklingError, TypeError) as exc:
            self.log("warning", f"cannot checkpoint ({exc}); a restart will re-read the session")

    # -- bus -----------------------------------------------------------------------------------
    def setup(self) -> int | None:
        self.wait_ready(self.wait_subscribers, ("observations",))
        flow = None if self.flow_from is None else self.session.flow_endpoint(self.flow_from)
        self.sub = Subscriber(
            self.session.subscribe_endpoints(exclude=(self.name,)),
            (*INPUT_TOPICS, "log"),
            flow_endpoint=flow,
            context=self.ctx,
        )
        if self.recording is not None:
            self._published = PublishedCounter(self._path(PUBLISHED_FILE))
            ck = self._load_checkpoint()
            if ck is not None or self.incarnation > 0:
                self._resume(ck)
        return None

    def _resume(self, ck: dict | None) -> None:
        """Continue where the previous incarnation stood (see the module docstring)."""
        if ck is not None:
            self.stage, self.consumed = ck["stage"], dict(ck["consumed"])
            self.last_recv_ns = ck.get("recv_ns")
        self.window = OutputWindow(self._published.get())
        if ck is not None:  # outputs from before the checkpoint that may not have reached everyone
            for envs in ck.get("recent", {}).values():
                self._publish(envs)
        plan = GapPlan(self.consumed)
        since = None if self.last_recv_ns is None else self.last_recv_ns - 2_000_000_000
        self.state = "catching up"
        self.publish_status()
        res = catch_up(self.recording, INPUT_TOPICS, plan, self.sub.recv, since_ns=since,
                       stop=self.stopping, on_wait=self._catching_up)  # fmt: skip
        for env in res.recorded:
            self._push(env)
        for env in res.live:
            self.handle(env)
        self.catchup = {
            "from_checkpoint": ck is not None,
            "recorded": len(res.recorded),
            "live_buffered": len(res.live),
            "lost": sum(res.lost.values()),
            "reads": res.reads,
            "seconds": round(res.waited_s, 3),
            "error": res.error,
        }
        lost = f"; {sum(res.lost.values())} sample(s) lost: {res.lost}" if res.lost else ""
        err = f"; recording unreadable: {res.error}" if res.error else ""
        self.log(
            "warning" if (res.lost or res.error) else "info",
            f"resumed {'from its checkpoint' if ck else 'from the session start'}: "
            f"{len(res.recorded)} recorded sample(s) caught up in {res.waited_s:.1f} s, "
            f"{self.window.suppressed} output(s) already published skipped, "
            f"{self.window.resent} re-sent{lost}{err}",
        )
        self.state = "running"

    def _catching_up(self) -> None:
        """During the catch-up: the status says so once a second."""
        now = time.monotonic_ns()
        if now >= self._next_status:
            self.publish_status(now)

    def _publish(self, outs: list[Envelope]) -> None:
        for env in outs:
            if not self.window.admit(env):
                continue
            seq = int(env.header.seq)
            try:
                self.pub.publish(env.topic, env.payload, env.arrays, source_ns=env.header.source_ns)
            except EnvelopeError as exc:
                # a stage output the bus refuses is a bug: named, counted, and the loop goes
                # on (a crash would restart into the same output and drop the rest with it)
                self.unpublishable += 1
                self.log("error", f"{env.topic} #{seq} not published: {exc}")
            else:
                self.rates.add(env.topic)
            if self._published is not None:
                self._published.advance(env.topic, seq)
                self.window.sent(env)

    def _push(self, env: Envelope) -> None:
        # until the stage's outputs are all out, its state must not be checkpointed: a restart
        # from that state would never produce them again
        self._consistent = False
        self._publish(self.stage.push(env))
        self.consumed[stream_key(env)] = int(env.header.seq)
        if env.header.recv_ns:
            self.last_recv_ns = int(env.header.recv_ns)
            if self.flow_from is None:  # live: stamped by the link / mocap when read
                lag = time.monotonic_ns() - self.last_recv_ns
                self._lag_max = max(self._lag_max, lag)
        self._dirty = True
        self._consistent = True

    def handle(self, env: Envelope) -> None:
        """One message from the bus: a sample for the stage, or the replay's end marker."""
        if env.topic == "log":
            if env.payload.get("message", "").startswith(FINISHED) and not self.finished_replay:
                self._publish(self.stage.flush())
                self.finished_replay = True
                self.state = "finished"
                text = f"{DETECTOR_FINISHED}: {json.dumps(self.summary(), sort_keys=True)}"
                self.log("info", text)
            return
        key = stream_key(env)
        if int(env.header.seq) <= self.consumed.get(key, -1):
            return  # caught up from the recording already
        self._push(env)

    def summary(self) -> dict:
        """Counters for ``status`` and the finished line."""
        sub = self.sub
        return {
            "stage": self.stage.stats.as_dict(),
            "gaps": {} if sub is None else {t: s.gaps for t, s in sub.stats.items()},
            "received": {} if sub is None else {t: s.received for t, s in sub.stats.items()},
            "bad_messages": 0 if sub is None else sub.bad_messages,
            "unpublishable": self.unpublishable,
        }

    def step(self, timeout_ms: int = 100) -> bool:
        """Handle at most one message; False on timeout."""
        env = self.sub.recv(timeout_ms)
        now = time.monotonic_ns()
        if now >= self._next_checkpoint:
            self.checkpoint()
            self._next_checkpoint = now + _CHECKPOINT_NS
        if env is None:
            return False
        self.handle(env)
        return True

    def status_topics(self, now_ns: int) -> dict:
        topics = self.rates.snapshot(now_ns)
        s = self.summary()
        topics["stage"] = s["stage"]
        topics["gaps"] = s["gaps"]
        if self.flow_from is None:
            topics["lag_s"] = round(self._lag_max / 1e9, 3)
            self._lag_max = 0
        if self.catchup:
            w = self.window
            topics["catchup"] = {**self.catchup, "suppressed": w.suppressed, "resent": w.resent}
        return topics

    def status_text(self) -> str:
        st = self.stage.stats
        return f"{st.events} contacts, {st.observations} observations"

    def teardown(self) -> None:
        self.checkpoint()
        if self.sub is not None:
            self.sub.close()
        if self._published is not None:
            self._published.close()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m groundstation.runtime.workers.detector")
    add_session_arguments(p)
    p.add_argument("--name", default="detector", help="process name (its endpoint)")
    p.add_argument("--flow-from", default=None, help="publisher to take credit from (replay)")
    p.add_argument("--wait-subscribers", type=int, default=1, help="subscribers to wait for")
    p.add_argument(
        "--first-id", type=first_id, default=0, help="first observation id, or 'auto' (clock)"
    )
    p.add_argument(
        "--recording", default=None, help="the session's recording: catch up after a restart"
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

    def build(args: argparse.Namespace) -> DetectorProcess:
        return DetectorProcess(
            session_from_args(args),
            worker_config(args),
            name=args.name,
            flow_from=args.flow_from,
            wait_subscribers=args.wait_subscribers,
            first_id=args.first_id,
            recording=args.recording,
        )

    return worker_main(argv, _parser(), build)


if __name__ == "__main__":
    sys.exit(main())
