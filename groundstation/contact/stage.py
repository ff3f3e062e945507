"""The detector stage (pure): sample envelopes in, observation and contact-event envelopes out.

One class, two shells: :class:`ContactStage` runs inside the detector process
(``groundstation.runtime.workers.detector``) and inside the offline pipeline
(``groundstation.pipeline.offline``), so both produce the same contact events from the same log.

Pairing (time axis: ``t_station_ns`` of each sample, see ``acquisition/decoders.py``)
------------------------------------------------------------------------------------
Every IMU sample at station time t is paired with

* the attitude at t: slerp between the two ``samples.attitude`` that bracket t (a
  :class:`~groundstation.sync.aligner.PoseBuffer` holding orientations, ``attitude_max_gap_s``);
* the mocap position at t: linear interpolation between the two ``samples.pose`` of the tracked
  rigid body that bracket t (``pose_max_gap_s``; invalid poses are not inserted), else no pose.

Ordering rule (why the result never depends on how the topics interleave on arrival)
------------------------------------------------------------------------------------
Each stream's *watermark* is the newest ``t_station_ns`` of a sample its buffer accepted.
Invalid poses (tracking lost) and rejected samples do not advance it: an invalid pose just after
t says nothing about the valid pose that will bracket t, so releasing on it would make the
result depend on arrival order. IMU samples wait in a queue and are released, oldest first,
only when

1. both the attitude and the pose watermarks have reached their time t (so both bracketing
   samples are present and the interpolation is final), or
2. the IMU watermark has passed ``t + max_wait_s`` (bounded wait, in *data* time: a pose stream
   that is silent - no mocap, a CSV import without positions - cannot stall detection), or
3. :meth:`ContactStage.flush` is called at the end of the data.

Within each stream messages arrive in order (one ZeroMQ connection never reorders). Under rule
1 the bracketing samples of t are present whatever the interleaving, and a look-up at t never
uses anything newer; under rule 2 the pose look-up at t > pose watermark is ``NoPose("after")``
whatever arrived before (the aligner never extrapolates); a valid pose newer than t that arrives
later than that lies more than ``max_wait_s`` after t, so the bracketing gap exceeds
``pose_max_gap_s`` (which must stay below ``max_wait_s``) and the answer is "no pose" either way.
So the output is a function of the streams alone, provided no stream lags another by more
than ``max_wait_s`` of data time on arrival. The replay source publishes every stream from one
process in log order, and the live link/mocap processes publish within milliseconds, far inside
the default 0.25 s.

Output envelopes carry per-topic sequence numbers from 0 (origin 0), as a fresh publisher would
number them; the process shell republishes their payload through its own publisher.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from collections.abc import Iterable

import numpy as np

from groundstation.bus.envelope import Envelope, Header
from groundstation.bus.topics import TOPICS
from groundstation.contact.detector import (
    ContactDetector,
    ContactEvent,
    Observation,
    earth_acceleration,
)
from groundstation.contact.impulse import ImpulseDetector, tilt_cos
from groundstation.contact.settings import AlignmentSettings, ContactSettings
from groundstation.contact.vehicle import VehicleSettings
from groundstation.sync.aligner import PoseBuffer

INPUT_TOPICS = ("samples.imu", "samples.attitude", "samples.pose")
OUTPUT_TOPICS = ("observations", "contact.event")
_NAN3 = np.full(3, np.nan)
_ZERO3 = np.zeros(3)


@dataclasses.dataclass
class StageStats:
    """Counters of one stage (cumulative)."""

    imu: int = 0
    attitude: int = 0
    pose: int = 0
    bad: int = 0  # malformed envelopes / unknown topics (skipped)
    late: int = 0  # IMU samples not after the previous one (skipped)
    released_on_time: int = 0  # rule 1
    released_by_wait: int = 0  # rule 2
    released_at_flush: int = 0  # rule 3
    no_attitude: int = 0  # IMU samples dropped: no attitude at their time
    no_pose: int = 0  # IMU samples processed without a position
    observations: int = 0
    events: int = 0
    at_floor: int = 0  # candidates rejected because they began with the body at the floor
    upset_rejected: int = 0  # ... because they began with the body tilted past the line
    tilted: int = 0  # free-space samples not taken: the body was tilted past the limit
    upset_ms: int = 0  # data time with the body tilted past UPSET_TILT_DEG (a flip, a crash)
    upset_first_ns: int = -1  # data time of the first such sample (-1: none)

    def as_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)


#: A body tilted further than this from level is *upset*: flipped by an impact, or down after a
#: crash. Level flight stays under ~40 deg (the 99th percentile of the tilt is 20-38 deg on every
#: evaluation flight that neither crashed nor flew the aggressive 'free' pilot); the stage
#: counts the data time past it (``StageStats.upset_ms``), which report.html and the benches
#: show, so a crashed flight is known as one.
UPSET_TILT_DEG = 60.0
#: ... as the cosine of the angle between the thrust axis and the vertical (``tilt_cos``).
UPSET_COS = math.cos(math.radians(UPSET_TILT_DEG))
#: The longest step between two IMU samples counted as upset time (a gap counts this much).
_UPSET_MAX_STEP_NS = 100_000_000

#: A buffer of attitudes or poses is trimmed (by time) once it holds this many entries...
_TRIM_AT = 8192
#: ... and never holds more than this (11 minutes of 200 Hz mocap, about 40 MB): the backstop of
#: a detector that has fallen that far behind, or of a session whose IMU never arrives.
_CAPACITY = 1 << 17


def _t_station(env: Envelope) -> int:
    t = env.payload.get("t_station_ns")
    return int(env.header.source_ns if t is None else t)


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def observation_payload(obs: Observation) -> tuple[dict, dict[str, np.ndarray]]:
    """``observations`` payload and arrays of one :class:`Observation`."""
    payload = {
        "id": int(obs.id),
        "label": int(obs.label),
        "event_id": int(obs.event_id),
        "accel_g": float(obs.accel_g),
    }
    if obs.label != 1 and np.isfinite(obs.p_false):
        payload.update(
            p_false=float(obs.p_false),
            dv_mps=_finite_or_none(obs.dv_mps),
            rebound=bool(obs.rebound),
            sigma_m=_finite_or_none(obs.sigma_m),
        )
    arrays = {
        "x_m": np.asarray(obs.position, dtype=np.float64).reshape(3),
        "normal": np.asarray(obs.normal, dtype=np.float64).reshape(3),
    }
    return payload, arrays


def observation_from_envelope(env: Envelope) -> Observation:
    """Inverse of :func:`observation_payload`; ``t_ns`` is the header's ``source_ns``.

    Raises
    ------
    KeyError, ValueError
        On a malformed message (the caller counts and skips it).
    """
    p, a = env.payload, env.arrays
    x = np.array(a["x_m"], dtype=np.float64).reshape(3)
    n = np.array(a["normal"], dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(x)):
        raise ValueError(f"observation {p.get('id')} has a non-finite position {x}")
    return Observation(
        id=int(p["id"]),
        t_ns=int(env.header.source_ns),
        position=x,
        label=float(p["label"]),
        normal=n,
        event_id=int(p.get("event_id", -1)),
        accel_g=float(p.get("accel_g", 0.0)),
        p_false=_float(p.get("p_false")),
        dv_mps=_float(p.get("dv_mps")),
        rebound=bool(p.get("rebound", False)),
        sigma_m=_float(p.get("sigma_m")),
    )


def _float(v) -> float:
    return float("nan") if v is None else float(v)


def event_payload(ev: ContactEvent, state: str) -> dict:
    """``contact.event`` payload of a detector event (``state``: begin, end or rejected)."""
    payload = {"id": int(ev.id), "state": state, "peak_g": float(ev.peak_g)}
    if ev.features is not None:
        f = ev.features
        payload.update(
            p_false=float(ev.p_false),
            p_false_impulse=float(ev.p_false_impulse),
            dv_mps=float(f.dv_imu_mps),
            rebound=bool(f.rebound),
            features=f.as_dict(),
        )
    if math.isfinite(ev.floor_clearance_m):
        payload.update(floor_clearance_m=float(ev.floor_clearance_m), at_floor=bool(ev.at_floor))
    if math.isfinite(ev.tilt_deg):
        payload.update(tilt_deg=float(ev.tilt_deg), upset=bool(ev.upset))
    return payload


class ContactStage:
    """Sample envelopes -> observation and contact-event envelopes (see the module docstring).

    Parameters
    ----------
    settings : ContactSettings
        Detector settings.
    alignment : AlignmentSettings
        Pairing settings.
    first_id : int
        Id of the first observation.
    """

    def __init__(
        self,
        settings: ContactSettings | None = None,
        alignment: AlignmentSettings | None = None,
        first_id: int = 0,
        vehicle: VehicleSettings | None = None,
        batch: int = 1,
    ) -> None:
        self.settings = s = settings or ContactSettings()
        self.alignment = al = alignment or AlignmentSettings()
        self.vehicle = vehicle or VehicleSettings()
        if s.detector == "impulse":
            self.detector = ImpulseDetector(s, self.vehicle, first_id=first_id, batch=batch)
        else:
            self.detector = ContactDetector(s, first_id=first_id)
        self._events_out = 0
        # trimmed by time behind the oldest queued IMU sample (:meth:`_trim`), never by count
        # while the IMU still needs them: a detector that falls behind live data reads the pose
        # stream ahead of the IMU stream (the bus serves its publishers in turn), and a
        # count-bounded buffer then dropped the very poses its queued IMU samples needed
        self._att = PoseBuffer(max_gap_ns=int(al.attitude_max_gap_s * 1e9), capacity=_CAPACITY)
        self._pose = PoseBuffer(max_gap_ns=int(al.pose_max_gap_s * 1e9), capacity=_CAPACITY)
        self._body = None if al.body_id < 0 else int(al.body_id)
        self._wait_ns = int(al.max_wait_s * 1e9)
        self._queue: collections.deque[tuple[int, np.ndarray]] = collections.deque()
        self._wm = {"imu": None, "attitude": None, "pose": None}
        self._seq = dict.fromkeys(OUTPUT_TOPICS, 0)
        self._last_imu: int | None = None
        self._last_processed: int | None = None  # IMU time of the last sample processed
        self._upset_ns = 0
        self.stats = StageStats()

    # -- input ---------------------------------------------------------------------------------
    def push(self, env: Envelope) -> list[Envelope]:
        """Take one sample envelope; return the output envelopes it released (data-time order).

        Malformed envelopes and other topics are counted in ``stats.bad`` and skipped.
        """
        try:
            self._ingest(env)
        except (KeyError, ValueError, TypeError, IndexError):
            self.stats.bad += 1
            return []
        return self._release(final=False)

    def push_many(self, envs: Iterable[Envelope]) -> list[Envelope]:
        """:meth:`push` each envelope; the concatenated outputs."""
        out: list[Envelope] = []
        for env in envs:
            out += self.push(env)
        return out

    def flush(self) -> list[Envelope]:
        """End of data: release every queued IMU sample (rule 3), then let an impulse detector
        decide what it still holds."""
        out = self._release(final=True)
        if isinstance(self.detector, ImpulseDetector):
            out += self._impulse_outputs(self.detector.flush())
        return out

    @property
    def pending(self) -> int:
        """IMU samples waiting for their attitude/pose."""
        return len(self._queue)

    def _mark(self, stream: str, t: int) -> None:
        wm = self._wm[stream]
        if wm is None or t > wm:
            self._wm[stream] = t

    def _ingest(self, env: Envelope) -> None:
        topic, a = env.topic, env.arrays
        if topic == "samples.imu":
            t = _t_station(env)
            acc = np.array(a["accel_mps2"], dtype=np.float64).reshape(3)
            self.stats.imu += 1
            if self._last_imu is not None and t <= self._last_imu:
                self.stats.late += 1
                return
            self._last_imu = t
            self._queue.append((t, acc))
            self._mark("imu", t)
        elif topic == "samples.attitude":
            t = _t_station(env)
            self.stats.attitude += 1
            if self._att.insert(t, _ZERO3, np.asarray(a["q_wxyz"], dtype=np.float64)):
                self._mark("attitude", t)
                if len(self._att) > _TRIM_AT:
                    self._trim()
        elif topic == "samples.pose":
            body = int(env.payload["body_id"])
            if self._body is None:
                self._body = body
            if body != self._body:
                return
            t = _t_station(env)
            self.stats.pose += 1
            if env.payload.get("valid", True) and self._pose.insert(
                t, a["position_m"], a["q_wxyz"]
            ):
                self._mark("pose", t)
                if len(self._pose) > _TRIM_AT:
                    self._trim()
        else:
            raise KeyError(topic)

    # -- release -------------------------------------------------------------------------------
    def _release(self, final: bool) -> list[Envelope]:
        out: list[Envelope] = []
        wm = self._wm
        while self._queue:
            t, acc = self._queue[0]
            if (
                wm["attitude"] is not None
                and wm["attitude"] >= t
                and (wm["pose"] is not None and wm["pose"] >= t)
            ):
                self.stats.released_on_time += 1
            elif wm["imu"] - t >= self._wait_ns:
                self.stats.released_by_wait += 1
            elif final:
                self.stats.released_at_flush += 1
            else:
                break
            self._queue.popleft()
            out += self._process(t, acc)
        if out or final:
            self._trim()
        return out

    def _trim(self) -> None:
        """Forget attitudes and poses more than 1 s older than the oldest IMU sample that may
        still need them (the queue's head, or the newest IMU sample when none is queued; none
        before the first IMU sample, whose time is unknown until it arrives)."""
        wm = self._wm["imu"]
        if self._queue:
            keep = self._queue[0][0] - 1_000_000_000
        elif wm is not None:
            keep = wm - 1_000_000_000
        else:
            return
        self._att.drop_before(keep)
        self._pose.drop_before(keep)

    def _count_upset(self, t: int, q: np.ndarray) -> None:
        """Add the step since the last processed sample to ``upset_ms`` when the body is
        tilted past ``UPSET_TILT_DEG`` at ``t`` (attitude ``q``, w x y z FRD -> NED)."""
        prev, self._last_processed = self._last_processed, t
        if not tilt_cos(q) < UPSET_COS:  # level enough, or an unknown attitude
            return
        if self.stats.upset_first_ns < 0:
            self.stats.upset_first_ns = t
        if prev is not None:
            self._upset_ns += min(max(t - prev, 0), _UPSET_MAX_STEP_NS)
            self.stats.upset_ms = self._upset_ns // 1_000_000

    def _process(self, t: int, acc: np.ndarray) -> list[Envelope]:
        att = self._att.at(t)
        if not att:
            self.stats.no_attitude += 1
            return []
        self._count_upset(t, att.quaternion)
        pose = self._pose.at(t)
        if not pose:
            self.stats.no_pose += 1
        det = self.detector
        if isinstance(det, ImpulseDetector):
            return self._impulse_outputs(
                det.update(t, acc, att.quaternion, pose.position if pose else None)
            )
        was_in, n_events = det.in_contact, det.stats.contacts
        obs = det.update(
            t, earth_acceleration(acc, att.quaternion), pose.position if pose else None
        )
        out: list[Envelope] = []
        if det.stats.contacts > n_events:  # a contact began at this sample
            ev = det.open_event
            pos = _NAN3 if ev.position is None else ev.position
            out.append(self._event_env("begin", ev.id, ev.peak_g, pos, ev.normal, t))
        elif was_in and not det.in_contact:  # a contact ended at this sample
            ev = det.events[-1]
            pos = _NAN3 if ev.position is None else ev.position
            out.append(self._event_env("end", ev.id, ev.peak_g, pos, ev.normal, t))
        for o in obs:
            payload, arrays = observation_payload(o)
            out.append(self._env("observations", payload, arrays, o.t_ns))
        self.stats.observations += len(obs)
        return out

    def _impulse_outputs(self, obs: list[Observation]) -> list[Envelope]:
        """Event messages of the impulses the detector closed, then their observations."""
        out: list[Envelope] = []
        events = self.detector.events
        for ev in events[self._events_out :]:
            pos = _NAN3 if ev.position is None else ev.position
            states = (("rejected", ev.t_start_ns),) if ev.rejected else (
                ("begin", ev.t_start_ns), ("end", ev.t_end_ns)
            )  # fmt: skip
            self.stats.at_floor += ev.at_floor
            self.stats.upset_rejected += ev.upset
            for state, t in states:
                self.stats.events += state == "begin"
                out.append(self._env("contact.event", event_payload(ev, state), {
                    "position_m": np.array(pos, dtype=np.float64).reshape(3),
                    "normal": np.array(ev.normal, dtype=np.float64).reshape(3),
                }, t))  # fmt: skip
        self._events_out = len(events)
        self.stats.tilted = self.detector.stats.tilted
        for o in obs:
            payload, arrays = observation_payload(o)
            out.append(self._env("observations", payload, arrays, o.t_ns))
        self.stats.observations += len(obs)
        return out

    def _event_env(self, state, ev_id, peak_g, position, normal, t) -> Envelope:
        self.stats.events += state == "begin"
        payload = {"id": int(ev_id), "state": state, "peak_g": float(peak_g)}
        arrays = {
            "position_m": np.array(position, dtype=np.float64).reshape(3),
            "normal": np.array(normal, dtype=np.float64).reshape(3),
        }
        return self._env("contact.event", payload, arrays, t)

    def _env(self, topic: str, payload: dict, arrays: dict, t: int) -> Envelope:
        spec = TOPICS[topic]
        seq = self._seq[topic]
        self._seq[topic] = seq + 1
        return Envelope(
            topic, Header(spec.type, spec.schema_version, seq, int(t), 0, 0), payload, arrays
        )
