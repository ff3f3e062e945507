"""Bus envelopes -> Foxglove well-known-schema messages (pure; no I/O, no clock).

:class:`FoxgloveTranslator` takes the station's bus messages in log order (live: as the recorder
receives them; replay: the decoded samples and the pipeline's results) and returns the Foxglove
protobuf messages of :mod:`~groundstation.openformats.channels` that they produce. It keeps what
a view needs between messages: the detector signal's filter, the contact points and their
states, the flown path. Unknown topics translate to nothing.

Rates: the detector signal follows every IMU sample (200 Hz live); IMU, attitude, pose and
``/tf`` are thinned to ``sample_rate_hz`` (50 Hz: plenty for plots and the 3D view, and it
halves the cost of writing them; the raw bytes keep every sample); the trajectory is re-sent
at most once per ``trajectory_period_s`` of data time and the contact cloud at most once per
``contacts_period_s`` (and after every fit); :meth:`finish` sends the last state of both.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from groundstation.bus.envelope import Envelope
from groundstation.contact.settings import AlignmentSettings, ContactSettings
from groundstation.openformats.channels import CHANNELS, message_class
from groundstation.openformats.signal import DetectorSignal
from groundstation.openformats.state import ContactBook, Trajectory
from groundstation.viewer.scene import STATE_COLORS

WORLD, BODY, NED = "world", "body", "ned"
_LEVELS = {"debug": 1, "info": 2, "warning": 3, "error": 4, "fatal": 5}


@dataclasses.dataclass(frozen=True)
class FoxgloveMessage:
    """One serialized Foxglove message and where it goes.

    Attributes
    ----------
    topic : str
        A topic of :data:`~groundstation.openformats.channels.CHANNELS`.
    data : bytes
        Protobuf encoding of the channel's schema.
    log_time_ns, publish_time_ns : int
        MCAP times, ns on the recording's log axis.
    """

    topic: str
    data: bytes
    log_time_ns: int
    publish_time_ns: int

    @property
    def schema(self) -> str:
        return CHANNELS[self.topic].schema


@dataclasses.dataclass(frozen=True)
class TranslatorSettings:
    """How often growing state is re-sent, seconds of data time, how the path is thinned, and
    the rate of the IMU / attitude / pose channels (None: every sample)."""

    sample_rate_hz: float | None = 50.0
    trajectory_period_s: float = 1.0
    contacts_period_s: float = 0.5
    trajectory_spacing_m: float = 0.05
    trajectory_max_points: int = 2000


_CLASSES: dict[str, Any] = {}


def _pb(schema: str):
    cls = _CLASSES.get(schema)
    if cls is None:
        cls = _CLASSES[schema] = message_class(schema)
    return cls


def _stamp(msg: Any, t_ns: int) -> None:
    msg.timestamp.FromNanoseconds(int(t_ns))


def _identity_pose(pose: Any) -> None:
    pose.orientation.w = 1.0


def _set_pose(pose: Any, position, q_wxyz) -> None:
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in position)
    o = pose.orientation
    o.w, o.x, o.y, o.z = (float(v) for v in q_wxyz)


def _kv(entity: Any, key: str, value: Any) -> None:
    entity.metadata.add(key=key, value=str(value))


def _fmt3(v: np.ndarray) -> str:
    return "(" + ", ".join(f"{float(x):.3f}" for x in np.asarray(v).reshape(-1)) + ")"


class FoxgloveTranslator:
    """Bus messages in, Foxglove messages out (module docstring).

    Parameters
    ----------
    contact : ContactSettings
        The detector's settings (signal filter and threshold).
    alignment : AlignmentSettings
        Attitude pairing of the signal.
    settings : TranslatorSettings
    keep_signal : bool
        Also keep every ``(t_ns, filtered |a| in G)`` in :attr:`signal_series` (replay reports).
    """

    def __init__(
        self,
        contact: ContactSettings | None = None,
        alignment: AlignmentSettings | None = None,
        settings: TranslatorSettings | None = None,
        *,
        keep_signal: bool = False,
    ) -> None:
        self.settings = s = settings or TranslatorSettings()
        self.signal = DetectorSignal(contact, alignment)
        self.signal_series: list[tuple[int, float]] | None = [] if keep_signal else None
        self.contacts = ContactBook()
        self.trajectory = Trajectory(s.trajectory_spacing_m, s.trajectory_max_points)
        self._body_id: int | None = None
        self._event_begin: dict[int, int] = {}
        self._event_info: dict[int, tuple[float, np.ndarray, np.ndarray, float | None]] = {}
        self._due = {"imu": -(2**62), "attitude": -(2**62), "pose": -(2**62)}
        self._period = 0 if s.sample_rate_hz is None else int(1e9 / s.sample_rate_hz)
        self._traj_sent = (0, -(2**62))  # (version, data time)
        self._contacts_sent = (0, -(2**62))
        self._last_t = 0
        self.counts: dict[str, int] = {}
        self.bad = 0

    # -- entry points --------------------------------------------------------------------------
    def translate(self, env: Envelope, log_time_ns: int | None = None) -> list[FoxgloveMessage]:
        """The Foxglove messages one bus message produces (empty for topics it does not use).

        Parameters
        ----------
        env : Envelope
            A bus message (decoded).
        log_time_ns : int, optional
            Its log time in the recording; default: the header's receive time, else its
            source time.
        """
        h = env.header
        log_t = int(log_time_ns if log_time_ns is not None else (h.recv_ns or h.source_ns))
        try:
            out = self._dispatch(env.topic, env.payload, env.arrays, int(h.source_ns), log_t)
        except (KeyError, ValueError, TypeError, IndexError):
            self.bad += 1
            return []
        for m in out:
            self.counts[m.topic] = self.counts.get(m.topic, 0) + 1
        return out

    def finish(self) -> list[FoxgloveMessage]:
        """End of data: the signal still queued, the last trajectory and contact cloud."""
        t = self._last_t
        out = self._signal(self.signal.flush(), t)
        out += self._trajectory(t, force=True)
        out += self._contacts(t, force=True)
        for m in out:
            self.counts[m.topic] = self.counts.get(m.topic, 0) + 1
        return out

    # -- dispatch ------------------------------------------------------------------------------
    def _dispatch(
        self, topic: str, p: Mapping[str, Any], a: Mapping[str, np.ndarray], src: int, log_t: int
    ) -> list[FoxgloveMessage]:
        self._last_t = max(self._last_t, log_t)
        if topic == "samples.imu":
            return self._imu(p, a, src, log_t)
        if topic == "samples.attitude":
            t = int(p.get("t_station_ns", src))
            out = [self._attitude(a, t, log_t)] if self._take("attitude", t) else []
            return out + self._signal(self.signal.push_attitude(t, a["q_wxyz"]), log_t)
        if topic == "samples.pose":
            return self._pose(p, a, src, log_t)
        if topic == "observations":
            self.contacts.add_observation(
                p["id"], p["label"], a["x_m"], p.get("event_id", -1), p.get("p_false")
            )
            return self._contacts(src, force=False)
        if topic == "contact.event":
            return self._event(p, a, src, log_t)
        if topic == "mapper.fit":
            return self._fit(p, a, src, log_t)
        if topic == "mesh":
            return [self._mesh(p, a, src, log_t)]
        if topic == "log":
            level = _LEVELS.get(str(p.get("level", "info")), 0)
            text = str(p["message"]) + (f" (hint: {p['hint']})" if p.get("hint") else "")
            return [self._log(level, str(p.get("process", "")), text, src, log_t)]
        if topic == "status":
            text = f"[{p.get('state')}] {p.get('text') or ''}".rstrip()
            return [self._log(2, str(p.get("process", "")), text, src, log_t)]
        return []

    def _take(self, stream: str, t: int) -> bool:
        """Thin a sample stream to ``sample_rate_hz`` of data time."""
        due = self._due[stream]
        if t < due - 2 * self._period:  # time went back (a new replay): restart
            due = t
        if t < due:
            return False
        nxt = due + self._period  # a grid of due times; resynchronised after a gap
        self._due[stream] = nxt if nxt > t else t + self._period
        return True

    def _msg(self, topic: str, pb: Any, log_t: int, pub_t: int) -> FoxgloveMessage:
        return FoxgloveMessage(topic, pb.SerializeToString(), int(log_t), int(pub_t))

    def _vector3(self, topic: str, xyz, t: int, log_t: int) -> FoxgloveMessage:
        x, y, z = (float(c) for c in xyz)
        return self._msg(topic, _pb("foxglove.Vector3")(x=x, y=y, z=z), log_t, t)

    def _log(self, level: int, name: str, text: str, t: int, log_t: int) -> FoxgloveMessage:
        m = _pb("foxglove.Log")(level=level, message=text, name=name)
        _stamp(m, t)
        return self._msg("/log", m, log_t, t)

    # -- samples -------------------------------------------------------------------------------
    def _imu(self, p, a, src: int, log_t: int) -> list[FoxgloveMessage]:
        t = int(p.get("t_station_ns", src))
        out = []
        if self._take("imu", t):
            out = [
                self._vector3("/imu/accel", np.asarray(a["accel_mps2"]).reshape(3).tolist(), t,
                              log_t),
                self._vector3("/imu/gyro", np.asarray(a["gyro_radps"]).reshape(3).tolist(), t,
                              log_t),
            ]  # fmt: skip
        return out + self._signal(self.signal.push_imu(t, a["accel_mps2"]), log_t)

    def _signal(self, values: list[tuple[int, float]], log_t: int) -> list[FoxgloveMessage]:
        thr, rel = self.signal.threshold_g, self.signal.release_g
        if self.signal_series is not None:
            self.signal_series += values
        # A sample is released by a later message: it goes on the log axis at its own data time,
        # so the signal lines up with the events and the IMU channels.
        return [self._vector3("/detector/signal", (g, thr, rel), t, t) for t, g in values]

    def _attitude(self, a, t: int, log_t: int) -> FoxgloveMessage:
        m = _pb("foxglove.PoseInFrame")(frame_id=NED)
        _stamp(m, t)
        _set_pose(m.pose, (0.0, 0.0, 0.0), np.asarray(a["q_wxyz"]).reshape(4).tolist())
        return self._msg("/vehicle/attitude", m, log_t, t)

    def _pose(self, p, a, src: int, log_t: int) -> list[FoxgloveMessage]:
        body = int(p.get("body_id", 0))
        if self._body_id is None:
            self._body_id = body
        if body != self._body_id or not p.get("valid", True):
            return []
        pos = np.asarray(a["position_m"], dtype=np.float64).reshape(3).tolist()
        q = np.asarray(a["q_wxyz"], dtype=np.float64).reshape(4).tolist()
        if not all(math.isfinite(v) for v in (*pos, *q)):
            return []
        t = int(p.get("t_station_ns", src))
        self.trajectory.add(t, pos)
        if not self._take("pose", t):
            return self._trajectory(t, force=False, log_t=log_t)
        pose = _pb("foxglove.PoseInFrame")(frame_id=WORLD)
        _stamp(pose, t)
        _set_pose(pose.pose, pos, q)
        tf = _pb("foxglove.FrameTransform")(parent_frame_id=WORLD, child_frame_id=BODY)
        _stamp(tf, t)
        tf.translation.x, tf.translation.y, tf.translation.z = pos
        tf.rotation.w, tf.rotation.x, tf.rotation.y, tf.rotation.z = q
        out = [self._msg("/vehicle/pose", pose, log_t, t), self._msg("/tf", tf, log_t, t)]
        return out + self._trajectory(t, force=False, log_t=log_t)

    # -- derived -------------------------------------------------------------------------------
    def _event(self, p, a, src: int, log_t: int) -> list[FoxgloveMessage]:
        ev_id, state, peak = int(p["id"]), str(p["state"]), float(p["peak_g"])
        p_false = p.get("p_false")
        pos = np.asarray(a["position_m"], dtype=np.float64).reshape(3)
        normal = np.asarray(a["normal"], dtype=np.float64).reshape(3)
        self.contacts.add_event(ev_id, state, p_false)
        out = [self._vector3("/detector/event_peak", (peak, ev_id, state == "begin"), src, log_t)]
        extra = "" if p_false is None else f", p_false {float(p_false):.2f}"
        where = "no position" if not np.all(np.isfinite(pos)) else f"vehicle at {_fmt3(pos)} m"
        out.append(
            self._log(2, "detector", f"contact {ev_id} {state}: peak {peak:.2f} G, {where}{extra}",
                      src, log_t)
        )  # fmt: skip
        if state == "begin":
            self._event_begin[ev_id] = src
        else:
            start = self._event_begin.pop(ev_id, src)
            ev = _pb("foxglove.Event")()
            ev.start_time.FromNanoseconds(int(start))
            ev.end_time.FromNanoseconds(int(src))
            kind = "rejected" if state == "rejected" else "contact"
            for key, value in (("id", ev_id), ("state", kind), ("peak_g", f"{peak:.3f}"),
                               ("position_m", _fmt3(pos)), ("normal", _fmt3(normal))):  # fmt: skip
                ev.metadata.add(key=key, value=str(value))
            if p_false is not None:
                ev.metadata.add(key="p_false", value=f"{float(p_false):.4f}")
            out.append(self._msg("/detector/events", ev, log_t, src))
        return out

    def _fit(self, p, a, src: int, log_t: int) -> list[FoxgloveMessage]:
        flagged = p.get("flagged_events")
        self.contacts.apply_fit(a["ids"], a["u"], a["flags"], int(p["fit_index"]), flagged)
        t = int(p.get("data_ns", src))
        reliable = bool(p.get("reliable", True))
        n_flag = self.contacts.flagged_events()
        text = (
            f"fit {int(p['fit_index'])}: {len(np.asarray(a['ids']))} observations, "
            f"{self.contacts.events} contacts ({n_flag} flagged)"
        )
        if "fit_s" in p:
            text += f", {float(p['fit_s']):.2f} s"
        waiting = p.get("awaiting_events") or ()
        if waiting:
            text += "; awaiting a second touch: " + ", ".join(str(int(e)) for e in waiting)
        if not reliable:
            text += "; FIT UNRELIABLE: " + "; ".join(str(r) for r in p.get("reasons", ()))
        out = [self._log(2 if reliable else 3, "mapper", text, t, log_t)]
        return out + self._contacts(t, force=True, log_t=log_t)

    def _mesh(self, p, a, src: int, log_t: int) -> FoxgloveMessage:
        from groundstation.mapping.surface import std_colors

        v = np.asarray(a["vertices"], dtype=np.float64).reshape(-1, 3)
        tri = np.asarray(a["triangles"], dtype=np.int64).reshape(-1, 3)
        sd = np.asarray(a["vertex_std"], dtype=np.float64).reshape(-1)
        if sd.shape[0] != v.shape[0] or (tri.size and (tri.min() < 0 or tri.max() >= len(v))):
            raise ValueError("mesh arrays do not fit together")
        update = _pb("foxglove.SceneUpdate")()
        ent = update.entities.add(frame_id=WORLD, id="mesh")
        _stamp(ent, src)
        fit_index = int(p["fit_index"])
        colors, (lo, hi) = std_colors(sd) if sd.size else (np.zeros((0, 3)), (0.0, 1.0))
        for key, value in (("fit_index", fit_index), ("vertices", len(v)),
                           ("triangles", len(tri)), ("std_min", f"{lo:.4g}"),
                           ("std_max", f"{hi:.4g}")):  # fmt: skip
            _kv(ent, key, value)
        prim = ent.triangles.add()
        _identity_pose(prim.pose)
        point3, color = _pb("foxglove.Point3"), _pb("foxglove.Color")
        prim.points.extend([point3(x=x, y=y, z=z) for x, y, z in v.tolist()])
        prim.colors.extend([color(r=r, g=g, b=b, a=1.0) for r, g, b in colors.tolist()])
        prim.indices.extend(tri.reshape(-1).tolist())
        return self._msg("/map/mesh", update, log_t, src)

    def _trajectory(self, t: int, force: bool, log_t: int | None = None) -> list[FoxgloveMessage]:
        version, last = self._traj_sent
        tr = self.trajectory
        if tr.version == version or len(tr) < 2:  # points() copies the whole path
            return []
        if not force and t - last < self.settings.trajectory_period_s * 1e9:
            return []
        self._traj_sent = (tr.version, t)
        update = _pb("foxglove.SceneUpdate")()
        ent = update.entities.add(frame_id=WORLD, id="trajectory")
        _stamp(ent, t)
        _kv(ent, "spacing_m", f"{tr.spacing_m:.3g}")
        line = ent.lines.add(type=0, thickness=0.02, scale_invariant=False)  # LINE_STRIP
        _identity_pose(line.pose)
        line.color.r, line.color.g, line.color.b, line.color.a = 1.0, 0.55, 0.0, 1.0
        point3 = _pb("foxglove.Point3")
        line.points.extend([point3(x=x, y=y, z=z) for x, y, z in tr.points().tolist()])
        return [self._msg("/vehicle/trajectory", update, t if log_t is None else log_t, t)]

    def _contacts(self, t: int, force: bool, log_t: int | None = None) -> list[FoxgloveMessage]:
        version, last = self._contacts_sent
        book = self.contacts
        if book.version == version or (not force and len(book) == 0):
            return []
        if not force and t - last < self.settings.contacts_period_s * 1e9:
            return []
        self._contacts_sent = (book.version, t)
        return [self._msg("/map/contacts", contact_cloud(book.arrays(), t), t if log_t is None
                          else log_t, t)]  # fmt: skip


#: The PointCloud layout of ``/map/contacts`` (little-endian, packed).
CLOUD_DTYPE = np.dtype(
    [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1"),
     ("alpha", "u1"), ("state", "u1"), ("p_false", "<f4"), ("u", "<f4"), ("event_id", "<i4")]
)  # fmt: skip
_FIELD_TYPES = {"|u1": 1, "<f4": 7, "<i4": 6}  # foxglove.PackedElementField.NumericType


def contact_cloud(arrays: Mapping[str, np.ndarray], t_ns: int):
    """The ``/map/contacts`` PointCloud of :meth:`ContactBook.arrays` at data time ``t_ns``."""
    k = len(arrays["state"])
    rec = np.zeros(k, dtype=CLOUD_DTYPE)
    xyz = np.asarray(arrays["xyz"]).reshape(k, 3)
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rgb = np.round(STATE_COLORS[arrays["state"]] * 255).astype(np.uint8).reshape(k, 3)
    rec["red"], rec["green"], rec["blue"], rec["alpha"] = rgb[:, 0], rgb[:, 1], rgb[:, 2], 255
    rec["state"] = arrays["state"]
    rec["p_false"], rec["u"], rec["event_id"] = arrays["p_false"], arrays["u"], arrays["event_id"]
    cloud = _pb("foxglove.PointCloud")(frame_id=WORLD, point_stride=CLOUD_DTYPE.itemsize)
    _stamp(cloud, t_ns)
    _identity_pose(cloud.pose)
    for name in CLOUD_DTYPE.names:
        fdt, offset = CLOUD_DTYPE.fields[name][:2]
        cloud.fields.add(name=name, offset=offset, type=_FIELD_TYPES[fdt.str])
    cloud.data = rec.tobytes()
    return cloud
