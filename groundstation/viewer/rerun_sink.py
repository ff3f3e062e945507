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

- :class:`RerunServer`: Rerun's own server (``rerun --serve-web``, the CLI shipped in the
  ``rerun-sdk`` wheel) as a child process: a gRPC proxy that buffers the stream for late
  viewers and an HTTP server for the web viewer. It binds to ``127.0.0.1`` unless told
  otherwise (the Python SDK's own ``serve_grpc``/``serve_web_viewer`` bind every interface,
  which is why the CLI is used). :attr:`RerunServer.web_url` is the page to open.

Failures never reach the pipeline: a missing ``rerun-sdk`` raises :class:`RerunUnavailable`
(a ``GroundstationError`` with the install hint) before anything starts, and the logger counts
and skips malformed messages.
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.parse
from collections.abc import Mapping
from typing import Any

import numpy as np

from groundstation.errors import ConfigError, GroundstationError
from groundstation.openformats.signal import DetectorSignal
from groundstation.openformats.state import ContactBook, Trajectory
from groundstation.viewer.scene import STATE_COLORS

TIMELINE = "flight_time"
APP_ID = "groundstation"


class RerunUnavailable(GroundstationError, RuntimeError):
    """rerun-sdk is not installed, or its server did not start."""


def require_rerun():
    """Import ``rerun`` or raise :class:`RerunUnavailable` with the install hint."""
    try:
        import rerun as rr
    except ImportError as exc:
        raise RerunUnavailable(
            f"--viewer rerun needs the rerun-sdk package ({exc})",
            hint="install it with ./bootstrap.sh (without GS_NO_RERUN=1) or "
            ".venv/bin/pip install -e '.[rerun]'",
        ) from None
    return rr


@dataclasses.dataclass(frozen=True)
class RerunSettings:
    """Where the web view is served and what the stream keeps.

    Attributes
    ----------
    bind : str
        Address both servers listen on; ``127.0.0.1`` (default) keeps them on this machine:
        reach them from elsewhere through an SSH tunnel (README). ``0.0.0.0`` exposes them to
        the network without authentication.
    web_port : int
        HTTP port of the web viewer page (Rerun's default 9090; 0 picks a free one).
    grpc_port : int
        gRPC port of the data stream (Rerun's default 9876; 0 picks a free one).
    server_memory_limit : str
        What the server buffers for late viewers (Rerun syntax: ``"1GiB"``, ``"25%"``).
    rrd : str or None
        Also save the stream to this ``.rrd`` file (opens with ``rerun FILE``).
    pose_rate_hz : float
        Vehicle transforms logged at most this often (data time).
    """

    bind: str = "127.0.0.1"
    web_port: int = 9090
    grpc_port: int = 9876
    server_memory_limit: str = "1GiB"
    rrd: str | None = None
    pose_rate_hz: float = 20.0

    def __post_init__(self) -> None:
        for name in ("web_port", "grpc_port"):
            port = getattr(self, name)
            if not (isinstance(port, int) and 0 <= port <= 65535):
                raise ConfigError(f"rerun {name} {port!r} must be a port number 0-65535")
        if self.web_port and self.web_port == self.grpc_port:
            raise ConfigError(f"the web and gRPC ports must differ (both {self.web_port})")
        try:
            socket.getaddrinfo(self.bind, None)
        except (socket.gaierror, UnicodeError):
            raise ConfigError(
                f"--web-bind {self.bind!r} is not an address of this machine",
                hint="use 127.0.0.1 (default), 0.0.0.0 or one interface's address",
            ) from None
        if not self.pose_rate_hz > 0:
            raise ConfigError(f"pose_rate_hz {self.pose_rate_hz} must be > 0")


def _die_with_parent() -> None:
    try:
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _free_port(host: str) -> int:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _listening(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.2):
            return True
    except OSError:
        return False


class RerunServer:
    """Rerun's gRPC proxy + web viewer as a child process (module docstring).

    Parameters
    ----------
    settings : RerunSettings
    start_timeout_s : float
        How long to wait for both ports to listen.
    """

    def __init__(self, settings: RerunSettings, start_timeout_s: float = 30.0) -> None:
        require_rerun()
        self.settings = s = settings
        exe = shutil.which("rerun", path=os.path.dirname(sys.executable)) or shutil.which("rerun")
        if exe is None:
            raise RerunUnavailable("the rerun command of rerun-sdk was not found on PATH")
        self.host = "127.0.0.1" if s.bind in ("0.0.0.0", "::", "") else s.bind
        self.grpc_port = s.grpc_port or _free_port(s.bind)
        self.web_port = s.web_port or _free_port(s.bind)
        for port in (self.grpc_port, self.web_port):
            if _listening(self.host, port):
                raise RerunUnavailable(
                    f"port {port} on {self.host} is already in use",
                    hint="choose others with --web-port / --grpc-port (0 = any free port)",
                )
        argv = [
            exe, "--serve-web", "--bind", s.bind, "--port", str(self.grpc_port),
            "--web-viewer-port", str(self.web_port), "--server-memory-limit",
            s.server_memory_limit,
        ]  # fmt: skip
        env = dict(os.environ, RERUN_ANALYTICS="0", CI=os.environ.get("CI", "1"))
        # Same process group as this process (a supervisor that stops a worker's group stops
        # its server too), and SIGTERM when this process dies (Linux), so no orphan keeps the
        # ports.
        self.proc = subprocess.Popen(  # noqa: S603 - our own argv
            argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
            env=env, preexec_fn=_die_with_parent,
        )  # fmt: skip
        deadline = time.monotonic() + start_timeout_s
        while not (_listening(self.host, self.grpc_port) and _listening(self.host, self.web_port)):
            if self.proc.poll() is not None:
                err = (self.proc.stderr.read() or b"").decode(errors="replace")[-400:]
                raise RerunUnavailable(f"rerun server exited ({self.proc.returncode}): {err}")
            if time.monotonic() > deadline:
                self.close()
                raise RerunUnavailable(f"rerun server did not listen within {start_timeout_s} s")
            time.sleep(0.1)

    @property
    def grpc_url(self) -> str:
        """Where the SDK (and viewers) connect: ``rerun+http://HOST:PORT/proxy``."""
        return f"rerun+http://{self.host}:{self.grpc_port}/proxy"

    @property
    def web_url(self) -> str:
        """The web viewer page, already pointed at the stream."""
        url = urllib.parse.quote(self.grpc_url, safe="")
        return f"http://{self.host}:{self.web_port}/?url={url}"

    def close(self) -> None:
        """Stop the server (idempotent)."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        if self.proc.stderr is not None:
            self.proc.stderr.close()


def blueprint():
    """The default layout: 3D world on the left, signal plot and log on the right."""
    rr = require_rerun()
    rrb = rr.blueprint
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(origin="world", name="map"),
            rrb.Vertical(
                rrb.TimeSeriesView(origin="signal", name="detector signal (G)"),
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
        series = (
            ("signal/accel_g", [40, 40, 40], "filtered |a|"),
            ("signal/threshold_g", [214, 39, 40], "threshold a0"),
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
