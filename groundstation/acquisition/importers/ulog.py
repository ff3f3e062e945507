"""Import PX4 ULog files (read with ``pyulog``).

Topics used (instance 0), all in PX4's conventions, which are MAVLink's:

- ``sensor_combined``: ``accelerometer_m_s2[0..2]`` (specific force incl. gravity, body FRD,
  m/s^2) and ``gyro_rad[0..2]`` (body FRD, rad/s) at ``timestamp`` (us) -> HIGHRES_IMU;
- ``vehicle_attitude``: ``q[0..3]`` = (w, x, y, z), body FRD -> local NED -> ATTITUDE_QUATERNION;
  body rates from ``rollspeed/pitchspeed/yawspeed`` when logged (old PX4), else the nearest
  ``sensor_combined`` gyro sample;
- ``vehicle_local_position``: ``x, y, z`` NED (m) -> poses (NatNet or ATT_POS_MOCAP) with the
  nearest attitude as orientation; samples with ``xy_valid`` or ``z_valid`` false are skipped.

No unit or frame change is needed; times are us -> ns. When the log's clock does not fit
ATTITUDE_QUATERNION's 32-bit ``time_boot_ms`` (SITL logs use Unix time), all times are
rebased to the log's start timestamp (noted in the report).

pyulog runs in a child process under a time limit (:func:`read_ulog`): on a corrupted file it
can loop for ever (a 36 KB damaged log kept ``import ulog`` busy for more than 60 s, inside
``ULog._read_file_definitions``). A stuck or crashed parse becomes an :class:`ImportDataError`
naming the file and the limit; nothing is written.
"""

from __future__ import annotations

import os
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.acquisition.importers import (
    MAX_ABS_VALUE,
    FlightStreams,
    ImportDataError,
    ImportReport,
    canonical_quat,
    check_source,
    nearest_index,
    write_flight,
)

TOPICS = ("sensor_combined", "vehicle_attitude", "vehicle_local_position")
_MAX_BOOT_MS = 2**32 - 1
_MAX_TIME_US = (2**63 - 1) // 1000  # times become int64 ns
#: Time limit of the pyulog parse: this base plus :data:`TIME_LIMIT_PER_MB_S` per MB of file
#: (pyulog reads the 4 MB ``sample.ulg`` in ~0.3 s here, so this is > 30x headroom).
TIME_LIMIT_BASE_S = 20.0
TIME_LIMIT_PER_MB_S = 2.0


@dataclass(frozen=True)
class ParsedULog:
    """What the importer needs from a ULog: the start timestamp (us) and the instance-0 data
    of :data:`TOPICS` (field name -> array), as parsed by pyulog."""

    start_timestamp: int
    datasets: dict[str, dict[str, np.ndarray]]


def default_time_limit_s(size_bytes: int) -> float:
    """The pyulog time limit for a file of ``size_bytes``, s."""
    return TIME_LIMIT_BASE_S + TIME_LIMIT_PER_MB_S * size_bytes / 1e6


def parse_ulog(data: bytes | str) -> ParsedULog:
    """Parse a ULog (bytes in memory or a path) with pyulog, in this process, no time limit.

    Raises
    ------
    ImportDataError
        pyulog rejected the file (any exception it raises).
    """
    import contextlib
    import io

    from pyulog import ULog

    source = io.BytesIO(data) if isinstance(data, bytes | bytearray) else data
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # pyulog prints its warnings
            ulog = ULog(source, list(TOPICS))
        sets = {d.name: dict(d.data) for d in ulog.data_list if d.multi_id == 0}
        return ParsedULog(int(ulog.start_timestamp), sets)
    except Exception as exc:  # noqa: BLE001 - pyulog raises assorted errors on bad files
        raise ImportDataError(f"pyulog cannot read it: {type(exc).__name__}: {exc}") from None


def _child(path: str, conn: Any) -> None:
    try:
        conn.send(("ok", parse_ulog(path)))
    except ImportDataError as exc:
        conn.send(("error", exc.message))
    except BaseException as exc:  # noqa: BLE001 - MemoryError and the like: report, exit
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        conn.close()


def read_ulog(path: str | os.PathLike[str], time_limit_s: float | None = None) -> ParsedULog:
    """Parse ``path`` with pyulog in a child process that is killed after ``time_limit_s``.

    Parameters
    ----------
    path : path
        ULog file.
    time_limit_s : float, optional
        Default :func:`default_time_limit_s` of the file size.

    Raises
    ------
    ImportDataError
        pyulog rejected the file, crashed, or did not finish in time (the message names the file,
        the limit and the library).
    """
    import multiprocessing

    p = Path(path)
    limit = default_time_limit_s(p.stat().st_size) if time_limit_s is None else time_limit_s
    if not limit > 0:
        raise ImportDataError(f"ULog time limit {limit!r} s must be > 0")
    methods = multiprocessing.get_all_start_methods()
    ctx = multiprocessing.get_context("fork" if "fork" in methods else "spawn")
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(str(p), send), daemon=True, name="pyulog")
    proc.start()
    send.close()
    try:
        if not recv.poll(limit):
            raise ImportDataError(
                f"cannot read ULog {str(p)!r}: pyulog did not finish within {limit:.0f} s "
                "(stopped); the file is probably corrupt",
                hint="check it with 'ulog_info FILE'; if it is only very large, raise --time-limit",
            )
        try:
            kind, value = recv.recv()
        except (EOFError, OSError):
            proc.join(5)
            raise ImportDataError(
                f"cannot read ULog {str(p)!r}: pyulog crashed (exit code {proc.exitcode})"
            ) from None
    finally:
        recv.close()
        if proc.is_alive():
            proc.kill()
        proc.join(5)
    if kind != "ok":
        raise ImportDataError(f"cannot read ULog {str(p)!r}: {value}")
    return value


def _dataset(ulog: ParsedULog, name: str) -> dict[str, np.ndarray] | None:
    return ulog.datasets.get(name)


def _clean(
    t_us: np.ndarray, arrays: list[np.ndarray], what: str, skipped: Counter
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Drop rows with non-finite or out-of-range values or non-increasing time, counting them."""
    finite = np.all(np.stack([np.all(np.isfinite(a), axis=1) for a in arrays]), axis=0)
    skipped[f"{what}: NaN/inf"] += int((~finite).sum())
    t_us, arrays = t_us[finite], [a[finite] for a in arrays]
    ok = (t_us >= 0) & (t_us <= _MAX_TIME_US)
    for a in arrays:
        ok &= np.all(np.abs(a) <= MAX_ABS_VALUE, axis=1)
    skipped[f"{what}: value out of range"] += int((~ok).sum())
    t_us, arrays = t_us[ok], [a[ok] for a in arrays]
    keep = np.ones(t_us.size, bool)
    last = -1
    for i, t in enumerate(t_us):  # strictly increasing (duplicates and steps back dropped)
        if t <= last:
            keep[i] = False
        else:
            last = t
    skipped[f"{what}: time not increasing"] += int((~keep).sum())
    return t_us[keep], [a[keep] for a in arrays]


def _times(data: dict[str, np.ndarray], topic: str) -> np.ndarray:
    """``timestamp`` (us) as int64; values beyond int64 become -1 (dropped by :func:`_clean`)."""
    if "timestamp" not in data:
        raise ImportDataError(f"ULog topic {topic!r} lacks a timestamp field")
    t = np.asarray(data["timestamp"])
    if t.dtype.kind == "u":
        return np.where(t > _MAX_TIME_US, -1, t.astype(np.int64, copy=False))
    return t.astype(np.int64)


def _cols(data: dict[str, np.ndarray], names: list[str], topic: str) -> np.ndarray:
    missing = [n for n in names if n not in data]
    if missing:
        raise ImportDataError(f"ULog topic {topic!r} lacks field(s) {missing}")
    return np.stack([np.asarray(data[n], dtype=np.float64) for n in names], axis=1)


def convert_ulog(
    path: str | os.PathLike[str] | ParsedULog, time_limit_s: float | None = None
) -> FlightStreams:
    """Read a ULog file (under a time limit, see :func:`read_ulog`) and convert it to
    :class:`FlightStreams`; ``path`` may also be an already parsed :class:`ParsedULog`."""
    if isinstance(path, ParsedULog):
        p, ulog = Path("<memory>"), path
    else:
        p = check_source(path)
        ulog = read_ulog(p, time_limit_s)
    skipped: Counter = Counter()
    notes: list[str] = []
    sc = _dataset(ulog, "sensor_combined")
    att = _dataset(ulog, "vehicle_attitude")
    if sc is None or att is None:
        raise ImportDataError(
            f"ULog {str(p)!r} lacks sensor_combined or vehicle_attitude",
            hint="log these topics (PX4 SDLOG_PROFILE default includes them)",
        )
    imu_t = _times(sc, "sensor_combined")
    acc = _cols(sc, [f"accelerometer_m_s2[{i}]" for i in range(3)], "sensor_combined")
    gyr = _cols(sc, [f"gyro_rad[{i}]" for i in range(3)], "sensor_combined")
    imu_t, (acc, gyr) = _clean(imu_t, [acc, gyr], "sensor_combined", skipped)

    att_t = _times(att, "vehicle_attitude")
    q = _cols(att, [f"q[{i}]" for i in range(4)], "vehicle_attitude")
    if all(k in att for k in ("rollspeed", "pitchspeed", "yawspeed")):
        rates = _cols(att, ["rollspeed", "pitchspeed", "yawspeed"], "vehicle_attitude")
        notes.append("attitude rates from vehicle_attitude roll/pitch/yawspeed")
    else:
        rates = np.full((att_t.size, 3), np.nan)
    norm = np.linalg.norm(q, axis=1)
    bad_q = ~(np.abs(norm - 1.0) < 1e-3)
    skipped["vehicle_attitude: quaternion not unit norm"] += int(bad_q.sum())
    att_t, q, rates = att_t[~bad_q], q[~bad_q], rates[~bad_q]
    if np.isnan(rates).any():
        rates = gyr[nearest_index(imu_t, att_t)] if imu_t.size else np.zeros_like(rates)
        notes.append("attitude rates: nearest sensor_combined gyro sample")
    att_t, (q, rates) = _clean(att_t, [q, rates], "vehicle_attitude", skipped)
    q = canonical_quat(q)

    pose_t = np.zeros(0, np.int64)
    pos = np.zeros((0, 3))
    lp = _dataset(ulog, "vehicle_local_position")
    if lp is None:
        notes.append("no vehicle_local_position: no positions")
    else:
        pose_t = _times(lp, "vehicle_local_position")
        pos = _cols(lp, ["x", "y", "z"], "vehicle_local_position")
        valid = np.ones(pose_t.size, bool)
        for flag in ("xy_valid", "z_valid"):
            if flag in lp:
                valid &= np.asarray(lp[flag]) != 0
        skipped["vehicle_local_position: xy/z not valid"] += int((~valid).sum())
        pose_t, pos = pose_t[valid], pos[valid]
        pose_t, (pos,) = _clean(pose_t, [pos], "vehicle_local_position", skipped)
    if imu_t.size == 0 or att_t.size == 0:
        raise ImportDataError(f"ULog {str(p)!r} has no usable IMU or attitude samples")
    q_pose = q[nearest_index(att_t, pose_t)] if pose_t.size else np.zeros((0, 4))

    t0 = 0
    last_us = max(int(imu_t[-1]), int(att_t[-1]), int(pose_t[-1]) if pose_t.size else 0)
    if last_us // 1000 > _MAX_BOOT_MS:
        t0 = int(ulog.start_timestamp)
        notes.append(f"times rebased to the log start ({t0} us): clock too large for time_boot_ms")
    first = min(int(imu_t[0]), int(att_t[0]), int(pose_t[0]) if pose_t.size else 2**62)
    if first < t0:
        t0 = first
    notes.append("ULog is already SI, body FRD, NED, q (w,x,y,z): no unit/frame change")
    skipped = Counter({k: v for k, v in skipped.items() if v})
    return FlightStreams(
        imu_t_ns=(imu_t - t0) * 1000,
        accel_frd=acc,
        gyro_frd=gyr,
        att_t_ns=(att_t - t0) * 1000,
        q_ned_frd=q,
        rates_frd=rates,
        pose_t_ns=(pose_t - t0) * 1000,
        pos_ned=pos,
        q_pose=q_pose,
        skipped=skipped,
        notes=notes,
    )


def import_ulog(
    src: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    pose_transport: str = "natnet",
    created_by: str = "groundstation import ulog",
    time_limit_s: float | None = None,
) -> ImportReport:
    """Import a PX4 ULog file into a recording at ``out`` (pyulog under ``time_limit_s``)."""
    streams = convert_ulog(src, time_limit_s)
    name = Path(src).name
    return write_flight(
        streams,
        out,
        source=str(src),
        created_by=created_by,
        link_uri=f"import:ulog:{name}",
        mocap_uri=f"import:ulog:{name}#vehicle_local_position",
        pose_transport=pose_transport,
    )
