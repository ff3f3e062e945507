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
"""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.acquisition.importers import (
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


def _dataset(ulog: Any, name: str) -> dict[str, np.ndarray] | None:
    for d in ulog.data_list:
        if d.name == name and d.multi_id == 0:
            return d.data
    return None


def _clean(
    t_us: np.ndarray, arrays: list[np.ndarray], what: str, skipped: Counter
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Drop rows with non-finite values or non-increasing time, counting them."""
    finite = np.all(np.stack([np.all(np.isfinite(a), axis=1) for a in arrays]), axis=0)
    skipped[f"{what}: NaN/inf"] += int((~finite).sum())
    t_us, arrays = t_us[finite], [a[finite] for a in arrays]
    keep = np.ones(t_us.size, bool)
    last = -1
    for i, t in enumerate(t_us):  # strictly increasing (duplicates and steps back dropped)
        if t <= last:
            keep[i] = False
        else:
            last = t
    skipped[f"{what}: time not increasing"] += int((~keep).sum())
    return t_us[keep], [a[keep] for a in arrays]


def _cols(data: dict[str, np.ndarray], names: list[str], topic: str) -> np.ndarray:
    missing = [n for n in names if n not in data]
    if missing:
        raise ImportDataError(f"ULog topic {topic!r} lacks field(s) {missing}")
    return np.stack([np.asarray(data[n], dtype=np.float64) for n in names], axis=1)


def convert_ulog(path: str | os.PathLike[str]) -> FlightStreams:
    """Read a ULog file and convert it to :class:`FlightStreams`."""
    from pyulog import ULog

    p = check_source(path)
    try:
        ulog = ULog(str(p), list(TOPICS))
    except Exception as exc:  # noqa: BLE001 - pyulog raises assorted errors on bad files
        raise ImportDataError(f"cannot read ULog {str(p)!r}: {exc}") from None
    skipped: Counter = Counter()
    notes: list[str] = []
    sc = _dataset(ulog, "sensor_combined")
    att = _dataset(ulog, "vehicle_attitude")
    if sc is None or att is None:
        raise ImportDataError(
            f"ULog {str(p)!r} lacks sensor_combined or vehicle_attitude",
            hint="log these topics (PX4 SDLOG_PROFILE default includes them)",
        )
    imu_t = np.asarray(sc["timestamp"], dtype=np.int64)
    acc = _cols(sc, [f"accelerometer_m_s2[{i}]" for i in range(3)], "sensor_combined")
    gyr = _cols(sc, [f"gyro_rad[{i}]" for i in range(3)], "sensor_combined")
    imu_t, (acc, gyr) = _clean(imu_t, [acc, gyr], "sensor_combined", skipped)

    att_t = np.asarray(att["timestamp"], dtype=np.int64)
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
        pose_t = np.asarray(lp["timestamp"], dtype=np.int64)
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
) -> ImportReport:
    """Import a PX4 ULog file into a recording at ``out``."""
    streams = convert_ulog(src)
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
