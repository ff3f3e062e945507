"""Import CSV IMU files such as ``aggressive_flight`` (Xsens DOT on a DJI Phantom 4 RTK).

Input columns (``IMU_*.csv``, 120 Hz): ``time`` s, ``Euler_X/Y/Z`` deg, ``Acc_X/Y/Z`` m/s^2
(specific force, gravity included), ``Gyr_X/Y/Z`` deg/s. Optional ``GT.csv`` beside it (RTK, 10
Hz): ``time`` s, ``compass_heading``/``pitch``/``roll`` deg, ``North``/``East``/``Down`` m.

Conventions, verified on the data (tests/contract/test_importers.py):

- Sensor frame S is right-handed with z up (Xsens): a hovering vehicle reads Acc_Z ~ +9.8
  (specific force points up). With x forward this is FLU, and FRD = diag(1, -1, -1) S, so
  ``accel_frd = (Ax, -Ay, -Az)``, ``gyro_frd = deg2rad(Gx, -Gy, -Gz)``.
- Euler angles are Xsens's: roll X, pitch Y, yaw Z, ``R_ENU<-S = Rz(yaw) Ry(pitch) Rx(roll)``
  (intrinsic Z-Y-X) with the local frame ENU. Check: rotating the specific force to ENU with it
  gives a flight mean of (0.0 +- 0.3, 0.0 +- 0.3, 9.73) m/s^2 on all three paths (a periodic
  path has zero mean acceleration), while the X-Y-Z order leaves 1-4 m/s^2 horizontally.
  Then ``q_NED<-FRD = q_NED<-ENU * q_ENU<-FLU * q_FLU<-FRD``
  (``firmware_bridge.frames.quat_enu_flu_to_ned_frd``).
- Euler_X equals GT roll and Euler_Y equals minus GT pitch (correlation > 0.98 on all paths),
  confirming x forward and the FLU -> FRD flip.
- GT times are not aligned with IMU times on every path (Horizontal/path_1: the GT leads by
  0.68 s). The lag is estimated by cross-correlating GT roll with Euler_X (+-3 s, 10 ms steps);
  positions are imported at ``t_GT + lag`` when the correlation is >= 0.9, else left out (noted).
  GT orientation (DJI heading/pitch/roll, aerospace Z-Y-X in NED) becomes the pose orientation.

Data licence: CC BY 4.0, Hurwitz and Klein, "Quadrotor Dead Reckoning with Multiple Inertial
Sensors" (attribution stored in the recording's metadata).
"""

from __future__ import annotations

import csv
import io
import math
import os
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from groundstation.acquisition.importers import (
    FlightStreams,
    ImportDataError,
    ImportReport,
    canonical_quat,
    check_source,
    quat_from_euler_zyx,
    write_flight,
)

IMU_COLUMNS = (
    "time", "Euler_X", "Euler_Y", "Euler_Z", "Acc_X", "Acc_Y", "Acc_Z", "Gyr_X", "Gyr_Y", "Gyr_Z",
)  # fmt: skip
GT_COLUMNS = ("time", "compass_heading(degrees)", "pitch(degrees)", "roll(degrees)")
GT_POSITION = ("North", "East", "Down")
FLU_TO_FRD = np.array([1.0, -1.0, -1.0])
MIN_LAG_CORRELATION = 0.9
ATTRIBUTION = (
    "aggressive_flight data: CC BY 4.0, Hurwitz and Klein, "
    "'Quadrotor Dead Reckoning with Multiple Inertial Sensors'"
)


#: Plausible magnitude of each column (by name prefix); rows beyond are skipped and counted.
#: Xsens DOT: +-16 g, +-2000 deg/s; time in s since the start (< 1e9 s keeps ns in int64).
LIMITS = {
    "time": 1e9,
    "Acc_": 1e4,  # m/s^2
    "Gyr_": 1e5,  # deg/s
    "Euler_": 1e4,  # deg
    "North": 1e7,  # m
    "East": 1e7,
    "Down": 1e7,
    "compass_heading": 1e4,  # deg
    "pitch": 1e4,
    "roll": 1e4,
}
_MAX_LINE_ERRORS_NAMED = 3


def _limit(column: str) -> float:
    for prefix, limit in LIMITS.items():
        if column.startswith(prefix):
            return limit
    return 1e6


def read_numeric_csv(
    path: str | os.PathLike[str], columns: tuple[str, ...], skipped: Counter
) -> dict[str, np.ndarray]:
    """Read the named columns of a CSV file with a header row.

    Rows with the wrong field count, non-numbers (including bytes that are not UTF-8),
    non-finite values or values beyond :data:`LIMITS` (``time`` must be in [0, 1e9) s), lines
    the CSV parser rejects (NUL bytes, oversized fields), and rows whose ``time`` does not
    increase, are skipped and counted in ``skipped`` by reason.

    Returns
    -------
    dict of column name -> (n,) float64

    Raises
    ------
    ImportDataError
        No header, missing columns, or no usable row.
    """
    p = check_source(path)
    try:
        f = open(p, newline="", encoding="utf-8-sig", errors="surrogateescape")  # noqa: SIM115
    except OSError as exc:
        raise ImportDataError(f"cannot read {str(p)!r}: {exc.strerror or exc}") from None
    with f:
        return _parse_rows(csv.reader(f), p.name, str(p), columns, skipped)


def parse_numeric_csv(
    text: str, columns: tuple[str, ...], skipped: Counter, name: str = "<csv>"
) -> dict[str, np.ndarray]:
    """:func:`read_numeric_csv` on text in memory (the same rules)."""
    return _parse_rows(csv.reader(io.StringIO(text, newline="")), name, name, columns, skipped)


def _parse_rows(
    reader: Iterator[list[str]],
    name: str,
    where: str,
    columns: tuple[str, ...],
    skipped: Counter,
) -> dict[str, np.ndarray]:
    header = None
    while header is None:
        try:
            header = [h.strip() for h in next(reader)]
        except StopIteration:
            raise ImportDataError(f"{where!r} is empty") from None
        except csv.Error as exc:
            raise ImportDataError(f"{where!r}: the header line is not CSV ({exc})") from None
    missing = [c for c in columns if c not in header]
    if missing:
        shown = [h.encode("utf-8", "backslashreplace").decode()[:40] for h in header[:20]]
        raise ImportDataError(
            f"{where!r} lacks column(s) {missing}; header is {shown}",
            hint="expected the aggressive_flight layout (time, Euler_*, Acc_*, Gyr_*)",
        )
    idx = [header.index(c) for c in columns]
    limits = [_limit(c) for c in columns]
    t_col = columns.index("time")
    rows: list[list[float]] = []
    last_t = -math.inf
    while True:
        try:
            row = next(reader)
        except StopIteration:
            break
        except csv.Error as exc:  # NUL byte, field beyond csv.field_size_limit()
            reason = f"{name}: malformed CSV line"
            if skipped[reason] < _MAX_LINE_ERRORS_NAMED:
                skipped[f"{name}: line {getattr(reader, 'line_num', '?')}: {exc}"] += 1
            skipped[reason] += 1
            continue
        if not row or all(not c.strip() for c in row):
            continue
        if len(row) != len(header):
            skipped[f"{name}: wrong field count"] += 1
            continue
        try:
            values = [float(row[i]) for i in idx]
        except (ValueError, UnicodeEncodeError):
            skipped[f"{name}: not a number"] += 1
            continue
        if not all(math.isfinite(v) for v in values):
            skipped[f"{name}: NaN/inf"] += 1
            continue
        if values[t_col] < 0 or any(abs(v) >= lim for v, lim in zip(values, limits, strict=True)):
            skipped[f"{name}: value out of range"] += 1
            continue
        if values[t_col] <= last_t:
            skipped[f"{name}: time not increasing"] += 1
            continue
        last_t = values[t_col]
        rows.append(values)
    if not rows:
        raise ImportDataError(f"{where!r} has no usable rows ({dict(skipped)})")
    data = np.asarray(rows, dtype=np.float64)
    return {c: data[:, k] for k, c in enumerate(columns)}


def convert_xsens(cols: dict[str, np.ndarray]) -> FlightStreams:
    """Convert Xsens IMU columns to body FRD / NED streams (see the module docstring).

    Parameters
    ----------
    cols : dict
        ``time`` (n,) s; ``Euler_X/Y/Z`` deg; ``Acc_X/Y/Z`` m/s^2; ``Gyr_X/Y/Z`` deg/s.
    """
    from firmware_bridge.frames import quat_enu_flu_to_ned_frd

    t_ns = np.round(cols["time"] * 1e9).astype(np.int64)
    if t_ns.size and t_ns[0] < 0:
        raise ImportDataError(f"IMU time starts at {cols['time'][0]} s; must be >= 0")
    acc = np.stack([cols["Acc_X"], cols["Acc_Y"], cols["Acc_Z"]], axis=1) * FLU_TO_FRD
    gyr = np.radians(np.stack([cols["Gyr_X"], cols["Gyr_Y"], cols["Gyr_Z"]], axis=1)) * FLU_TO_FRD
    q_enu_flu = quat_from_euler_zyx(
        np.radians(cols["Euler_X"]), np.radians(cols["Euler_Y"]), np.radians(cols["Euler_Z"])
    )
    q = canonical_quat(quat_enu_flu_to_ned_frd(q_enu_flu))
    return FlightStreams(
        imu_t_ns=t_ns,
        accel_frd=acc,
        gyro_frd=gyr,
        att_t_ns=t_ns.copy(),
        q_ned_frd=q,
        rates_frd=gyr.copy(),
        notes=[
            "IMU: Xsens sensor frame (x fwd, z up) -> body FRD (x, -y, -z); deg/s -> rad/s",
            "attitude: Xsens Euler ZYX (ENU) -> quaternion FRD->NED",
        ],
    )


def estimate_lag(
    t_ref: np.ndarray,
    x_ref: np.ndarray,
    t_other: np.ndarray,
    x_other: np.ndarray,
    max_lag_s: float = 3.0,
    step_s: float = 0.01,
) -> tuple[float, float]:
    """Lag that best aligns two signals: ``x_other(t)`` matches ``x_ref(t + lag)``.

    Parameters
    ----------
    t_ref, x_ref : (n,) arrays
        Reference signal (s, any unit), ``t_ref`` increasing.
    t_other, x_other : (m,) arrays
        Signal to align (s, same unit).
    max_lag_s, step_s : float
        Search range and step, s.

    Returns
    -------
    lag_s : float
    correlation : float
        Pearson correlation at that lag (nan if no lag had >= 10 overlapping samples).
    """
    best = (0.0, -math.inf)
    for lag in np.arange(-max_lag_s, max_lag_s + step_s / 2, step_s):
        tt = t_other + lag
        ok = (tt >= t_ref[0]) & (tt <= t_ref[-1])
        if ok.sum() < 10:
            continue
        a = np.interp(tt[ok], t_ref, x_ref)
        b = x_other[ok]
        if a.std() == 0 or b.std() == 0:
            continue
        c = float(np.corrcoef(a, b)[0, 1])
        if c > best[1]:
            best = (float(lag), c)
    return (best[0], best[1]) if math.isfinite(best[1]) else (0.0, math.nan)


def add_ground_truth(
    streams: FlightStreams, imu: dict[str, np.ndarray], gt: dict[str, np.ndarray]
) -> float:
    """Align ``GT.csv`` to the IMU clock and add its positions as poses (in place).

    Returns the lag applied (s); leaves the poses empty (with a note) if alignment fails.
    """
    lag, corr = estimate_lag(imu["time"], imu["Euler_X"], gt["time"], gt["roll(degrees)"])
    if not (corr >= MIN_LAG_CORRELATION):
        streams.notes.append(
            f"GT.csv not aligned (best roll correlation {corr:.2f} < {MIN_LAG_CORRELATION}): "
            "positions left out"
        )
        return math.nan
    t_ns = np.round((gt["time"] + lag) * 1e9).astype(np.int64)
    keep = (t_ns >= streams.imu_t_ns[0]) & (t_ns <= streams.imu_t_ns[-1])
    streams.skipped["GT.csv: outside the IMU time span after alignment"] += int((~keep).sum())
    streams.pose_t_ns = t_ns[keep]
    streams.pos_ned = np.stack([gt[c] for c in GT_POSITION], axis=1)[keep]
    streams.q_pose = quat_from_euler_zyx(
        np.radians(gt["roll(degrees)"][keep]),
        np.radians(gt["pitch(degrees)"][keep]),
        np.radians(gt["compass_heading(degrees)"][keep]),
    )
    streams.notes.append(
        f"GT.csv aligned to the IMU clock: lag {lag:+.2f} s (roll correlation {corr:.3f}); "
        "RTK North/East/Down relative to take-off, DJI heading/pitch/roll -> pose quaternion"
    )
    return lag


def convert_csv(imu_path: str | os.PathLike[str], gt_path: str | None = None) -> FlightStreams:
    """Read and convert one IMU CSV (and ``GT.csv`` if given or found beside it)."""
    skipped: Counter = Counter()
    imu = read_numeric_csv(imu_path, IMU_COLUMNS, skipped)
    streams = convert_xsens(imu)
    streams.skipped.update(skipped)
    gt_file = Path(gt_path) if gt_path else Path(imu_path).with_name("GT.csv")
    if gt_file.is_file():
        gt = read_numeric_csv(gt_file, GT_COLUMNS + GT_POSITION, streams.skipped)
        add_ground_truth(streams, imu, gt)
    else:
        streams.notes.append(f"no ground truth ({gt_file.name} not found): no positions")
    streams.notes.append(ATTRIBUTION)
    return streams


def import_csv(
    src: str | os.PathLike[str],
    out: str | os.PathLike[str],
    *,
    gt_path: str | None = None,
    pose_transport: str = "natnet",
    created_by: str = "groundstation import csv",
) -> ImportReport:
    """Import an IMU CSV file (plus ground truth) into a recording at ``out``."""
    streams = convert_csv(src, gt_path)
    lag_note = [n for n in streams.notes if n.startswith("GT.csv aligned")]
    truth = {
        "source": "aggressive_flight CSV",
        "contacts": [],
        "contact_free": True,
        "note": "no contact happened in this flight: every detected contact is a false positive",
        "attribution": ATTRIBUTION,
        "ground_truth_alignment": lag_note[0] if lag_note else "none",
    }
    return write_flight(
        streams,
        out,
        source=str(src),
        created_by=created_by,
        link_uri=f"import:csv:{Path(src).name}",
        mocap_uri=f"import:csv:{Path(gt_path).name if gt_path else 'GT.csv'}",
        pose_transport=pose_transport,
        truth=truth,
    )
