"""The live status line: aggregate bus messages into one line per second (pure).

:class:`StatusBoard` ingests every message the ``live`` command's monitor subscriber receives
(samples, ``status``, ``link.health``, ``log``, ``pilot.event``, ``pilot.command``,
``observations``, ``contact.event``, ``mapper.fit``, ``mesh``) with the monitor's receive time
``now_ns`` passed in (no clock reads here), and renders:

- rates per stream over the last line interval (imu, att, pose, cmd), bus gaps (the monitor's
  own sequence gaps, and the recorder's), contacts (``contact.event`` begins), observations;
- mapper: last refit time (from the mapper's ``status`` / ``mapper.fit``; see
  :func:`refit_seconds`), mesh fit index and age;
- the pilot path, loudly when it is not sending for a fault: the mux's own status line
  (``!!! PILOT FAILSAFE: JOYSTICK LOST - NOT SENDING ... !!!``), or ``!!! PILOT PROCESS DOWN``;
- process states from the supervisor (``DOWN`` for a dead worker);
- everything :class:`~groundstation.runtime.alerts.Alerts` finds wrong, in upper case (a worker
  restarting, a silent stream, MAVLink frame loss, a missing device, a stale map, a recorder
  behind, ...), and the list of those conditions in the closing summary with what data was lost.

Measurements kept for the closing summary (:meth:`StatusBoard.summary`): refit times, mesh
update intervals (time between successive ``mesh`` arrivals at the monitor), and
contact-to-mesh latency: for each contact observation (label 0), the time from its arrival at
the monitor to the arrival of the first mesh whose fit included its id (``mapper.fit`` ids of
the same ``fit_index``). Bounded memory: per-id state is dropped once the id is meshed, and at
most :data:`MAX_PENDING` contacts / fits are kept waiting.
"""

from __future__ import annotations

import dataclasses
import math
from collections import OrderedDict
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from groundstation.bus.envelope import Envelope
from groundstation.bus.topics import TOPICS
from groundstation.runtime.alerts import Alerts

#: Streams whose rate is shown, in order, with their short names.
RATE_STREAMS: tuple[tuple[str, str], ...] = (
    ("samples.imu", "imu"),
    ("samples.attitude", "att"),
    ("samples.pose", "pose"),
    ("pilot.command", "cmd"),
)
#: Pilot events printed at once (and shown loudly).
LOUD_PILOT_EVENTS = frozenset(
    {"failsafe", "failsafe_reason", "estop", "device_device_lost", "device_read_error"}
)
#: Keys that carry a refit duration in seconds (or ms with ``_ms``) in mapper payloads.
REFIT_KEYS_S = ("refit_s", "last_refit_s", "fit_s", "refit_time_s", "fit_time_s")
REFIT_KEYS_MS = ("refit_ms", "last_refit_ms", "fit_ms")
MAX_PENDING = 20_000
_LATEST = frozenset(n for n, t in TOPICS.items() if t.policy == "latest")
_MAX_SERIES = 100_000


def refit_seconds(payload: Mapping[str, Any]) -> float | None:
    """The refit duration (s) found in a mapper ``status`` or ``mapper.fit`` payload, or None.

    Looks for :data:`REFIT_KEYS_S` (seconds) or :data:`REFIT_KEYS_MS` (milliseconds) at the top
    level, then in nested dicts (e.g. ``topics["mapper"]``), first match wins.
    """
    stack: list[Mapping[str, Any]] = [payload]
    while stack:
        d = stack.pop(0)
        for keys, scale in ((REFIT_KEYS_S, 1.0), (REFIT_KEYS_MS, 1e-3)):
            for k in keys:
                v = d.get(k)
                if isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v):
                    return float(v) * scale
        stack.extend(v for v in d.values() if isinstance(v, Mapping))
    return None


def _stats(values: Iterable[float]) -> dict[str, float | int | None]:
    a = np.asarray(list(values), float)
    if a.size == 0:
        return {"n": 0, "median": None, "p95": None, "max": None, "mean": None}
    return {
        "n": int(a.size),
        "median": round(float(np.median(a)), 6),
        "p95": round(float(np.percentile(a, 95)), 6),
        "max": round(float(a.max()), 6),
        "mean": round(float(a.mean()), 6),
    }


@dataclasses.dataclass
class _Mesh:
    fit_index: int
    t_ns: int


class StatusBoard:
    """Aggregates bus messages into the live status line (see the module docstring).

    Parameters
    ----------
    t0_ns : int
        Session start, ns (monotonic; the clock of every ``now_ns`` given later).
    alerts : Alerts, optional
        The conditions to watch (default: worker restarts and the other workers' reports
        only, no stream expected).
    """

    def __init__(self, t0_ns: int, alerts: Alerts | None = None):
        self.t0_ns = int(t0_ns)
        self.alerts = alerts if alerts is not None else Alerts(t0_ns)
        self.counts: dict[str, int] = {}
        self._counts_at_line: dict[str, int] = {}
        self._line_ns: int | None = None
        self.rates: dict[str, float] = {}
        self.status: dict[str, dict[str, Any]] = {}
        self.gaps: dict[str, int] = {}
        self.contacts = 0
        self.flagged: int | None = None  # contact events the last fit flags as false
        self.awaiting = 0  # of them, those flagged only for want of a second touch
        self.fit_reliable = True
        self.observations = 0
        self.contact_observations = 0
        self.link_connected: bool | None = None
        self.pilot_events: list[tuple[int, str, str]] = []
        self.failsafes = 0
        self.warnings = 0
        self.errors = 0
        self.refit_s: list[float] = []
        self.refit_parts: dict[str, float] = {}  # mapper.fit timings summed over refits, seconds
        self._last_refit_key: tuple[Any, ...] | None = None
        self.mesh: _Mesh | None = None
        self.mesh_intervals_s: list[float] = []
        self.latencies_s: list[float] = []
        self._contact_t: OrderedDict[int, int] = OrderedDict()  # id -> arrival ns, not yet fitted
        self._fit_new: OrderedDict[int, list[int]] = OrderedDict()  # fit -> newly fitted ids
        self._mesh_t: OrderedDict[int, int] = OrderedDict()  # fit -> mesh arrival ns (no fit yet)

    # -- ingest ---------------------------------------------------------------------------------
    def ingest(self, env: Envelope, now_ns: int) -> list[str]:
        """Take one message received at ``now_ns``; returns lines to print at once (pilot
        faults, warnings and errors from ``log``)."""
        topic, p = env.topic, env.payload
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self.alerts.on_message(env, now_ns)
        if topic == "status":
            self.status[str(p.get("process", "?"))] = dict(p)
            if p.get("process") == "mapper":
                self._refit(p, ("status", p.get("state")))
        elif topic == "link.health":
            self.link_connected = bool(p.get("connected"))
        elif topic == "log":
            level = p.get("level")
            if level in ("warning", "error"):
                self.warnings += level == "warning"
                self.errors += level == "error"
                hint = f" (hint: {p['hint']})" if p.get("hint") else ""
                return [f"{p.get('process', '?')}: {level}: {p.get('message', '')}{hint}"]
        elif topic == "pilot.event":
            kind, text = str(p.get("event", "?")), str(p.get("text", ""))
            self.pilot_events.append((now_ns, kind, text))
            del self.pilot_events[:-1000]
            if kind == "failsafe":
                self.failsafes += 1
            if kind in LOUD_PILOT_EVENTS:
                return [text if text.startswith("!!!") else f"!!! PILOT {kind.upper()}: {text}"]
            return [f"pilot: {kind}: {text}"]
        elif topic == "contact.event":
            self.contacts += p.get("state") == "begin"
        elif topic == "observations":
            self.observations += 1
            if p.get("label") == 0:
                self.contact_observations += 1
                self._contact_t[int(p["id"])] = now_ns
                while len(self._contact_t) > MAX_PENDING:
                    self._contact_t.popitem(last=False)
        elif topic == "mapper.fit":
            self._on_fit(env, now_ns)
        elif topic == "mesh":
            self._on_mesh(int(p.get("fit_index", -1)), now_ns)
        return []

    def _refit(self, payload: Mapping[str, Any], key: tuple[Any, ...]) -> None:
        s = refit_seconds(payload)
        if s is not None:
            k = (*key, s)
            if k != self._last_refit_key:  # a republished status is not a new refit
                self._last_refit_key = k
                self.refit_s.append(s)
                del self.refit_s[:-_MAX_SERIES]

    def _on_fit(self, env: Envelope, now_ns: int) -> None:
        k = int(env.payload.get("fit_index", -1))
        self.fit_reliable = bool(env.payload.get("reliable", True))
        if "flagged_events" in env.payload:
            self.flagged = len(env.payload["flagged_events"])
            self.awaiting = len(env.payload.get("awaiting_events", ()))
        self._refit(env.payload, ("fit", k))
        timings = env.payload.get("timings")
        if isinstance(timings, Mapping):
            for part, s in timings.items():
                if isinstance(s, (int, float)) and not isinstance(s, bool) and math.isfinite(s):
                    self.refit_parts[str(part)] = self.refit_parts.get(str(part), 0.0) + s
        ids = env.arrays.get("ids")
        new = []
        if ids is not None:
            for i in np.asarray(ids).tolist():
                if i in self._contact_t:
                    new.append(i)
        self._fit_new[k] = new
        while len(self._fit_new) > 64:
            self._fit_new.popitem(last=False)
        if k in self._mesh_t:
            self._meshed(k, self._mesh_t.pop(k))

    def _on_mesh(self, k: int, now_ns: int) -> None:
        if self.mesh is not None and now_ns > self.mesh.t_ns:
            self.mesh_intervals_s.append((now_ns - self.mesh.t_ns) / 1e9)
            del self.mesh_intervals_s[:-_MAX_SERIES]
        self.mesh = _Mesh(k, now_ns)
        if k in self._fit_new:
            self._meshed(k, now_ns)
        else:
            self._mesh_t[k] = now_ns
            while len(self._mesh_t) > 64:
                self._mesh_t.popitem(last=False)

    def _meshed(self, k: int, mesh_ns: int) -> None:
        for i in self._fit_new.pop(k, []):
            t = self._contact_t.pop(i, None)
            if t is not None and mesh_ns >= t:
                self.latencies_s.append((mesh_ns - t) / 1e9)
        del self.latencies_s[:-_MAX_SERIES]

    def on_worker(self, name: str, kind: str, restarts: int, detail: str, now_ns: int) -> None:
        """A supervisor event (started, exited, restarting, gave_up) at ``now_ns``."""
        self.alerts.on_worker(name, kind, restarts, detail, now_ns)

    def set_gaps(self, gaps: Mapping[str, int]) -> None:
        """The monitor subscriber's own gap counts per topic."""
        self.gaps = {k: int(v) for k, v in gaps.items()}

    # -- render --------------------------------------------------------------------------------
    def recorder_status(self) -> dict[str, Any]:
        """The status of the recorder that writes (of an active/standby pair), or {}."""
        recs = {
            n: st
            for n, st in self.status.items()
            if n.startswith("recorder") or "recording" in st.get("topics", {})
        }
        for st in recs.values():
            if st.get("topics", {}).get("recording", {}).get("role", "active") == "active":
                return st
        return recs.get("recorder", next(iter(recs.values()), {}))

    def _recorder_gaps(self, latest: bool) -> int:
        rec = self.recorder_status().get("topics", {})
        return sum(
            int(v.get("gaps", 0))
            for k, v in rec.items()
            if isinstance(v, dict) and k in TOPICS and (k in _LATEST) == latest
        )

    @property
    def recorder_gaps(self) -> int:
        """Sequence gaps the recorder reports on lossless topics (faults)."""
        return self._recorder_gaps(latest=False)

    @property
    def recorder_latest_drops(self) -> int:
        """Superseded messages of latest-value topics (mesh, status, ...) the recorder did not
        get: dropped by design at the high-water mark, shown but not counted as gaps."""
        return self._recorder_gaps(latest=True)

    @property
    def monitor_gaps(self) -> int:
        """Sequence gaps the monitor itself saw on lossless topics (latest-value topics drop by
        design: not counted)."""
        return sum(v for k, v in self.gaps.items() if k not in _LATEST)

    def pilot_text(self, alive: Mapping[str, bool]) -> str | None:
        """The pilot part of the line (None when no pilot process runs)."""
        if "pilot" not in alive and "pilot" not in self.status:
            return None
        if not alive.get("pilot", True):
            return "!!! PILOT PROCESS DOWN - NOT SENDING - vehicle failsafe in charge !!!"
        st = self.status.get("pilot")
        if st is None:
            return "pilot: starting"
        return str(st.get("text") or f"PILOT: {st.get('state')}")

    def line(
        self, now_ns: int, alive: Mapping[str, bool] | None = None, final: bool = False
    ) -> str:
        """One status line at ``now_ns``; rates are over the time since the previous line.
        ``final``: the line after every worker stopped (no stream or link is expected then)."""
        alive = dict(alive or {})
        dt = None if self._line_ns is None else (now_ns - self._line_ns) / 1e9
        for topic, _ in RATE_STREAMS:
            n = self.counts.get(topic, 0) - self._counts_at_line.get(topic, 0)
            self.rates[topic] = n / dt if dt else 0.0
        self._counts_at_line, self._line_ns = dict(self.counts), now_ns
        parts: list[str] = []
        pilot = self.pilot_text(alive)
        loud = pilot is not None and pilot.startswith("!!!")
        if loud:
            parts.append(pilot)
        parts.append(f"t={(now_ns - self.t0_ns) / 1e9:6.1f} s")
        for topic, short in RATE_STREAMS:
            if topic == "pilot.command" and pilot is None:
                continue
            parts.append(f"{short} {self.rates[topic]:5.1f} Hz")
        gaps = self.monitor_gaps
        rec_gaps = self.recorder_gaps if self.recorder_status() else None
        word = "GAPS" if (gaps or rec_gaps) else "gaps"  # loud when anything was lost
        parts.append(f"{word} {gaps}" + ("" if rec_gaps is None else f"/{rec_gaps} rec"))
        if rec_gaps is not None and self.recorder_latest_drops:
            parts.append(f"(rec skipped {self.recorder_latest_drops} superseded)")
        parts.append(
            f"contacts {self.contacts}"
            + ("" if self.flagged is None else f" ({self.flagged} flagged)")
        )
        if self.flagged and self.awaiting:
            parts.append(f"{self.awaiting} awaiting a second touch")
        parts.append(f"obs {self.observations}")
        if self.refit_s:
            parts.append(f"refit {self.refit_s[-1]:.2f} s")
        if not self.fit_reliable:
            parts.append("FIT UNRELIABLE (last good mesh kept)")
        if self.mesh is not None:
            age = (now_ns - self.mesh.t_ns) / 1e9
            parts.append(f"mesh #{self.mesh.fit_index} age {age:.1f} s")
        elif "mapper" in alive:
            parts.append("mesh none")
        no_device = self.status.get("link", {}).get("state") in ("no_device", "disconnected")
        if self.link_connected is False and not final and not no_device:
            parts.append("LINK DISCONNECTED")  # (the link's own state says more when it has one)
        rec = self.recorder_status().get("topics", {}).get("recording")
        if rec:
            parts.append(f"rec {rec.get('bytes_written', 0) / 1e6:.1f} MB")
            if rec.get("dropped"):
                parts.append(f"REC DROPPED {rec['dropped']}")
        if pilot is not None and not loud:
            parts.append(pilot)
        if not final:
            parts += self.alerts.update(now_ns, alive)
        restarts = {n: w["restarts"] for n, w in self.alerts.workers.items() if w["restarts"]}
        note = "; restarts " + ", ".join(f"{n} {k}" for n, k in sorted(restarts.items()))
        if alive:
            down = [n for n, up in alive.items() if not up]
            state = ("DOWN: " + ", ".join(down)) if down else "all up"
            parts.append("[" + state + (note if restarts else "") + "]")
        return "  ".join(parts)

    def refit_time(self) -> dict[str, dict[str, float]]:
        """Where the refits' time went: each part the mapper reports (``mapper.fit``
        ``timings``), summed over the session, seconds and share of the summed total."""
        total = self.refit_parts.get("total_s", 0.0)
        return {
            part.removesuffix("_s"): {
                "sum_s": round(s, 3),
                "share": round(s / total, 3) if total > 0 else math.nan,
            }
            for part, s in sorted(self.refit_parts.items())
        }

    def summary(self) -> dict[str, Any]:
        """Measured numbers of the session (for the closing note and the soak test), every
        condition the status line showed (``events``: when, how long) and what data was lost
        (``data_loss``)."""
        link = self.status.get("link", {}).get("topics", {}).get("pilot.command", {})
        return {
            "duration_s": None if self._line_ns is None else (self._line_ns - self.t0_ns) / 1e9,
            "counts": dict(sorted(self.counts.items())),
            "gaps_monitor": self.monitor_gaps,
            "gaps_recorder": self.recorder_gaps,
            "recorder_latest_dropped": self.recorder_latest_drops,
            "gaps_by_topic": dict(sorted(self.gaps.items())),
            "contacts": self.contacts,
            "contacts_flagged": self.flagged,
            "contacts_awaiting": self.awaiting,
            "observations": self.observations,
            "contact_observations": self.contact_observations,
            "refit_s": _stats(self.refit_s),
            "refit_time_s": self.refit_time(),
            "mesh_interval_s": _stats(self.mesh_intervals_s),
            "contact_to_mesh_s": _stats(self.latencies_s),
            "meshes": self.counts.get("mesh", 0),
            "pilot_failsafes": self.failsafes,
            "manual_control_sent": link.get("manual_control_sent"),
            "manual_control_stale_dropped": link.get("stale_dropped"),
            "manual_control_unsent": link.get("unsent"),
            "warnings": self.warnings,
            "errors": self.errors,
            "restarts": {n: w["restarts"] for n, w in sorted(self.alerts.workers.items())},
            "link_lost_frames": self.alerts.lost_frames,
            "events": [dict(e) for e in self.alerts.events],
            "data_loss": self.alerts.data_loss(),
        }
