"""Importers: outside recordings re-encoded as the wire bytes a live session would have recorded.

Each importer has a pure part that reads and converts the source into :class:`FlightStreams`
(SI units, body FRD, local NED, quaternions (w, x, y, z) FRD -> NED, integer ns) and shares
:func:`write_flight`, which encodes those streams exactly as the live sources would have sent
them and records them in the layout of :mod:`groundstation.acquisition.layout`:

- IMU -> MAVLink 2 HIGHRES_IMU and attitude -> ATTITUDE_QUATERNION frames (system 1, component
  1, as an autopilot would send), one frame per ``raw.mavlink`` message, source ``link_uri``;
- positions -> NatNet 4.1 frames of data on ``raw.natnet`` (rigid body 1, Motive Y-up; the pose
  is converted NED -> station world (ENU) -> Motive with ``firmware_bridge.frames``), or with
  ``pose_transport="mavlink"`` ATT_POS_MOCAP frames on a second ``raw.mavlink`` channel whose
  source is ``mocap_uri``.

Replay then runs the same decoders on these bytes. Log time = publish time = source time.

Failure never leaves output behind: every importer writes to a hidden temporary file beside
``out`` and renames it into place only when the import succeeded (:func:`atomic_output`); bad
input raises :class:`ImportDataError` naming the problem (fuzzed: ``groundstation bench fuzz``).

Modules: :mod:`.csv_imu` (aggressive_flight CSV), :mod:`.ulog` (PX4 ULog), :mod:`.tlog`
(MAVLink telemetry logs, copied frame by frame), :mod:`.export_tlog` (recording -> tlog), and
the command modules ``cli_*``.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.acquisition import layout
from groundstation.acquisition.recorder import Recorder
from groundstation.errors import InputDataError

#: MAVLink address of the (simulated) autopilot in imported logs.
AUTOPILOT_SYSTEM_ID = 1
AUTOPILOT_COMPONENT_ID = 1
#: Component of the ATT_POS_MOCAP sender (MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY).
MOCAP_COMPONENT_ID = 197
#: NatNet rigid-body streaming id used for the imported vehicle.
RIGID_BODY_ID = 1
NATNET_VERSION = (4, 1)
#: Largest magnitude of any imported value (m/s^2, rad/s, m; quaternions are unit): far above
#: anything physical, far below what the wire formats (float32) and unit conversions overflow on.
MAX_ABS_VALUE = 1e6


class ImportDataError(InputDataError):
    """An outside recording cannot be imported (missing file, no usable data, bad columns)."""


@dataclass
class FlightStreams:
    """Converted streams of one flight (pure data).

    Attributes
    ----------
    imu_t_ns : (n,) int64
        Source time of each IMU sample, ns.
    accel_frd : (n, 3) float64
        Specific force including gravity, body FRD, m/s^2 (about (0, 0, -9.81) level at rest).
    gyro_frd : (n, 3) float64
        Angular rate, body FRD, rad/s.
    att_t_ns : (m,) int64
        Source time of each attitude, ns.
    q_ned_frd : (m, 4) float64
        Unit quaternion (w, x, y, z) rotating body FRD into local NED.
    rates_frd : (m, 3) float64
        Body rates for ATTITUDE_QUATERNION, rad/s.
    pose_t_ns : (k,) int64
        Source time of each position, ns (may be empty).
    pos_ned : (k, 3) float64
        Position in local NED, m.
    q_pose : (k, 4) float64
        Orientation for the pose, (w, x, y, z) FRD -> NED.
    skipped : Counter
        Rows/messages dropped while reading, by reason.
    notes : list of str
        Conversions applied and anything the user should know.
    """

    imu_t_ns: np.ndarray
    accel_frd: np.ndarray
    gyro_frd: np.ndarray
    att_t_ns: np.ndarray
    q_ned_frd: np.ndarray
    rates_frd: np.ndarray
    pose_t_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    pos_ned: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    q_pose: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    skipped: Counter = field(default_factory=Counter)
    notes: list[str] = field(default_factory=list)

    def validate(self) -> None:
        """Check shapes, finiteness, unit quaternions and monotonic times; raise on violation."""
        for t, arrays, what in (
            (self.imu_t_ns, (self.accel_frd, self.gyro_frd), "imu"),
            (self.att_t_ns, (self.q_ned_frd, self.rates_frd), "attitude"),
            (self.pose_t_ns, (self.pos_ned, self.q_pose), "pose"),
        ):
            if t.ndim != 1 or t.dtype.kind != "i":
                raise ImportDataError(f"{what} times must be a 1-D integer array, got {t.dtype}")
            for a in arrays:
                if a.ndim != 2 or a.shape[0] != t.shape[0]:
                    raise ImportDataError(
                        f"{what} arrays must have {t.shape[0]} rows, got shape {a.shape}"
                    )
                if not np.all(np.isfinite(a)):
                    raise ImportDataError(f"{what} contains NaN or inf after conversion")
            if t.size and (t[0] < 0 or np.any(np.diff(t) <= 0)):
                raise ImportDataError(f"{what} times must be >= 0 and strictly increasing")
            for a in arrays:
                if a.size and np.max(np.abs(a)) > MAX_ABS_VALUE:
                    raise ImportDataError(
                        f"{what} holds a value of magnitude {np.max(np.abs(a)):.3g} "
                        f"(limit {MAX_ABS_VALUE:g}): wrong units or a corrupt file?"
                    )
        for q, what in ((self.q_ned_frd, "attitude"), (self.q_pose, "pose")):
            if q.size and np.max(np.abs(np.linalg.norm(q, axis=1) - 1.0)) > 1e-6:
                raise ImportDataError(f"{what} quaternions are not unit norm")


@dataclass
class ImportReport:
    """What an import converted.

    Attributes
    ----------
    source : str
        Input file.
    out : str
        Output recording.
    counts : dict of str to int
        Messages written per kind ("imu", "attitude", "pose", or MAVLink message names).
    skipped : dict of str to int
        Dropped input rows/messages by reason.
    start_ns, end_ns : int or None
        Log-time span written.
    notes : list of str
        Conversions applied.
    """

    source: str
    out: str
    counts: dict[str, int]
    skipped: dict[str, int]
    start_ns: int | None
    end_ns: int | None
    notes: list[str] = field(default_factory=list)

    @property
    def duration_s(self) -> float:
        if self.start_ns is None or self.end_ns is None:
            return 0.0
        return (self.end_ns - self.start_ns) / 1e9

    def rates_hz(self) -> dict[str, float]:
        d = self.duration_s
        return {k: (n / d if d > 0 else 0.0) for k, n in self.counts.items()}

    def describe(self) -> str:
        rates = self.rates_hz()
        lines = [f"imported {self.source} -> {self.out}: {self.duration_s:.2f} s"]
        for kind, n in sorted(self.counts.items()):
            lines.append(f"  {kind:<20} {n:>8} messages  {rates[kind]:8.1f} Hz")
        for reason, n in sorted(self.skipped.items()):
            lines.append(f"  skipped {n} ({reason})")
        lines.extend(f"  note: {note}" for note in self.notes)
        return "\n".join(lines)


def _station_version() -> str:
    try:
        from importlib.metadata import version

        return version("groundstation")
    except Exception:  # noqa: BLE001 - metadata is informative only
        return "unknown"


def import_metadata(created_by: str, sources: list[str], extra: Mapping[str, str] | None = None):
    """The ``groundstation`` metadata record for an imported file."""
    return layout.station_metadata(
        station_version=_station_version(), created_by=created_by, sources=sources, extra=extra
    )


@contextmanager
def atomic_output(out: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``out``; rename it to ``out`` only if the block succeeds.

    On any exception the temporary file is removed and ``out`` is left as it was (an earlier
    recording at that path is not replaced by a partial one).
    """
    target = Path(out)
    tmp = target.with_name(f".{target.name}.partial-{os.getpid()}")
    try:
        yield tmp
        os.replace(tmp, target)
    except BaseException:
        try:
            tmp.unlink()
        except FileNotFoundError:
            pass
        raise


def check_source(path: str | os.PathLike[str]) -> Path:
    """Return ``path`` as a Path if it is a readable file, else raise :class:`ImportDataError`."""
    p = Path(path)
    if not p.is_file():
        raise ImportDataError(f"input file {str(p)!r} does not exist or is not a file")
    return p


def write_flight(
    streams: FlightStreams,
    out: str | os.PathLike[str],
    *,
    source: str,
    created_by: str,
    link_uri: str,
    mocap_uri: str,
    pose_transport: str = "natnet",
    truth: Mapping[str, Any] | None = None,
) -> ImportReport:
    """Encode ``streams`` as live wire bytes and record them at ``out``.

    Parameters
    ----------
    streams : FlightStreams
        Validated here.
    out : path
        Output MCAP file.
    source : str
        Input file (for the report and metadata).
    created_by : str
        Command line, stored in the metadata.
    link_uri, mocap_uri : str
        Channel ``source`` of the MAVLink and mocap channels (e.g. ``"import:csv"``).
    pose_transport : {"natnet", "mavlink"}
        How positions travel (see the module docstring).
    truth : mapping, optional
        Written as ``truth.json``.

    Returns
    -------
    ImportReport
    """
    from firmware_bridge.errors import BridgeError

    if pose_transport not in ("natnet", "mavlink"):
        raise ImportDataError(
            f"pose_transport must be 'natnet' or 'mavlink', got {pose_transport!r}"
        )
    streams.validate()
    try:
        with atomic_output(out) as tmp:
            return _write_flight(
                streams, tmp, out, source, created_by, link_uri, mocap_uri, pose_transport, truth
            )
    except BridgeError as exc:  # a value the wire format cannot carry (checked per frame)
        raise ImportDataError(f"cannot import {source}: {exc.message}", exc.hint) from None


def _write_flight(
    streams: FlightStreams,
    tmp: Path,
    out: str | os.PathLike[str],
    source: str,
    created_by: str,
    link_uri: str,
    mocap_uri: str,
    pose_transport: str,
    truth: Mapping[str, Any] | None,
) -> ImportReport:
    from firmware_bridge.frames import ned_to_enu, quat_ned_frd_to_enu_flu, world_to_motive
    from firmware_bridge.mavlink.codec import MavlinkCodec
    from firmware_bridge.mavlink.messages import AttitudeSample, ImuSample, MocapPose
    from firmware_bridge.natnet import FrameOfData, RigidBody, encode_frame_of_data

    link = MavlinkCodec(AUTOPILOT_SYSTEM_ID, AUTOPILOT_COMPONENT_ID)
    mocap = MavlinkCodec(AUTOPILOT_SYSTEM_ID, MOCAP_COMPONENT_ID)
    # Merge the three streams by time; ties keep the order imu, attitude, pose (stable sort).
    times = np.concatenate([streams.imu_t_ns, streams.att_t_ns, streams.pose_t_ns])
    kinds = np.concatenate(
        [
            np.zeros(streams.imu_t_ns.size, np.int8),
            np.ones(streams.att_t_ns.size, np.int8),
            np.full(streams.pose_t_ns.size, 2, np.int8),
        ]
    )
    index = np.concatenate(
        [np.arange(streams.imu_t_ns.size), np.arange(streams.att_t_ns.size)]
        + [np.arange(streams.pose_t_ns.size)]
    )
    order = np.lexsort((kinds, times))
    if streams.pose_t_ns.size and pose_transport == "natnet":
        p_motive, q_motive = world_to_motive(
            ned_to_enu(streams.pos_ned), quat_ned_frd_to_enu_flu(streams.q_pose), up="y"
        )
    counts: Counter = Counter()
    natnet_meta = {
        layout.KEY_NATNET_VERSION: f"{NATNET_VERSION[0]}.{NATNET_VERSION[1]}",
        layout.KEY_MOTIVE_UP: "y",
    }
    meta = import_metadata(created_by, [str(source)])
    with Recorder(tmp, metadata=meta) as rec:
        for k in order:
            t = int(times[k])
            i = int(index[k])
            kind = int(kinds[k])
            if kind == 0:
                frame = link.encode(
                    ImuSample(
                        tuple(streams.accel_frd[i]), tuple(streams.gyro_frd[i]), time_source_ns=t
                    )
                )
                rec.write(frame, layout.RAW_MAVLINK_TOPIC, t, t, source=link_uri)
                counts["imu (HIGHRES_IMU)"] += 1
            elif kind == 1:
                frame = link.encode(
                    AttitudeSample(
                        tuple(streams.q_ned_frd[i]), tuple(streams.rates_frd[i]), time_source_ns=t
                    )
                )
                rec.write(frame, layout.RAW_MAVLINK_TOPIC, t, t, source=link_uri)
                counts["attitude (ATTITUDE_QUATERNION)"] += 1
            elif pose_transport == "natnet":
                body = RigidBody(RIGID_BODY_ID, tuple(p_motive[i]), tuple(q_motive[i]), 0.0, True)
                datagram = encode_frame_of_data(
                    FrameOfData(i, (body,), t / 1e9), version=NATNET_VERSION
                )
                rec.write(
                    datagram,
                    layout.RAW_NATNET_TOPIC,
                    t,
                    t,
                    source=mocap_uri,
                    channel_metadata=natnet_meta,
                )
                counts["pose (NatNet 4.1)"] += 1
            else:
                frame = mocap.encode(
                    MocapPose(tuple(streams.q_pose[i]), tuple(streams.pos_ned[i]), time_source_ns=t)
                )
                rec.write(frame, layout.RAW_MAVLINK_TOPIC, t, t, source=mocap_uri)
                counts["pose (ATT_POS_MOCAP)"] += 1
        if truth is not None:
            rec.add_truth(truth)
    stats = rec.stats
    return ImportReport(
        source=str(source),
        out=str(out),
        counts=dict(counts),
        skipped=dict(streams.skipped),
        start_ns=stats.start_ns,
        end_ns=stats.end_ns,
        notes=list(streams.notes),
    )


def nearest_index(t_from: np.ndarray, t_to: np.ndarray) -> np.ndarray:
    """Index into sorted ``t_from`` of the sample nearest to each time in ``t_to``.

    Parameters
    ----------
    t_from : (n,) sorted array, n >= 1
    t_to : (m,) array

    Returns
    -------
    (m,) int64 indices
    """
    j = np.searchsorted(t_from, t_to)
    j = np.clip(j, 1, max(len(t_from) - 1, 1))
    left = t_from[j - 1]
    right = t_from[np.minimum(j, len(t_from) - 1)]
    use_left = np.abs(t_to - left) <= np.abs(right - t_to)
    return np.where(use_left, j - 1, np.minimum(j, len(t_from) - 1)).astype(np.int64)


def quat_from_euler_zyx(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """Quaternions (w, x, y, z) of intrinsic Z-Y-X Euler angles: R = Rz(yaw) Ry(pitch) Rx(roll).

    Parameters
    ----------
    roll, pitch, yaw : (n,) arrays, rad

    Returns
    -------
    (n, 4) float64, unit norm, w >= 0.
    """
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    q = np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )
    return canonical_quat(q)


def canonical_quat(q: np.ndarray) -> np.ndarray:
    """Normalise (n, 4) quaternions and pick the sign with w >= 0."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)
