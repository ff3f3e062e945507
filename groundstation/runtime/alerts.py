"""What the status line must say in upper case, and the list of it at the end (pure).

:class:`Alerts` watches the messages the ``live`` monitor receives and the supervisor's worker
events, with the receive time passed in (no clock reads), and answers which conditions hold now
(:meth:`Alerts.current`). Each condition has a key; :meth:`Alerts.update` turns them into the
texts of the status line and keeps an event list (when each began, how long it lasted) for the
closing summary. :meth:`Alerts.data_loss` says what data the session lost (the exit code).

=====================================  =========================================================
condition                              shown as
=====================================  =========================================================
a worker down or just restarted        ``DETECTOR RESTARTING (restart 3)``, ``DETECTOR RESTARTED
                                       x3`` (for ``restart_note_s``), ``MOCAP GAVE UP``
no sample of a stream for > 0.5 s      ``NO IMU 1.3 s``, ``NO ATTITUDE ...``, ``NO POSE ...``
MAVLink frames lost (sequence gaps)    ``LINK LOSS 412 FRAMES (3.1 %) IN 5 S``
no byte from the link for > 1 s        ``LINK SILENT 2.0 s``
link device missing or lost            ``LINK NO DEVICE: <reason>``, ``LINK DISCONNECTED``
mocap socket failed / silent           ``MOCAP FAILED: <reason>``, ``MOCAP SILENT 4 s (no
                                       datagram from natnet://...: wrong host or port?)``
mocap datagrams rejected / bad         ``MOCAP REJECTED 12``, ``MOCAP BAD 3``
no new mesh for > 3 refit periods      ``MAP STALE 12 s``
recorder writing late / failed         ``REC BEHIND 2.3 s``, ``REC FAILED: ...``
the detector reading samples > 1 s     ``DETECTOR BEHIND 4.2 s``
late (CPU starvation)
a restarted worker reading what it      ``DETECTOR CATCHING UP 12 s``
missed from the recording
data a restart could not recover       ``DETECTOR LOST 40 SAMPLES IN RESTART``,
                                       ``REC LOST 12 AT TAKEOVER``, ``LINK RESTART GAP 0.43 s``
the monitor itself behind              ``STATUS LAGS 2.1 s``
the body tilted past 60 deg for        ``UPSET 3.2 s (TILTED 88 DEG)``: flipped by an impact, or
> 0.5 s (``samples.attitude``)         down after a crash (``contact.stage.UPSET_TILT_DEG``)
=====================================  =========================================================
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

from groundstation.bus.envelope import Envelope
from groundstation.contact.impulse import tilt_cos
from groundstation.contact.stage import UPSET_COS

S = 1_000_000_000
#: Streams watched for silence: topic -> name on the status line.
STREAMS = {"samples.imu": "IMU", "samples.attitude": "ATTITUDE", "samples.pose": "POSE"}


@dataclasses.dataclass(frozen=True)
class AlertSettings:
    """Thresholds (seconds unless said otherwise)."""

    silence_s: float = 0.5
    link_silent_s: float = 1.0
    mocap_silent_s: float = 2.0
    refit_period_s: float = 2.0
    stale_periods: float = 3.0
    min_contacts: int = 1
    rec_behind_s: float = 1.0
    detector_behind_s: float = 1.0
    restart_note_s: float = 10.0
    loss_window_s: float = 5.0
    monitor_lag_s: float = 1.0
    upset_s: float = 0.5


def _count_rejected(tree: Any) -> int:
    """Sum of integer counters whose key mentions ``rejected`` anywhere in a status tree."""
    total = 0
    if isinstance(tree, Mapping):
        for k, v in tree.items():
            if isinstance(v, Mapping):
                total += _count_rejected(v)
            elif "rejected" in str(k) and isinstance(v, int) and not isinstance(v, bool):
                total += v
    return total


class Alerts:
    """Conditions the operator must see (see the module docstring).

    Parameters
    ----------
    t0_ns : int
        Session start (monotonic ns; the clock of every ``now_ns``).
    settings : AlertSettings
    expect : iterable of str
        Sample topics that must flow (``samples.pose`` only with a mocap source).
    """

    def __init__(self, t0_ns: int, settings: AlertSettings | None = None, expect=()):
        self.t0_ns = int(t0_ns)
        self.s = settings or AlertSettings()
        self.expect = tuple(expect)
        self.last: dict[str, int] = {}
        self.status: dict[str, dict[str, Any]] = {}
        self.workers: dict[str, dict[str, Any]] = {}
        self.link_lost: list[tuple[int, int, int]] = []  # (now, lost total, rx total)
        self.lost_frames = 0
        self.mesh_ns: int | None = None
        self.obs_after_mesh = 0
        self.contacts_seen = 0
        self.external_seen = 0
        self.map_ready_ns: int | None = None
        self.monitor_lag_s = 0.0
        self.restart_gaps: dict[str, list[float]] = {}
        self.events: list[dict[str, Any]] = []
        self._open: dict[str, dict[str, Any]] = {}
        self.upset_since_ns: int | None = None  # first attitude past UPSET_TILT_DEG, in a row
        self.upset_deg = 0.0  # the latest such attitude's tilt

    # -- input ---------------------------------------------------------------------------------
    def on_message(self, env: Envelope, now_ns: int) -> None:
        """One message the monitor received at ``now_ns``."""
        topic, p = env.topic, env.payload
        self.last[topic] = now_ns
        if topic in STREAMS and env.header.recv_ns:
            self.monitor_lag_s = max(0.0, (now_ns - env.header.recv_ns) / S)
        if topic == "samples.attitude":
            self._attitude(env.arrays.get("q_wxyz"), now_ns)
        elif topic == "status":
            name = str(p.get("process", "?"))
            self.status[name] = dict(p)
            self._restart_gap(name, p)
        elif topic == "link.health":
            lost, rx = int(p.get("lost_frames") or 0), int(p.get("rx_messages") or 0)
            self.link_lost.append((now_ns, lost, rx))
            cut = now_ns - int(self.s.loss_window_s * S)
            while len(self.link_lost) > 2 and self.link_lost[1][0] <= cut:
                self.link_lost.pop(0)
        elif topic == "mesh":
            self.mesh_ns, self.obs_after_mesh = now_ns, 0
        elif topic == "observations":
            self.obs_after_mesh += 1
            label = p.get("label")
            self.contacts_seen += label == 0
            self.external_seen += label == 1
            if (
                self.map_ready_ns is None
                and self.contacts_seen >= self.s.min_contacts
                and self.external_seen >= 1
            ):
                self.map_ready_ns = now_ns

    def _attitude(self, q: Any, now_ns: int) -> None:
        """Follow whether the body is upset (tilted past ``UPSET_TILT_DEG``); an attitude that
        cannot be read changes nothing."""
        try:
            c = tilt_cos(q)
        except (TypeError, ValueError):  # no quaternion, or not four numbers
            return
        if math.isnan(c):
            return
        if c < UPSET_COS:
            if self.upset_since_ns is None:
                self.upset_since_ns = now_ns
            self.upset_deg = math.degrees(math.acos(max(-1.0, min(1.0, c))))
        else:
            self.upset_since_ns = None

    def _restart_gap(self, name: str, p: Mapping[str, Any]) -> None:
        topics = p.get("topics") or {}
        for part in ("link", "mocap"):
            info = topics.get(part) if isinstance(topics, Mapping) else None
            gap = info.get("restart_gap_s") if isinstance(info, Mapping) else None
            pid = (topics.get("process") or {}).get("pid") if isinstance(topics, Mapping) else None
            if isinstance(gap, int | float) and not isinstance(gap, bool):
                key = f"{name}:{pid}"
                if key not in self.restart_gaps:
                    self.restart_gaps[key] = [float(gap)]

    def on_worker(self, name: str, kind: str, restarts: int, detail: str, now_ns: int) -> None:
        """A supervisor event: ``started``, ``exited``, ``restarting``, ``gave_up``."""
        w = self.workers.setdefault(name, {"restarts": 0, "down_ns": None, "up_ns": None})
        if kind in ("exited", "restarting"):
            w["down_ns"] = w["down_ns"] or now_ns
        elif kind == "started":
            w["restarts"], w["down_ns"], w["up_ns"] = restarts, None, now_ns
        elif kind == "gave_up":
            w["gave_up"] = detail or True

    # -- conditions ----------------------------------------------------------------------------
    def current(self, now_ns: int, alive: Mapping[str, bool] | None = None) -> dict[str, str]:
        """Conditions that hold at ``now_ns``: key -> upper-case text."""
        out: dict[str, str] = {}
        alive = alive or {}
        for name, w in sorted(self.workers.items()):
            n = w["restarts"]
            if w.get("gave_up"):
                out[f"gave_up:{name}"] = f"{name.upper()} GAVE UP ({w['gave_up']})"
            elif w["down_ns"] is not None:
                out[f"down:{name}"] = f"{name.upper()} RESTARTING (restart {n + 1})"
            elif n and w["up_ns"] is not None and now_ns - w["up_ns"] < self.s.restart_note_s * S:
                out[f"restarted:{name}:{n}"] = f"{name.upper()} RESTARTED x{n}"
        started = now_ns - self.t0_ns
        for topic in self.expect:
            ref = self.last.get(topic, self.t0_ns)
            quiet = (now_ns - ref) / S
            if quiet > self.s.silence_s and started > self.s.silence_s * S:
                out[f"no:{topic}"] = f"NO {STREAMS.get(topic, topic)} {quiet:.1f} s"
        self._link(out, now_ns)
        self._mocap(out)
        self._map(out, now_ns)
        self._recorders(out)
        for name, st in self.status.items():
            lag = (st.get("topics") or {}).get("lag_s")
            if name.startswith("detector") and isinstance(lag, int | float):
                if lag > self.s.detector_behind_s:
                    out[f"behind:{name}"] = f"{name.upper()} BEHIND {lag:.1f} s"
            if st.get("state") == "catching up":
                up = ((st.get("topics") or {}).get("process") or {}).get("uptime_s")
                took = f" {up:.0f} s" if isinstance(up, int | float) else ""
                out[f"catching_up:{name}"] = f"{name.upper()} CATCHING UP{took}"
            cu = (st.get("topics") or {}).get("catchup") or {}
            if cu.get("lost"):
                what = "SAMPLES" if name.startswith("detector") else "OBSERVATIONS"
                out[f"catchup:{name}"] = f"{name.upper()} LOST {cu['lost']} {what} IN RESTART"
        if self.monitor_lag_s > self.s.monitor_lag_s:
            out["monitor_lag"] = f"STATUS LAGS {self.monitor_lag_s:.1f} s"
        if self.upset_since_ns is not None:
            held = (now_ns - self.upset_since_ns) / S
            if held > self.s.upset_s:
                out["upset"] = f"UPSET {held:.1f} s (TILTED {self.upset_deg:.0f} DEG)"
        return out

    def _link(self, out: dict[str, str], now_ns: int) -> None:
        if len(self.link_lost) >= 1:
            lost_total = self.link_lost[-1][1]
            self.lost_frames = max(self.lost_frames, lost_total)
            if len(self.link_lost) >= 2:
                (_, l0, r0), (_, l1, r1) = self.link_lost[0], self.link_lost[-1]
                d_lost, d_rx = max(0, l1 - l0), max(0, r1 - r0)
                if d_lost:
                    pct = 100.0 * d_lost / max(1, d_lost + d_rx)
                    out["link_loss"] = (
                        f"LINK LOSS {d_lost} FRAMES ({pct:.1f} %) IN {self.s.loss_window_s:.0f} S"
                    )
        st = self.status.get("link")
        if st is None:
            return
        info = (st.get("topics") or {}).get("link") or {}
        if st.get("state") == "no_device":
            out["link_device"] = f"LINK NO DEVICE: {info.get('device_error') or st.get('text')}"
        elif st.get("state") == "disconnected":
            out["link_device"] = "LINK DISCONNECTED"
        silent = info.get("silent_s")
        if isinstance(silent, int | float) and silent > self.s.link_silent_s:
            out["link_silent"] = f"LINK SILENT {silent:.1f} s"
        for key, gaps in self.restart_gaps.items():
            if key.startswith("link:") and gaps[0] > 0.05:
                out[f"gap:{key}"] = f"LINK RESTART GAP {gaps[0]:.2f} s"

    def _mocap(self, out: dict[str, str]) -> None:
        st = self.status.get("mocap")
        if st is None:
            return
        topics = st.get("topics") or {}
        info = topics.get("mocap") or {}
        if st.get("state") == "failed":
            out["mocap_failed"] = f"MOCAP FAILED: {info.get('open_error') or st.get('text')}"
        silent = info.get("silent_s")
        if isinstance(silent, int | float) and silent > self.s.mocap_silent_s:
            uri = info.get("uri")
            hint = "" if info.get("heard") else f" (NO DATAGRAM FROM {uri}: WRONG HOST?)"
            out["mocap_silent"] = f"MOCAP SILENT {silent:.0f} s{hint}"
        rejected = _count_rejected(topics)
        if rejected:
            out["mocap_rejected"] = f"MOCAP REJECTED {rejected}"
        bad = (topics.get("decoder") or {}).get("bad")
        if bad:
            out["mocap_bad"] = f"MOCAP BAD {bad}"
        for key, gaps in self.restart_gaps.items():
            if key.startswith("mocap:") and gaps[0] > 0.05:
                out[f"gap:{key}"] = f"MOCAP RESTART GAP {gaps[0]:.2f} s"

    def _map(self, out: dict[str, str], now_ns: int) -> None:
        ref = self.mesh_ns if self.mesh_ns is not None else self.map_ready_ns
        if ref is None or (self.mesh_ns is not None and not self.obs_after_mesh):
            return
        age = (now_ns - ref) / S
        if age > self.s.stale_periods * self.s.refit_period_s:
            out["map_stale"] = f"MAP STALE {age:.0f} s"

    def _recorders(self, out: dict[str, str]) -> None:
        for name, st in self.status.items():
            rec = (st.get("topics") or {}).get("recording")
            if not isinstance(rec, Mapping):
                continue
            if st.get("state") == "failed":
                out[f"rec_failed:{name}"] = f"REC FAILED: {st.get('text', '')}"
            if rec.get("role", "active") == "active":
                lag = rec.get("lag_s") or 0
                if lag > self.s.rec_behind_s:
                    out["rec_behind"] = f"REC BEHIND {lag:.1f} s"
            if rec.get("takeover_lost"):
                out[f"rec_lost:{name}"] = f"REC LOST {rec['takeover_lost']} AT TAKEOVER"

    # -- edges and summary ---------------------------------------------------------------------
    def update(self, now_ns: int, alive: Mapping[str, bool] | None = None) -> list[str]:
        """The texts to show now; records when each condition began and ended."""
        cur = self.current(now_ns, alive)
        t = round((now_ns - self.t0_ns) / S, 1)
        for key, text in cur.items():
            ev = self._open.get(key)
            if ev is None:
                ev = {"t_s": t, "kind": key.split(":", 1)[0], "key": key, "text": text}
                self._open[key] = ev
                self.events.append(ev)
            ev["last"] = text
        for key in list(self._open):
            if key not in cur:
                ev = self._open.pop(key)
                ev["duration_s"] = round(t - ev["t_s"], 1)
        return list(cur.values())

    def close(self, now_ns: int) -> None:
        """End every open condition at ``now_ns`` (for the summary)."""
        t = round((now_ns - self.t0_ns) / S, 1)
        for ev in self._open.values():
            ev.setdefault("duration_s", round(t - ev["t_s"], 1))
        self._open = {}

    def data_loss(self) -> list[str]:
        """What data the session lost, from the conditions seen (empty: nothing); a configured
        stream that never arrived counts too (the session recorded nothing of it)."""
        out = [f"no {STREAMS.get(t, t)} ever received" for t in self.expect if t not in self.last]
        if self.lost_frames:
            out.append(f"{self.lost_frames} MAVLink frames lost on the link")
        for ev in self.events:
            if ev["kind"] in ("catchup", "rec_lost", "rec_failed", "gave_up"):
                out.append(ev.get("last", ev["text"]).lower())
            elif ev["kind"] == "gap":
                out.append(ev.get("last", ev["text"]).lower() + " of vehicle/mocap data")
        return out
