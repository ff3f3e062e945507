"""The Rerun sink: the live web view (``--viewer rerun`` on ``live``, ``replay`` and ``view``).

Two parts:

- :class:`RerunLogger` (no sockets of its own, no clock): bus messages -> Rerun entities on the
  ``flight_time`` timeline (seconds of log time from ``t0_ns``, the recording's start in
  replay, the first message in a live session), so a browser can scrub back through the
  flight. Entities (world frame: right-handed, z up, metres):

  ============================  ===================================================  ===========
  entity                        what                                                 from
  ============================  ===================================================  ===========
  ``world/mesh``                Mesh3D, vertex colours = predictive std (viridis)    ``mesh``
  ``world/contacts``            Points3D, green trusted / magenta flagged / grey     observations
                                pending (labels: event id and p_false when given)    + fits
  ``world/trajectory``          LineStrips3D, the flown path (5 cm apart, 1 Hz)      poses
  ``world/vehicle``             Transform3D (mocap pose, <= 20 Hz) + axes triad      poses
  ``signal/accel_g``            Scalars: filtered |a| in G (the detector's signal)   IMU + att.
  ``signal/threshold_g``        Scalars: the threshold a0 (and ``release_g``)        settings
  ``signal/events``             SeriesPoints at each contact event's end (its peak)  events
  ``log``                       TextLog: events, fits, warnings and errors           all
  ============================  ===================================================  ===========

- :class:`~groundstation.viewer.rerun_server.RerunServer` (its own module): Rerun's server,
  bound to ``127.0.0.1`` unless told otherwise; :func:`open_stream` connects a recording
  stream to it (and to an ``.rrd`` file).

Failures never reach the pipeline: a missing ``rerun-sdk`` raises :class:`RerunUnavailable`
(a ``GroundstationError`` with the install hint) before anything starts, and the logger counts
and skips malformed messages.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from groundstation.openformats.signal import DetectorSignal
from groundstation.openformats.state import ContactBook, Trajectory
from groundstation.viewer.rerun_server import (
    RerunServer,
    RerunSettings,
    RerunUnavailable,
    require_rerun,
)
from groundstation.viewer.scene import STATE_COLORS

__all__ = [
    "RerunLogger", "RerunServer", "RerunSettings", "RerunUnavailable", "blueprint", "open_stream",
]  # fmt: skip

TIMELINE = "flight_time"
APP_ID = "groundstation"


def blueprint():
    """The default layout: 3D world on the left, signal plot and log on the right."""
    rr = require_rerun()
    rrb = rr.blueprint
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="map"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="signal", name="detector signal"),
                rrb.TextLogView(origin="log", name="log"),
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def _rgb8(colors: np.ndarray) -> np.ndarray:
    return np.round(np.clip(colors, 0, 1) * 255).astype(np.uint8)


class RerunLogger:
    """Bus messages -> Rerun entities (module docstring).

    Parameters
    ----------
    recording : rerun.RecordingStream
        Where to log (its sinks decide where the data goes).
    contact, alignment : settings of the detector (the signal's filter and threshold)
    t0_ns : int, optional
        Zero of the ``flight_time`` timeline on the log axis; default the first message.
    settings : RerunSettings
    """

    def __init__(
        self,
        recording: Any,
        contact=None,
        alignment=None,
        *,
        t0_ns: int | None = None,
        settings: RerunSettings | None = None,
    ) -> None:
        self.rr = require_rerun()
        self.rec = recording
        self.settings = settings or RerunSettings()
        self.signal = DetectorSignal(contact, alignment)
        self.contacts = ContactBook()
        self.trajectory = Trajectory()
        self.t0_ns = t0_ns
        self._sig_t: list[int] = []
        self._sig_g: list[float] = []
        self._pose_next = -(2**62)
        self._traj_next = -(2**62)
        self._traj_version = 0
        self._body: int | None = None
        self.messages = 0
        self.bad = 0
        self.rr.log("world", self.rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True,
                    recording=self.rec)  # fmt: skip
        triad = self.rr.Arrows3D(
            vectors=np.eye(3) * 0.3, colors=[[230, 40, 40], [40, 200, 40], [40, 90, 230]]
        )
        self.rr.log("world/vehicle/axes", triad, static=True, recording=self.rec)
        impulse = self.signal.is_score
        series = (
            ("signal/accel_g", [40, 40, 40], "trigger score" if impulse else "filtered |a| (G)"),
            ("signal/threshold_g", [214, 39, 40], "trigger (1)" if impulse else "threshold a0"),
        )
        for path, color, name in series:
            style = self.rr.SeriesLines(colors=[color], names=[name])
            self.rr.log(path, style, static=True, recording=self.rec)
        self.rr.log("signal/events", self.rr.SeriesPoints(colors=[[217, 25, 143]],
                    markers=["diamond"], names=["contact events (peak G)"]), static=True,
                    recording=self.rec)  # fmt: skip

    # -- time ----------------------------------------------------------------------------------
    def _seconds(self, t_ns: int) -> float:
        if self.t0_ns is None:
            self.t0_ns = int(t_ns)
        return (int(t_ns) - self.t0_ns) / 1e9

    def _at(self, t_ns: int) -> None:
        self.rec.set_time(TIMELINE, duration=self._seconds(t_ns))

    # -- entry ---------------------------------------------------------------------------------
    def ingest(
        self,
        topic: str,
        payload: Mapping[str, Any],
        arrays: Mapping[str, np.ndarray],
        source_ns: int,
        recv_ns: int = 0,
    ) -> None:
        """Log one bus message; malformed ones are counted in :attr:`bad` and skipped."""
        self.messages += 1
        try:
            # bus arrays are zero-copy views into the message, at any byte offset; Rerun hands
            # numpy buffers to Arrow, which panics (and ends the viewer) on a misaligned one
            arrays = {k: np.require(v, requirements="A") for k, v in arrays.items()}
            self._dispatch(topic, payload, arrays, int(source_ns), int(recv_ns))
        except (KeyError, ValueError, TypeError, IndexError):
            self.bad += 1

    def ingest_envelope(self, env) -> None:
        h = env.header
        self.ingest(env.topic, env.payload, env.arrays, h.source_ns, h.recv_ns)

    def _dispatch(self, topic, p, a, src: int, recv: int) -> None:
        rr, rec = self.rr, self.rec
        if topic == "samples.imu":
            t = int(p.get("t_station_ns", src))
            self._signal(self.signal.push_imu(t, a["accel_mps2"]))
        elif topic == "samples.attitude":
            t = int(p.get("t_station_ns", src))
            self._signal(self.signal.push_attitude(t, a["q_wxyz"]))
        elif topic == "samples.pose":
            self._pose(p, a, src)
        elif topic == "observations":
            if self.contacts.add_observation(
                p["id"], p["label"], a["x_m"], p.get("event_id", -1), p.get("p_false")
            ):
                self._at(src)
                self._contacts()
        elif topic == "contact.event":
            ev, state, peak = int(p["id"]), str(p["state"]), float(p["peak_g"])
            self.contacts.add_event(ev, state, p.get("p_false"))
            self._at(src)
            if state == "end":  # the event's peak, at its end
                rr.log("signal/events", rr.Scalars(peak), recording=rec)
            extra = "" if p.get("p_false") is None else f", p_false {float(p['p_false']):.2f}"
            rr.log("log", rr.TextLog(f"contact {ev} {state}: peak {peak:.2f} G{extra}",
                   level="INFO"), recording=rec)  # fmt: skip
        elif topic == "mapper.fit":
            self.contacts.apply_fit(a["ids"], a["u"], a["flags"], int(p["fit_index"]),
                                    p.get("flagged_events"))  # fmt: skip
            self._at(int(p.get("data_ns", src)))
            self._contacts()
            n_flag = self.contacts.flagged_events()
            text = f"fit {int(p['fit_index'])}: {self.contacts.events} contacts ({n_flag} flagged)"
            waiting = p.get("awaiting_events") or ()
            if waiting:
                ids = ", ".join(str(int(e)) for e in waiting)
                text += f"; awaiting a second touch: {ids}"
            level = "INFO" if p.get("reliable", True) else "WARN"
            if level == "WARN":
                text += "; FIT UNRELIABLE: " + "; ".join(str(r) for r in p.get("reasons", ()))
            rr.log("log", rr.TextLog(text, level=level), recording=rec)
        elif topic == "mesh":
            self._mesh(p, a, src)
        elif topic == "log":
            self._at(src)
            level = {"warning": "WARN", "error": "ERROR"}.get(str(p.get("level")), "INFO")
            rr.log("log", rr.TextLog(f"{p.get('process', '')}: {p['message']}", level=level),
                   recording=rec)  # fmt: skip

    # -- parts ---------------------------------------------------------------------------------
    def _signal(self, values: list[tuple[int, float]]) -> None:
        for t, g in values:
            self._sig_t.append(t)
            self._sig_g.append(g)
        if len(self._sig_t) >= 100:
            self.flush_signal()

    def flush_signal(self) -> None:
        """Send the buffered signal samples as columns (one call per 100 samples)."""
        if not self._sig_t:
            return
        rr = self.rr
        secs = np.array([self._seconds(t) for t in self._sig_t])
        idx = [rr.TimeColumn(TIMELINE, duration=secs)]
        rr.send_columns("signal/accel_g", indexes=idx,
                        columns=rr.Scalars.columns(scalars=np.asarray(self._sig_g)),
                        recording=self.rec)  # fmt: skip
        thr = np.full(len(secs), self.signal.threshold_g)
        rr.send_columns("signal/threshold_g", indexes=idx, columns=rr.Scalars.columns(scalars=thr),
                        recording=self.rec)  # fmt: skip
        self._sig_t.clear()
        self._sig_g.clear()

    def _pose(self, p, a, src: int) -> None:
        body = int(p.get("body_id", 0))
        if self._body is None:
            self._body = body
        if body != self._body or not p.get("valid", True):
            return
        pos = np.asarray(a["position_m"], dtype=np.float64).reshape(3)
        q = np.asarray(a["q_wxyz"], dtype=np.float64).reshape(4)
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(q))):
            return
        t = int(p.get("t_station_ns", src))
        self.trajectory.add(t, pos)
        rr = self.rr
        if t >= self._pose_next:
            self._pose_next = t + int(1e9 / self.settings.pose_rate_hz)
            self._at(t)
            xyzw = [q[1], q[2], q[3], q[0]]
            rr.log("world/vehicle", rr.Transform3D(translation=pos, quaternion=xyzw),
                   recording=self.rec)  # fmt: skip
        if t >= self._traj_next and self.trajectory.version != self._traj_version:
            self._traj_next = t + 1_000_000_000
            self._traj_version = self.trajectory.version
            self._at(t)
            pts = self.trajectory.points()
            if len(pts) >= 2:
                rr.log("world/trajectory", rr.LineStrips3D([pts], colors=[[255, 140, 0]],
                       radii=0.01), recording=self.rec)  # fmt: skip

    def _contacts(self) -> None:
        arr = self.contacts.arrays()
        labels = [
            f"event {e}" + ("" if math.isnan(pf) else f", p_false {pf:.2f}")
            for e, pf in zip(arr["event_id"].tolist(), arr["p_false"].tolist(), strict=True)
        ]
        self.rr.log("world/contacts", self.rr.Points3D(arr["xyz"], colors=_rgb8(STATE_COLORS[
            arr["state"]]), radii=0.03, labels=labels, show_labels=False),
            recording=self.rec)  # fmt: skip

    def _mesh(self, p, a, src: int) -> None:
        from groundstation.mapping.surface import std_colors

        v = np.asarray(a["vertices"], dtype=np.float32).reshape(-1, 3)
        tri = np.asarray(a["triangles"], dtype=np.uint32).reshape(-1, 3)
        sd = np.asarray(a["vertex_std"], dtype=np.float64).reshape(-1)
        if sd.shape[0] != v.shape[0] or (tri.size and int(tri.max()) >= len(v)):
            raise ValueError("mesh arrays do not fit together")
        colors, _ = std_colors(sd) if sd.size else (np.zeros((0, 3)), None)
        self._at(src)
        self.rr.log("world/mesh", self.rr.Mesh3D(vertex_positions=v, triangle_indices=tri,
                    vertex_colors=_rgb8(colors)), recording=self.rec)  # fmt: skip
        self.rr.log("log", self.rr.TextLog(f"mesh of fit {int(p['fit_index'])}: {len(tri)} "
                    "triangles", level="DEBUG"), recording=self.rec)  # fmt: skip

    def finish(self) -> None:
        """End of data: release and send the rest of the signal and the last path."""
        self._signal(self.signal.flush())
        self.flush_signal()
        pts = self.trajectory.points()
        if len(pts) >= 2 and self.trajectory.version != self._traj_version:
            self._traj_version = self.trajectory.version
            self.rr.log("world/trajectory", self.rr.LineStrips3D([pts], colors=[[255, 140, 0]],
                        radii=0.01), recording=self.rec)  # fmt: skip


def open_stream(settings: RerunSettings, server: RerunServer | None, name: str = APP_ID):
    """A Rerun recording stream sending to ``server`` (and to ``settings.rrd`` when set),
    with the default layout."""
    rr = require_rerun()
    rec = rr.RecordingStream(APP_ID, recording_id=None)
    sinks = []
    if server is not None:
        sinks.append(rr.GrpcSink(server.grpc_url))
    if settings.rrd:
        sinks.append(rr.FileSink(settings.rrd))
    if sinks:
        rec.set_sinks(*sinks, default_blueprint=blueprint())
    return rec
