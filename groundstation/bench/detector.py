"""``groundstation bench detector``: false contacts per minute on real flights vs recall on touches.

Two kinds of input go through the same decoders a live session or a replay uses:

- **Real flights** (``aggressive_flight``: Horizontal/path_1, Horizontal/path_4, Vertical/path_1,
  ``IMU_1.csv`` and ``IMU_avg.csv``) are imported with the CSV importer into a temporary MCAP and
  read back with :func:`groundstation.acquisition.replay.iter_replay`. No contact happened in these
  flights (SOURCES.md): every detected contact is a false positive.
- **Simulated touches**: SITL survey (and slow-touch) sessions, whose wire bytes
  (:meth:`Simulation.outputs`) go through the live ``MavlinkStreamDecoder`` /
  ``NatNetStreamDecoder`` with the simulated time as receive time; the ground truth lists
  touch / slow_touch / gust events.

Each trace becomes earth-frame acceleration (``contact.earth_acceleration``, batched), paired with
the nearest attitude (max gap ``ATT_GAP_NS``) and an interpolated position (max gap
``POSE_GAP_NS``). For each filter variant the trace is filtered once with the detector's own filter
(``contact.filters.make_filter``), then a :class:`ContactDetector` with ``filter="none"`` runs per
threshold on the filtered vectors. Only the samples that can change the contact state are fed: those
with ``|a_f| >= release_ratio * a0`` and the first sample after each run of them (a sample below the
release level outside a contact changes nothing but external observations, which the bench does not
use), so events and contact observations equal those of a full run (tested).

Metrics per (filter, threshold): real-flight detected events per minute and fraction of samples
above a0; on the SITL sessions, recall of ``touch`` events (a detection matches a truth event when
their intervals overlap within ``tolerance_s``), the same for ``slow_touch`` (expected misses), the
fraction of gusts detected and detected gusts per minute, other unmatched detections per minute,
precision (detections on real contacts / all detections) and the localisation error of the
contact point (paper's cylinder rule, r and h from ContactSettings) of matched touches: distance to
the truth contact point and distance to the true surface, both at the event's peak observation.

Data licence: the aggressive_flight data is CC BY 4.0, Hurwitz and Klein, "Quadrotor Dead Reckoning
with Multiple Inertial Sensors"; the attribution is printed and written with every result.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.contact import ContactDetector, ContactSettings, G
from groundstation.contact.detector import LABEL_SURFACE
from groundstation.contact.filters import make_filter
from groundstation.errors import GroundstationError

ATTRIBUTION = (
    "aggressive_flight data: CC BY 4.0, Hurwitz and Klein, "
    "'Quadrotor Dead Reckoning with Multiple Inertial Sensors' "
    "(github.com/ansfl/Quadrotor-Dead-Reckoning-with-Multiple-Inertial-Sensors)"
)
REAL_PATHS = ("Horizontal/path_1", "Horizontal/path_4", "Vertical/path_1")
REAL_FILES = ("IMU_1.csv", "IMU_avg.csv")
SCENES = ("wall", "pillar", "pier")
PILOTS = ("survey", "slow_touch")
# 0.3 .. 1.2 G in 0.1 G steps (the task's range), then coarser to show where recall falls off.
DEFAULT_THRESHOLDS = tuple(round(0.3 + 0.1 * k, 2) for k in range(10)) + (1.5, 2.0, 2.5)
DEFAULT_FILTERS = (
    "moving_average:0.03",
    "moving_average:0.05",
    "moving_average:0.1",
    "butterworth2:5",
    "butterworth2:8",
    "butterworth2:15",
    "none",
)
ATT_GAP_NS = 50_000_000  # attitude farther than this from an IMU sample: sample dropped
POSE_GAP_NS = 250_000_000  # bracketing poses farther apart than this: no position
MAX_SIM_S = 600.0  # a session that never finishes its script stops here
# The detector's filters output the raw first sample (moving average of one sample; Butterworth
# started at steady state), so a trace can fire at its very first sample. Events that start this
# close to a trace's start are counted separately ("warm-up"), and the real-flight peak used for
# the threshold margin leaves this span out.
WARMUP_S = 0.2


class BenchDataError(GroundstationError):
    """The bench cannot find or use its input (external data, filter spec, thresholds)."""


# --- traces -------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class TruthEvent:
    """A ground-truth event: ``kind`` (touch, slow_touch, gust, ground), times s, point m/None."""

    kind: str
    start_s: float
    end_s: float
    point: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class Trace:
    """One flight as the detector sees it.

    Attributes
    ----------
    name : str
    source : {"real", "sitl"}
    t_ns : (n,) int64, strictly increasing, station time ns
    accel : (n, 3) float64, gravity-compensated acceleration, world ENU, m/s^2
    position : (n, 3) float64, world metres; NaN rows where no pose was available
    truth : tuple of TruthEvent (empty for the real flights)
    scene : str or None
        SITL scene name (for the surface distance of contact points).
    dropped : int
        IMU samples dropped (no attitude within ``ATT_GAP_NS``, non-finite, time not increasing).
    """

    name: str
    source: str
    t_ns: np.ndarray
    accel: np.ndarray
    position: np.ndarray
    truth: tuple[TruthEvent, ...] = ()
    scene: str | None = None
    dropped: int = 0

    @property
    def duration_s(self) -> float:
        return float(self.t_ns[-1] - self.t_ns[0]) / 1e9 if self.t_ns.size > 1 else 0.0


def earth_accelerations(specific_force_frd: np.ndarray, q_frd_ned: np.ndarray) -> np.ndarray:
    """Batched :func:`groundstation.contact.earth_acceleration`: a = R f + g, NED -> ENU.

    Parameters
    ----------
    specific_force_frd : (n, 3) m/s^2, body FRD
    q_frd_ned : (n, 4) (w, x, y, z), body FRD -> local NED

    Returns
    -------
    (n, 3) float64, world ENU, m/s^2
    """
    from firmware_bridge.frames import ned_to_enu, quat_to_matrix

    f = np.asarray(specific_force_frd, dtype=float)
    a_ned = np.einsum("nij,nj->ni", quat_to_matrix(q_frd_ned), f) + np.array([0.0, 0.0, G])
    return ned_to_enu(a_ned)


def collect_samples(messages: Iterable[Any]) -> dict[str, np.ndarray]:
    """Stack decoded ``samples.imu`` / ``samples.attitude`` / ``samples.pose`` messages.

    ``messages`` are :class:`~groundstation.acquisition.decoders.Decoded` or bus envelopes
    (anything with ``topic``, ``payload`` and ``arrays``); invalid poses are left out.

    Returns
    -------
    dict with imu_t (n,), accel (n, 3), att_t (m,), q (m, 4), pose_t (k,), pos (k, 3)
    """
    cols: dict[str, list] = {k: [] for k in ("imu_t", "accel", "att_t", "q", "pose_t", "pos")}
    for m in messages:
        if m.topic == "samples.imu":
            cols["imu_t"].append(int(m.payload["t_station_ns"]))
            cols["accel"].append(m.arrays["accel_mps2"])
        elif m.topic == "samples.attitude":
            cols["att_t"].append(int(m.payload["t_station_ns"]))
            cols["q"].append(m.arrays["q_wxyz"])
        elif m.topic == "samples.pose" and m.payload.get("valid", True):
            cols["pose_t"].append(int(m.payload["t_station_ns"]))
            cols["pos"].append(m.arrays["position_m"])
    shapes = {"accel": (0, 3), "q": (0, 4), "pos": (0, 3)}
    return {
        k: (np.asarray(v, dtype=np.int64) if k.endswith("_t") else np.asarray(v, float))
        if v
        else np.zeros(shapes.get(k, (0,)), np.int64 if k.endswith("_t") else float)
        for k, v in cols.items()
    }


def build_trace(name: str, source: str, s: dict[str, np.ndarray], truth=(), scene=None) -> Trace:
    """Pair IMU samples with the nearest attitude and an interpolated position (pure)."""
    t, f = s["imu_t"], s["accel"]
    if t.size == 0 or s["att_t"].size == 0:
        raise BenchDataError(f"{name}: no IMU or attitude samples were decoded")
    order = np.argsort(s["att_t"], kind="stable")
    at, q = s["att_t"][order], s["q"][order]
    k = np.clip(np.searchsorted(at, t), 1, at.size - 1) if at.size > 1 else np.zeros_like(t)
    if at.size > 1:
        k = np.where(np.abs(at[k - 1] - t) <= np.abs(at[k] - t), k - 1, k)
    keep = (np.abs(at[k] - t) <= ATT_GAP_NS) & np.isfinite(f).all(axis=1)
    keep &= np.concatenate([[True], np.diff(t) > 0])  # the detector rejects non-increasing time
    t, f, k = t[keep], f[keep], k[keep]
    if t.size < 2:
        raise BenchDataError(f"{name}: fewer than 2 IMU samples have an attitude")
    accel = earth_accelerations(f, q[k])
    pos = np.full((t.size, 3), np.nan)
    pt, pp = s["pose_t"], s["pos"]
    if pt.size >= 2:
        o = np.argsort(pt, kind="stable")
        pt, pp = pt[o], pp[o]
        j = np.searchsorted(pt, t)  # pt[j - 1] < t <= pt[j]
        jj = np.clip(j, 1, pt.size - 1)
        exact = pt[np.minimum(j, pt.size - 1)] == t
        ok = exact | ((j > 0) & (j < pt.size) & ((pt[jj] - pt[jj - 1]) <= POSE_GAP_NS))
        for ax in range(3):
            pos[:, ax] = np.where(ok, np.interp(t, pt, pp[:, ax]), np.nan)
    return Trace(name, source, t, accel, pos, tuple(truth), scene, int((~keep).sum()))


# --- detection ----------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class FilterSpec:
    """A named filter with its parameter: ``moving_average:0.05`` (window s), ``butterworth2:8``
    (cutoff Hz) or ``none``; a bare name takes the parameter of the base settings."""

    name: str
    window_s: float
    cutoff_hz: float

    @classmethod
    def parse(cls, text: str, base: ContactSettings) -> FilterSpec:
        name, _, param = text.strip().partition(":")
        try:
            value = float(param) if param else None
        except ValueError:
            raise BenchDataError(f"filter {text!r}: parameter {param!r} is not a number") from None
        if name not in ("moving_average", "butterworth2", "none"):
            raise BenchDataError(
                f"unknown filter {name!r} in {text!r}",
                hint="use moving_average[:window_s], butterworth2[:cutoff_hz] or none",
            )
        if value is not None and not (math.isfinite(value) and value > 0):
            raise BenchDataError(f"filter {text!r}: parameter must be a number > 0")
        w = value if name == "moving_average" and value else base.window_s
        c = value if name == "butterworth2" and value else base.cutoff_hz
        return cls(name, w, c)

    @property
    def label(self) -> str:
        if self.name == "moving_average":
            return f"moving_average {self.window_s * 1e3:g} ms"
        if self.name == "butterworth2":
            return f"butterworth2 {self.cutoff_hz:g} Hz"
        return "none"

    def settings(self, base: ContactSettings, threshold_g: float) -> ContactSettings:
        return dataclasses.replace(
            base,
            filter=self.name,
            window_s=self.window_s,
            cutoff_hz=self.cutoff_hz,
            threshold_g=threshold_g,
        )


def filter_trace(trace: Trace, spec: FilterSpec) -> np.ndarray:
    """The detector's filter run over the trace: (n, 3) filtered acceleration, m/s^2."""
    filt = make_filter(spec.name, spec.window_s, spec.cutoff_hz)
    out = np.empty_like(trace.accel)
    for i, (t, a) in enumerate(zip(trace.t_ns.tolist(), trace.accel, strict=True)):
        out[i] = filt.update(t, a)
    return out


@dataclasses.dataclass(frozen=True)
class Detection:
    """One detected contact event: times s, peak |a_f| in G, contact point at the peak (m, NaN
    when no pose)."""

    start_s: float
    end_s: float
    peak_g: float
    point: np.ndarray


def detect(
    trace: Trace, filtered: np.ndarray, settings: ContactSettings, *, reduced: bool = True
) -> list[Detection]:
    """Contact events of :class:`ContactDetector` on pre-filtered acceleration.

    ``settings.filter`` is ignored (the detector runs with ``filter="none"`` on ``filtered``).
    With ``reduced`` only the samples that can change the contact state are fed (module
    docstring); events and contact observations are the same as with every sample.
    """
    s = dataclasses.replace(settings, filter="none")
    det = ContactDetector(s)
    g = np.linalg.norm(filtered, axis=1) / G
    if reduced:
        hot = g >= s.release_ratio * s.threshold_g
        idx = np.flatnonzero(hot | np.concatenate([[False], hot[:-1]]))
    else:
        idx = np.arange(g.size)
    peak: dict[int, tuple[float, np.ndarray]] = {}
    t_list = trace.t_ns.tolist()
    for i in idx.tolist():
        pos = trace.position[i]
        for ob in det.update(t_list[i], filtered[i], None if np.isnan(pos[0]) else pos):
            if ob.label == LABEL_SURFACE and ob.accel_g > peak.get(ob.event_id, (-1.0,))[0]:
                peak[ob.event_id] = (ob.accel_g, ob.position)
    if det.in_contact:  # close the open event at the end of the trace (one zero sample)
        det.update(t_list[-1] + 1, np.zeros(3))
    nan3 = np.full(3, np.nan)
    return [
        Detection(e.t_start_ns / 1e9, e.t_end_ns / 1e9, e.peak_g, peak.get(e.id, (0.0, nan3))[1])
        for e in det.events
    ]


def above_fraction(filtered: np.ndarray, threshold_g: float) -> float:
    """Fraction of samples whose filtered |a| exceeds the threshold (G)."""
    return float(np.mean(np.linalg.norm(filtered, axis=1) / G > threshold_g))


def per_minute(count: int, duration_s: float) -> float:
    """Events per minute of flight (NaN for an empty duration)."""
    return count / (duration_s / 60.0) if duration_s > 0 else math.nan


PRIORITY = ("touch", "slow_touch", "ground", "gust")  # a detection counts as the first it hits


@dataclasses.dataclass
class Match:
    """Matching of detections to truth events (see :func:`match_events`).

    Attributes
    ----------
    truth_hit : list of bool, per truth event: some detection overlaps it
    truth_det : list of int, per truth event: index of the first overlapping detection or -1
    det_kind : list of str, per detection: kind of the truth event it counts for, or "none"
    """

    truth_hit: list[bool]
    truth_det: list[int]
    det_kind: list[str]


def match_events(
    truth: Sequence[TruthEvent], detections: Sequence[Detection], tolerance_s: float = 0.15
) -> Match:
    """Match by time overlap: detection [a, b] and truth [c, d] match if a <= d + tol and
    b >= c - tol. A detection overlapping several truth events counts for the kind first in
    ``PRIORITY`` (a real contact wins over a gust)."""
    hit, first = [False] * len(truth), [-1] * len(truth)
    kinds = []
    for j, d in enumerate(detections):
        best = len(PRIORITY)
        for i, e in enumerate(truth):
            if d.start_s <= e.end_s + tolerance_s and d.end_s >= e.start_s - tolerance_s:
                hit[i] = True
                if first[i] < 0:
                    first[i] = j
                if e.kind in PRIORITY:
                    best = min(best, PRIORITY.index(e.kind))
        kinds.append(PRIORITY[best] if best < len(PRIORITY) else "none")
    return Match(hit, first, kinds)


# --- metrics and sweep --------------------------------------------------------------------------


def _nanmedian(x: list[float]) -> float | None:
    a = np.asarray([v for v in x if math.isfinite(v)])
    return float(np.median(a)) if a.size else None


def evaluate(
    real: Sequence[tuple[Trace, np.ndarray]],
    sitl: Sequence[tuple[Trace, np.ndarray]],
    settings: ContactSettings,
    tolerance_s: float = 0.15,
    surface_distance=None,
) -> dict[str, Any]:
    """Metrics of one (filter, threshold) point over pre-filtered traces.

    Parameters
    ----------
    real, sitl : sequences of (Trace, (n, 3) filtered acceleration)
    settings : ContactSettings
        Threshold, hysteresis, refractory time, r and h (its ``filter`` is ignored).
    surface_distance : callable (scene name, (k, 3) points) -> (k,) metres, optional
        Signed distance to the true structures; without it the surface error is not measured.

    Returns
    -------
    dict (JSON-ready; rates per minute, fractions in [0, 1], distances in metres)
    """
    thr = settings.threshold_g
    out: dict[str, Any] = {"real": {}, "real_paths": {}}
    groups: dict[str, list[float]] = {}  # group -> [events, minutes, samples above, samples]
    for trace, filt in real:
        dets = detect(trace, filt, settings)
        n_ev = len(dets)
        t0 = trace.t_ns[0] / 1e9
        warm = sum(d.start_s - t0 < WARMUP_S for d in dets)
        above = above_fraction(filt, thr)
        out["real_paths"][trace.name] = {
            "events": n_ev,
            "warmup_events": warm,
            "minutes": trace.duration_s / 60,
            "per_min": per_minute(n_ev, trace.duration_s),
            "above": above,
        }
        for group in ("all", trace.name.rsplit("/", 1)[-1]):
            acc = groups.setdefault(group, [0.0, 0.0, 0.0, 0.0, 0.0])
            acc[0] += n_ev
            acc[1] += trace.duration_s / 60
            acc[2] += above * len(filt)
            acc[3] += len(filt)
            acc[4] += warm
    for group, (ev, minutes, above_n, n, warm) in groups.items():
        out["real"][group] = {
            "warmup_events": int(warm),
            "events": int(ev),
            "minutes": minutes,
            "per_min": ev / minutes if minutes else math.nan,
            "per_min_after_warmup": (ev - warm) / minutes if minutes else math.nan,
            "above": above_n / n if n else math.nan,
        }
    c = dict.fromkeys(
        (
            "touch",
            "touch_hit",
            "slow_touch",
            "slow_touch_hit",
            "gust",
            "gust_hit",
            "detections",
            "det_contact",
            "det_gust",
            "det_none",
        ),
        0,
    )
    minutes, point_err, surf_err = 0.0, [], []
    for trace, filt in sitl:
        dets = detect(trace, filt, settings)
        m = match_events(trace.truth, dets, tolerance_s)
        minutes += trace.duration_s / 60
        c["detections"] += len(dets)
        for kind in m.det_kind:
            key = {"gust": "det_gust", "none": "det_none"}.get(kind, "det_contact")
            c[key] += 1
        for e, hit, j in zip(trace.truth, m.truth_hit, m.truth_det, strict=True):
            if e.kind in ("touch", "slow_touch", "gust"):
                c[e.kind] += 1
                c[e.kind + "_hit"] += int(hit)
            if e.kind == "touch" and hit and e.point is not None:
                p = dets[j].point
                if np.isfinite(p).all():
                    point_err.append(float(np.linalg.norm(p - e.point)))
                    if surface_distance is not None and trace.scene:
                        surf_err.append(abs(float(surface_distance(trace.scene, p[None])[0])))

    def ratio(a: int, b: int) -> float:
        return a / b if b else math.nan

    out["sitl"] = {
        **c,
        "minutes": minutes,
        "recall_touch": ratio(c["touch_hit"], c["touch"]),
        "recall_slow_touch": ratio(c["slow_touch_hit"], c["slow_touch"]),
        "gust_detected": ratio(c["gust_hit"], c["gust"]),
        "gust_per_min": c["det_gust"] / minutes if minutes else math.nan,
        "other_fp_per_min": c["det_none"] / minutes if minutes else math.nan,
        "precision": ratio(c["det_contact"], c["detections"]),
        "loc_point_median_m": _nanmedian(point_err),
        "loc_point_p90_m": float(np.percentile(point_err, 90)) if point_err else None,
        "loc_surface_median_m": _nanmedian(surf_err),
        "loc_matched": len(point_err),
    }
    return out


def peak_stats(
    real: Sequence[tuple[Trace, np.ndarray]],
    sitl: Sequence[tuple[Trace, np.ndarray]],
    tolerance_s: float = 0.15,
) -> dict[str, float | None]:
    """Where the threshold can go for one filter: the largest filtered |a| (G) on the real
    flights, and the peaks of filtered |a| around true touches and gusts (min / 5th percentile /
    median)."""
    real_max, warm_max = None, None
    for trace, f in real:
        g = np.linalg.norm(f, axis=1) / G
        late = (trace.t_ns - trace.t_ns[0]) >= WARMUP_S * 1e9
        if late.any():
            real_max = max(real_max or 0.0, float(g[late].max()))
        warm_max = max(warm_max or 0.0, float(g[~late].max()))
    peaks: dict[str, list[float]] = {"touch": [], "gust": []}
    for trace, filt in sitl:
        g = np.linalg.norm(filt, axis=1) / G
        t = trace.t_ns / 1e9
        for e in trace.truth:
            if e.kind in peaks:
                w = (t >= e.start_s - tolerance_s) & (t <= e.end_s + tolerance_s)
                if w.any():
                    peaks[e.kind].append(float(g[w].max()))
    out: dict[str, float | None] = {"real_max_g": real_max, "real_warmup_max_g": warm_max}
    for kind, v in peaks.items():
        a = np.asarray(v)
        out[f"{kind}_min_g"] = float(a.min()) if a.size else None
        out[f"{kind}_p05_g"] = float(np.percentile(a, 5)) if a.size else None
        out[f"{kind}_median_g"] = float(np.median(a)) if a.size else None
    return out


def sweep(
    real: Sequence[Trace],
    sitl: Sequence[Trace],
    specs: Sequence[FilterSpec],
    thresholds: Sequence[float],
    base: ContactSettings,
    tolerance_s: float = 0.15,
    surface_distance=None,
    progress=None,
) -> tuple[list[dict[str, Any]], dict[str, dict]]:
    """Evaluate every (filter, threshold); each trace is filtered once per filter.

    Returns
    -------
    rows : list of dict, one per point (``filter``, ``threshold_g``, ``default`` + metrics)
    peaks : dict of filter label -> :func:`peak_stats`
    """
    rows, peaks = [], {}
    for spec in specs:
        fr = [(tr, filter_trace(tr, spec)) for tr in real]
        fs = [(tr, filter_trace(tr, spec)) for tr in sitl]
        peaks[spec.label] = peak_stats(fr, fs, tolerance_s)
        for thr in thresholds:
            s = spec.settings(base, float(thr))
            row = {
                "filter": spec.label,
                "filter_name": spec.name,
                "window_s": spec.window_s,
                "cutoff_hz": spec.cutoff_hz,
                "threshold_g": float(thr),
                "default": is_default(s, base),
            }
            row.update(evaluate(fr, fs, s, tolerance_s, surface_distance))
            row["margin"] = threshold_margin(peaks[spec.label], float(thr))
            rows.append(row)
            if progress is not None:
                progress.update(1)
    return rows, peaks


def threshold_margin(peaks: dict, threshold_g: float) -> float | None:
    """How safely a threshold sits between the real flights and the touches:
    ``min(touch peak p5 / a0, a0 / real max)`` (> 1: above every real sample after warm-up and
    below 95 % of touch peaks; the best threshold on a fine grid is their geometric mean)."""
    lo, hi = peaks.get("real_max_g"), peaks.get("touch_p05_g")
    if lo is None and hi is None:
        return None
    return min(hi / threshold_g if hi else math.inf, threshold_g / lo if lo else math.inf)


def is_default(s: ContactSettings, base: ContactSettings) -> bool:
    """Whether ``s`` has the base settings' filter, filter parameter and threshold."""
    if s.filter != base.filter or not math.isclose(s.threshold_g, base.threshold_g):
        return False
    if s.filter == "moving_average":
        return math.isclose(s.window_s, base.window_s)
    if s.filter == "butterworth2":
        return math.isclose(s.cutoff_hz, base.cutoff_hz)
    return True


def _key(row: dict) -> tuple:
    """Ranking among points that keep the recall: fewest real false contacts/min after the
    filter warm-up (a warm-up event is a filter start-up artefact, fixed in the filter rather
    than by the threshold; it is reported), then best recall, then the widest
    :func:`threshold_margin`, then fewest simulated false positives/min. (Gusts are not avoided
    on purpose: the robust map flags them; their rate is reported.)"""
    r, s = row["real"].get("all", {}), row["sitl"]
    margin = row.get("margin")
    return (
        round(r.get("per_min_after_warmup", 0.0), 9),
        -s["recall_touch"],
        -(margin if margin is not None else 0.0),
        s["gust_per_min"] + s["other_fp_per_min"],
    )


def recommend(rows: Sequence[dict], min_recall: float = 0.95) -> dict[str, Any]:
    """The point with recall >= ``min_recall`` on touches and the fewest real false contacts/min
    (ties: :func:`_key`), and whether the default is as good (same real rate, recall kept).

    Returns
    -------
    dict with ``best`` (row or None), ``default`` (row or None), ``default_ok`` (bool) and
    ``text`` (the recommendation, with numbers)
    """
    ok = [
        r
        for r in rows
        if math.isfinite(r["sitl"]["recall_touch"]) and r["sitl"]["recall_touch"] >= min_recall
    ]
    default = next((r for r in rows if r["default"]), None)
    best = min(ok, key=_key) if ok else None
    if best is None:
        text = f"no point keeps recall >= {min_recall:.2f} on simulated touches"
        return {"best": None, "default": default, "default_ok": False, "text": text}
    default_ok = (
        default is not None
        and default["sitl"]["recall_touch"] >= min_recall
        and default["real"].get("all", {}).get("per_min_after_warmup", 0.0)
        <= best["real"].get("all", {}).get("per_min_after_warmup", 0.0)
    )
    text = f"recommended: {_describe(best)}"
    if default is None:
        text += "\n(the default settings were not among the points measured)"
    elif default_ok:
        text += f"\nthe current default ({_describe(default)}) is as good on both measures: keep it"
    else:
        text += (
            f"\nthe current default ({_describe(default)}) is NOT the best choice: "
            f"change ContactSettings to filter={best['filter_name']!r}, "
            + (
                f"window_s={best['window_s']:g}, "
                if best["filter_name"] == "moving_average"
                else ""
            )
            + (
                f"cutoff_hz={best['cutoff_hz']:g}, "
                if best["filter_name"] == "butterworth2"
                else ""
            )
            + f"threshold_g={best['threshold_g']:g}"
        )
    return {"best": best, "default": default, "default_ok": default_ok, "text": text}


def _describe(row: dict) -> str:
    r, s = row["real"].get("all", {}), row["sitl"]
    real = (
        f"{r['per_min']:.2f} false contacts/min on real flights ({r['warmup_events']} warm-up "
        f"event(s); {r['per_min_after_warmup']:.2f}/min after warm-up), "
        if r
        else ""
    )
    return (
        f"{row['filter']}, a0 = {row['threshold_g']:g} G: {real}"
        f"touch recall {s['recall_touch']:.3f}, gusts detected {s['gust_detected']:.2f}, "
        f"other false positives {s['other_fp_per_min']:.2f}/min, "
        f"margin {_fmt(row.get('margin'))}"
    )


# --- inputs (I/O shells) ------------------------------------------------------------------------


def external_data_root() -> Path:
    """``GS_EXTERNAL_DATA`` or ``<project root>/../shared/external_data`` (as tests/conftest.py)."""
    default = Path(__file__).resolve().parents[2].parent / "shared" / "external_data"
    return Path(os.environ.get("GS_EXTERNAL_DATA", default))


def load_real_flight(root: Path, path: str, file: str, workdir: Path) -> Trace:
    """Import one aggressive_flight CSV through the CSV importer into an MCAP in ``workdir`` and
    read it back through the replay decoders (what a replay of the import sees)."""
    from groundstation.acquisition.importers.csv_imu import import_csv
    from groundstation.acquisition.replay import iter_replay

    src = root / "aggressive_flight" / path / file
    if not src.is_file():
        raise BenchDataError(
            f"real flight {str(src)!r} not found",
            hint="set GS_EXTERNAL_DATA to the folder holding aggressive_flight/, or --paths none",
        )
    out = workdir / f"{path.replace('/', '_')}_{Path(file).stem}.mcap"
    import_csv(src, out, created_by="groundstation bench detector")
    return build_trace(f"{path}/{file}", "real", collect_samples(iter_replay(str(out))))


def simulate_session(scene: str, pilot: str, seed: int, duration_s: float | None) -> Trace:
    """Run a SITL session and decode its wire bytes with the live stream decoders.

    ``duration_s`` None runs until the scripted pilot is done (at most ``MAX_SIM_S``).
    """
    from firmware_bridge.frames import AxisConvention
    from firmware_bridge.sitl.runner import Simulation
    from firmware_bridge.sitl.scene import load_scene
    from groundstation.acquisition.decoders import MavlinkStreamDecoder, NatNetStreamDecoder
    from groundstation.acquisition.settings import AcquisitionSettings

    sim = Simulation(
        load_scene(scene), f"script:{pilot}", seed=seed, duration=duration_s or MAX_SIM_S
    )
    a = AcquisitionSettings()
    latency = int(a.mocap_latency_ms * 1e6)
    mav = MavlinkStreamDecoder(a.timesync_window, int(a.timesync_max_rtt_ms * 1e6), latency)
    nat = NatNetStreamDecoder((4, 1), AxisConvention(sim.mocap.up, a.quaternion_order), latency)

    def decoded():
        for item in sim.outputs():
            yield from (mav if item.channel == "mavlink" else nat).feed(item.data, item.t_ns)
            if duration_s is None and sim.vehicle.pilot.done:
                break

    samples = collect_samples(decoded())
    truth = [
        TruthEvent(
            e["kind"],
            float(e["start"]),
            float(e["end"]),
            None if e["point"] is None else np.asarray(e["point"], float),
        )
        for e in sim.truth()["contacts"]
    ]
    return build_trace(f"{scene}/{pilot}/seed{seed}", "sitl", samples, truth, scene)


def _surface_distance():
    from firmware_bridge.sitl.scene import load_scene

    cache: dict[str, Any] = {}

    def distance(scene: str, points: np.ndarray) -> np.ndarray:
        if scene not in cache:
            cache[scene] = load_scene(scene)
        return cache[scene].signed_distance(points)

    return distance


# --- outputs ------------------------------------------------------------------------------------


def _fmt(v: Any, spec: str = ".2f") -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, spec)


def table_markdown(rows: Sequence[dict]) -> str:
    """Markdown table of every point; the default row is marked (bold threshold, "default")."""
    head = (
        "| filter | a0 (G) | real FP/min | IMU_1 FP/min | IMU_avg FP/min | of which warm-up "
        "| real % above "
        "| touch recall | slow_touch recall | gusts detected | gust FP/min | other FP/min "
        "| precision | loc. point med (m) | loc. surface med (m) | margin |"
    )
    lines = [head, "|" + "---|" * 16]
    for r in rows:
        real, s = r["real"], r["sitl"]
        thr = f"**{r['threshold_g']:g}** (default)" if r["default"] else f"{r['threshold_g']:g}"
        lines.append(
            f"| {r['filter']} | {thr} | {_fmt(real.get('all', {}).get('per_min'))} "
            f"| {_fmt(real.get('IMU_1.csv', {}).get('per_min'))} "
            f"| {_fmt(real.get('IMU_avg.csv', {}).get('per_min'))} "
            f"| {real.get('all', {}).get('warmup_events', '-')} "
            f"| {_fmt(100 * real['all']['above'] if 'all' in real else None, '.3f')} "
            f"| {_fmt(s['recall_touch'], '.3f')} | {_fmt(s['recall_slow_touch'], '.2f')} "
            f"| {_fmt(s['gust_detected'])} | {_fmt(s['gust_per_min'])} "
            f"| {_fmt(s['other_fp_per_min'])} | {_fmt(s['precision'], '.3f')} "
            f"| {_fmt(s['loc_point_median_m'], '.3f')} | {_fmt(s['loc_surface_median_m'], '.3f')} "
            f"| {_fmt(r.get('margin'))} |"
        )
    return "\n".join(lines)


def peaks_markdown(peaks: dict[str, dict]) -> str:
    """Per filter: largest filtered |a| on the real flights vs the peaks of true touches/gusts."""
    head = (
        "| filter | real max after warm-up (G) | real max in warm-up (G) | touch peak min (G) "
        "| touch peak p5 (G) | touch peak median (G) | gust peak median (G) |"
    )
    lines = [head, "|---|---|---|---|---|---|---|"]
    for label, p in peaks.items():
        lines.append(
            f"| {label} | {_fmt(p['real_max_g'])} | {_fmt(p['real_warmup_max_g'])} "
            f"| {_fmt(p['touch_min_g'])} "
            f"| {_fmt(p['touch_p05_g'])} | {_fmt(p['touch_median_g'])} "
            f"| {_fmt(p['gust_median_g'])} |"
        )
    return "\n".join(lines)


def plot(rows: Sequence[dict], path: Path, min_recall: float) -> None:
    """Threshold on x; real false contacts/min (left, symlog) and touch recall (right, dashed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7.5, 4.2), dpi=100)
    ax2 = ax.twinx()
    labels = list(dict.fromkeys(r["filter"] for r in rows))
    colors = plt.get_cmap("tab10")
    for k, label in enumerate(labels):
        rs = [r for r in rows if r["filter"] == label]
        x = [r["threshold_g"] for r in rs]
        fp = [r["real"].get("all", {}).get("per_min", math.nan) for r in rs]
        rec = [r["sitl"]["recall_touch"] for r in rs]
        ax.plot(x, fp, "-o", ms=3, color=colors(k), label=label)
        ax2.plot(x, rec, "--", color=colors(k))
        for r, xi, yi, ri in zip(rs, x, fp, rec, strict=True):
            if r["default"]:
                ax.plot([xi], [yi], "*", ms=12, color=colors(k))
                ax2.plot([xi], [ri], "*", ms=12, color=colors(k))
    ax.set_yscale("symlog", linthresh=0.5)
    ax.set_xlabel("threshold a0 (G)")
    ax.set_ylabel("false contacts / min, real flights (solid)")
    ax2.set_ylabel("recall of simulated touches (dashed)")
    ax2.set_ylim(0, 1.05)
    ax2.axhline(min_recall, color="grey", lw=0.6, ls=":")
    ax.legend(fontsize=7, loc="center left")
    ax.set_title("contact detector: * = default; real data CC BY 4.0 Hurwitz & Klein", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    return x


# --- command ------------------------------------------------------------------------------------


def _floats(text: str) -> list[float]:
    try:
        vals = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise BenchDataError(
            f"--thresholds {text!r}: expected numbers separated by commas"
        ) from None
    if not vals or not all(math.isfinite(v) and v > 0 for v in vals):
        raise BenchDataError(f"--thresholds {text!r}: thresholds must be numbers > 0 (G)")
    return vals
