"""The impulse detector: external-force impulses in the accelerometer, scored by their physics.

Pure and streaming: feed IMU samples in time order (:meth:`ImpulseDetector.update`), get
observations back. Time comes with the data; nothing reads a clock.

Signal (per IMU sample, body frame FRD)
---------------------------------------
``m``: the specific force averaged over ``impulse_window_s`` (30 ms: a touch's impulse lasts
20-40 ms, so this is close to the matched filter). A multirotor's own forces act along its thrust
axis ``u`` (plus small drag): across it the accelerometer sees external forces almost alone, and
along it thrust changes as the vehicle climbs, brakes and turns. So ``m`` is compared with what
preceded it, leaving ``baseline_gap_s`` out:

- across ``u`` (lateral): with the mean of ``m`` over the ``baseline_s`` before;
- along ``u`` (axial): with the straight line through the means of the two halves of that
  window, extrapolated to now (thrust ramps cancel; on the real aggressive flights this cut the
  axial residual's peak from 1.3 G to 0.9 G).

Trigger score ``s = hypot(|r_lat| / lateral_threshold_g, r_ax / axial_threshold_g)`` (in G). The
baselines look only backwards, so a strong impulse cannot echo into the samples before it.

Events
------
A candidate opens when ``s > 1`` (armed: warmed up, refractory over; within the refractory an
impulse stronger than the one that just ended opens one too: its ringing cannot outgrow it, but a
gust can push the vehicle into a wall right after, and that impact's onset is the contact). The
baseline of the opening sample is frozen (with ``hold_baseline``, one that opens while its window
still holds the previous impulse takes that impulse's baseline: the quiet level before the gust,
not the gust), and the candidate lasts while ``m`` stays
``release_ratio`` above it; a push longer than ``max_event_s`` is cut there. At the close, the
impulse is integrated in the world frame (its direction ``n``; friction tilts it on oblique
touches), its onset found by walking back from the peak to 15 % of it (the surface normal
contacts are placed with is ``n``, or with ``normal_from = "peak"`` the filtered residual's
direction at that peak, free of the manoeuvre around the impact), and
once ``evidence_window_s`` more of data has arrived the evidence of
:mod:`groundstation.contact.evidence` is measured (duration, impulse, mocap approach and rebound
speeds, their agreement with the IMU, how fast the vehicle was turning before the onset) and
:class:`~groundstation.contact.evidence.EvidenceModel` turns it into ``p_false``. Gusts come in
bursts: a candidate that follows, within ``burst_window_s``, one the model put at
``reject_p_false`` or more on its own impulse *and pushed the same way* (impulse directions
less than 90 degrees apart; a gust that throws the drone into a structure is followed by an
impact pushing back) has its odds multiplied by ``burst_odds``
(``p_false_impulse`` keeps the model's value on the impulse alone).

Observations
------------
An event with ``p_false < reject_p_false`` that did not begin with the body at the floor (its
lowest point within ``floor_margin_m`` of ``floor_z_m``, when the floor is known) yields a
contact observation (y = 0) at the **onset**
(where the body met the structure, before it compressed the guard and rebounded): the body point
facing ``-n`` (``contact/vehicle.py``) at the pose of that instant, an internal one ``d_in``
behind it (y = -1), and more pairs at ``contact_rate_hz`` while a long push lasts and the
vehicle stays within sliding reach of where it touched (``sustain_speed_mps``); each carries
``p_false``, the impulse ``dv_mps``, ``rebound`` and a placement uncertainty ``sigma_m``. The
pairs stop once the vehicle has moved out along ``n`` by ``sustain_normal_m``: it has left. Free
space (y = +1) is the vehicle position every ``1 / external_rate_hz`` of data time and every
``external_spacing_m`` of path, not during an impulse nor within ``quiet_s`` after one.

Determinism: every filtered value is a difference of prefix sums accumulated sample by sample,
so the result does not depend on how the samples were batched (live or replay, any speed); and
an impulse is decided at the first sample past its evidence window, in the same loop that
samples free space, so free space and contacts come out in one data-time order too.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from firmware_bridge.frames import quat_to_matrix
from groundstation.contact.detector import (
    LABEL_INSIDE,
    LABEL_OUTSIDE,
    LABEL_SURFACE,
    ContactEvent,
    DetectorStats,
    Observation,
)
from groundstation.contact.evidence import EvidenceModel, ImpulseFeatures
from groundstation.contact.settings import ContactSettings, G
from groundstation.contact.vehicle import VehicleSettings, contact_offset

_C_ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_C_FRD_FLU = np.diag([1.0, -1.0, -1.0])
_UP = np.array([0.0, 0.0, 1.0])  # the floor's outward normal, world ENU
_NAN3 = (math.nan, math.nan, math.nan)
_SEGMENT_GAP_NS = 250_000_000  # a longer gap in the samples restarts the warm-up
_ONSET_FRACTION = 0.15  # onset: walking back from the peak to this share of it
_PRE_GAP_S = 0.02  # the velocity windows stop this short of the impulse on either side
_KEEP_S = 3.0  # history kept beyond what the pending decisions need


class _Columns:
    """Growable per-sample arrays with absolute indices; old rows are dropped in bulk."""

    def __init__(self) -> None:
        self.base = 0  # absolute index of row 0
        self.n = 0
        cap = 1024
        self.t = np.zeros(cap, np.int64)
        self.f = np.zeros((cap, 3))
        self.q = np.zeros((cap, 4))
        self.p = np.zeros((cap, 3))
        self.sf = np.zeros((cap, 3))  # prefix sums of f, inclusive
        self.m = np.zeros((cap, 3))
        self.sm = np.zeros((cap, 3))  # prefix sums of m, inclusive
        self.seg = np.zeros(cap, np.int64)  # time its segment (no gap) started
        self.sf_prev = np.zeros(3)  # prefix sums of the rows dropped so far
        self.sm_prev = np.zeros(3)

    def _grow(self) -> None:
        for name in ("t", "f", "q", "p", "sf", "m", "sm", "seg"):
            a = getattr(self, name)
            b = np.zeros((2 * a.shape[0],) + a.shape[1:], a.dtype)
            b[: self.n] = a[: self.n]
            setattr(self, name, b)

    def append(self, t: int, f, q, p, seg: int) -> None:
        if self.n == self.t.shape[0]:
            self._grow()
        k = self.n
        self.t[k], self.f[k], self.q[k], self.p[k], self.seg[k] = t, f, q, p, seg
        self.n += 1

    def drop_before(self, index: int) -> None:
        """Forget rows with absolute index < ``index``."""
        k = index - self.base
        if k <= 0:
            return
        k = min(k, self.n)
        self.sf_prev, self.sm_prev = self.sf[k - 1].copy(), self.sm[k - 1].copy()
        for name in ("t", "f", "q", "p", "sf", "m", "sm", "seg"):
            a = getattr(self, name)
            a[: self.n - k] = a[k : self.n]
        self.n -= k
        self.base += k

    @property
    def end(self) -> int:
        """Absolute index one past the newest row."""
        return self.base + self.n


@dataclasses.dataclass
class _Open:
    """An impulse being followed: its opening row and frozen baseline (body FRD)."""

    i_open: int
    baseline: np.ndarray
    peak_score: float = 0.0


@dataclasses.dataclass
class _Closed:
    """An impulse that ended, waiting for the data its rebound is measured on."""

    baseline: np.ndarray
    peak_score: float
    rows: tuple[int, int]  # absolute indices: first row examined, closing row
    normal: np.ndarray  # the integrated impulse's direction: what the evidence is measured along
    surface_normal: np.ndarray  # the outward normal contacts are placed with (contact.normal_from)
    on: int  # absolute index of the onset row
    t_imp_end: int  # ns
    peak: float  # m/s^2 along the normal
    dv_imu: float  # m/s
    axial_fraction: float
    need_ns: int  # data time needed for the evidence


def tilt_cos(q: np.ndarray) -> float:
    """Cosine of the angle between the body's thrust axis and the vertical, for an attitude
    quaternion (w, x, y, z) body FRD -> NED (any norm): 1 level, 0 on its side, -1 upside
    down; NaN for a zero or non-finite quaternion."""
    w, x, y, z = (float(v) for v in q)
    n2 = w * w + x * x + y * y + z * z
    if not (n2 > 0.0 and math.isfinite(n2)):
        return math.nan
    return (w * w + z * z - x * x - y * y) / n2


def burst_raised(p: float, odds: float) -> float:
    """``p`` with its odds multiplied by ``odds`` (``contact.burst_odds``): a candidate in a
    burst after a clearly false one."""
    if not p < 1.0:
        return p
    o = p / (1.0 - p) * odds
    return o / (1.0 + o)


class ImpulseDetector:
    """Streaming impulse detector (see the module docstring).

    Parameters
    ----------
    settings : ContactSettings
    vehicle : VehicleSettings
        The body whose support point is the contact point.
    model : EvidenceModel, optional
        Default: ``settings.evidence_model`` or the bundled model.
    first_id : int
        Id of the first observation.
    batch : int
        Decide samples in batches of at least this many (latency against per-call overhead;
        the result does not depend on it).
    keep_residuals : bool
        Keep the lateral and axial residual of every sample (``residuals``).
    """

    def __init__(
        self,
        settings: ContactSettings | None = None,
        vehicle: VehicleSettings | None = None,
        model: EvidenceModel | None = None,
        first_id: int = 0,
        batch: int = 1,
        keep_residuals: bool = False,
    ) -> None:
        self.settings = s = settings or ContactSettings()
        self.vehicle = vehicle or VehicleSettings()
        self.model = model or EvidenceModel.load(s.evidence_model or None)
        u = np.asarray(s.thrust_axis, dtype=np.float64)
        self._u = u / np.linalg.norm(u)
        self._w = int(round(s.impulse_window_s * 1e9))
        self._gap = int(round(s.baseline_gap_s * 1e9))
        self._B = int(round(s.baseline_s * 1e9))
        self._batch = max(1, int(batch))
        #: (t_ns, lateral, axial) arrays of every decided block when ``keep_residuals`` (m/s^2;
        #: warm-up samples left out): what ``groundstation calibrate detector`` measures.
        self.residuals: list[tuple[np.ndarray, np.ndarray, np.ndarray]] | None = (
            [] if keep_residuals else None
        )
        self._thr = np.array([s.lateral_threshold_g, s.axial_threshold_g]) * G
        self._c = _Columns()
        self._m_done = 0  # absolute index: m and sm computed below this
        self._decided = 0  # absolute index: samples decided below this
        self._open: _Open | None = None
        self._closed: list[_Closed] = []
        self._refractory_until = -(2**62)
        self._refractory_peak = math.inf  # peak score of the impulse that set the refractory
        self._last_event_end = -(2**62)
        self._last_baseline: np.ndarray | None = None  # the last closed impulse's baseline
        #: (onset ns, world impulse direction) of recent candidates the model alone rejects
        self._false_pushes: list[tuple[int, np.ndarray]] = []
        self._last_external_t = -(2**62)
        self._last_external_pos: list[float] | None = None
        self._quiet_ns = int(s.quiet_s * 1e9)
        self._external_ns = int(1e9 / s.external_rate_hz)
        tilt = s.external_max_tilt_deg  # 180: every attitude is level enough
        self._level_cos = None if tilt >= 180.0 else math.cos(math.radians(tilt))
        self._seg_start: int | None = None
        self._next_id = int(first_id)
        self._next_event_id = 0
        self._last_t: int | None = None
        self.events: list[ContactEvent] = []  # closed candidates, in order
        self.stats = DetectorStats()
        self.last_score = 0.0

    # -- input ---------------------------------------------------------------------------------
    def update(self, t_ns: int, specific_force_frd, q_frd_ned, position=None) -> list[Observation]:
        """Take one IMU sample; return the observations it made decidable.

        Parameters
        ----------
        t_ns : int
            Data time (station axis), ns; must increase.
        specific_force_frd : (3,) array
            Accelerometer reading, body FRD, m/s^2 (a level vehicle at rest reads (0, 0, -g)).
        q_frd_ned : (4,) array
            Attitude (w, x, y, z), body FRD -> local NED.
        position : (3,) array or None
            Vehicle position (world ENU, m) at ``t_ns``, or None without a pose.
        """
        self.stats.samples += 1
        try:
            fx, fy, fz = map(float, specific_force_frd)
            qw, qx, qy, qz = map(float, q_frd_ned)
        except (TypeError, ValueError):
            self.stats.rejected += 1
            return []
        if not all(map(math.isfinite, (fx, fy, fz, qw, qx, qy, qz))) or (
            self._last_t is not None and t_ns <= self._last_t
        ):
            self.stats.rejected += 1
            return []
        p = _NAN3
        if position is not None:
            try:
                px, py, pz = map(float, position)
                if math.isfinite(px) and math.isfinite(py) and math.isfinite(pz):
                    p = (px, py, pz)
            except (TypeError, ValueError):
                pass
        t_ns = int(t_ns)
        if self._last_t is None or t_ns - self._last_t > _SEGMENT_GAP_NS:
            self._seg_start = t_ns
        self._last_t = t_ns
        self._c.append(t_ns, (fx, fy, fz), (qw, qx, qy, qz), p, self._seg_start)
        if self._c.end - self._decided < self._batch and not self._closed:
            return []
        return self._process(final=False)

    def flush(self) -> list[Observation]:
        """End of data: decide everything held (evidence windows cut at the end)."""
        return self._process(final=True)

    @property
    def in_contact(self) -> bool:
        return self._open is not None

    @property
    def pending(self) -> int:
        """Samples received but not decided yet."""
        return self._c.end - self._decided

    # -- filtering -----------------------------------------------------------------------------
    def _filter_new(self) -> None:
        """m (moving average of f) and the prefix sums for rows not done yet."""
        c = self._c
        lo, hi = self._m_done - c.base, c.n
        if hi <= lo:
            return
        prev = c.sf[lo - 1] if lo > 0 else c.sf_prev
        c.sf[lo:hi] = np.cumsum(np.vstack([prev, c.f[lo:hi]]), axis=0)[1:]
        t = c.t[:hi]
        j = np.searchsorted(t, t[lo:hi] - self._w, side="right")  # first row in (t - w, t]
        s_start = np.where((j > 0)[:, None], c.sf[np.maximum(j - 1, 0)], c.sf_prev)
        count = (np.arange(lo, hi) - j + 1).astype(np.float64)
        c.m[lo:hi] = (c.sf[lo:hi] - s_start) / count[:, None]
        prevm = c.sm[lo - 1] if lo > 0 else c.sm_prev
        c.sm[lo:hi] = np.cumsum(np.vstack([prevm, c.m[lo:hi]]), axis=0)[1:]
        self._m_done = c.base + hi

    def _box(self, lo_t: np.ndarray, hi_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean of m over [lo_t, hi_t] per row (rows present in the buffer), and the counts."""
        c = self._c
        t = c.t[: c.n]
        a = np.searchsorted(t, lo_t, side="left")
        b = np.searchsorted(t, hi_t, side="right")
        n = b - a
        sa = np.where((a > 0)[:, None], c.sm[np.maximum(a - 1, 0)], c.sm_prev)
        sb = np.where((b > 0)[:, None], c.sm[np.maximum(b - 1, 0)], c.sm_prev)
        with np.errstate(invalid="ignore", divide="ignore"):
            return (sb - sa) / n[:, None], n

    def _split(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """|lateral| and axial parts (m/s^2) of body-frame vectors r (k, 3)."""
        ax = r @ self._u
        lat = np.linalg.norm(r - ax[:, None] * self._u, axis=1)
        return lat, ax

    def _score(self, r: np.ndarray) -> np.ndarray:
        lat, ax = self._split(r)
        return np.hypot(lat / self._thr[0], ax / self._thr[1])

    # -- deciding ------------------------------------------------------------------------------
    def _baselines(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Baseline vectors (k, 3) of rows at times ``t`` and the row counts of their window:
        lateral part the window mean, axial part the two-half-means line extrapolated to t."""
        g, B = self._gap, self._B
        mean, n = self._box(t - g - B, t - g)
        old, n_old = self._box(t - g - B, t - g - B // 2)
        new, n_new = self._box(t - g - B // 2, t - g)
        k = (g + B / 4) / (B / 2)
        line = new + k * (new - old)
        both = (n_old > 0) & (n_new > 0)
        ax = np.where(both, line @ self._u, mean @ self._u)
        base = mean - np.outer(mean @ self._u, self._u) + np.outer(ax, self._u)
        return base, n

    def _process(self, final: bool) -> list[Observation]:
        """Decide the samples held once a batch is full, or at once when a closed impulse's
        evidence window has arrived (its event is not kept waiting for a batch), then the
        events whose windows are complete. Samples and events come out in one data-time
        order, whatever the batch: an event's observations after the free space sampled
        before its evidence window ended, before the free space sampled after (``_decide``)."""
        c = self._c
        if c.n == 0:
            return []
        lo = self._decided - c.base
        out: list[Observation] = []
        due = bool(self._closed) and int(c.t[c.n - 1]) >= self._closed[0].need_ns
        if c.n - lo >= (1 if final or due else self._batch):
            out = self._decide(lo, c.n, final)
            self._trim()
        if self._closed and final:
            out += self._finalize(final)
        return out

    def _decide(self, lo: int, hi: int, final: bool) -> list[Observation]:
        c, s = self._c, self.settings
        self._filter_new()
        idx = np.arange(lo, hi)
        t = c.t[idx]
        base, nb = self._baselines(t)
        score = self._score(c.m[idx] - base)
        warm = (t - c.seg[idx] >= self._gap + self._B + self._w) & (nb > 0)
        if self.residuals is not None:
            lat, ax = self._split(c.m[idx] - base)
            self.residuals.append((t[warm].copy(), lat[warm], ax[warm]))
        max_ns = int(s.max_event_s * 1e9)
        pos = c.p[idx].tolist()
        out: list[Observation] = []
        for k in range(idx.size):
            i = int(idx[k])  # buffer row
            ti = int(t[k])
            if self._closed and ti >= self._closed[0].need_ns:
                out += self._finalize_until(ti)
            ev = self._open
            if ev is None:
                rearmed = ti >= self._refractory_until or score[k] > self._refractory_peak
                if warm[k] and rearmed and score[k] > 1.0:
                    held = self._opening_baseline(base[k], ti)
                    self._open = _Open(i + c.base, held, float(score[k]))
                    self.stats.contacts += 1
                elif ti - self._last_event_end >= self._quiet_ns:
                    out += self._external(pos[k], ti, i)
                continue
            d = float(self._score((c.m[i] - ev.baseline)[None, :])[0])
            ev.peak_score = max(ev.peak_score, d)
            too_long = ti - int(c.t[ev.i_open - c.base]) >= max_ns
            if d < s.release_ratio or too_long or (final and k == idx.size - 1):
                self._close(ev, i + c.base)
                self._open = None
        self._decided = hi + c.base
        self.last_score = float(score[-1])
        return out

    def _opening_baseline(self, window: np.ndarray, t_ns: int) -> np.ndarray:
        """The baseline an impulse opening at ``t_ns`` is measured from: its window's
        (``window``), unless that window reaches back into the previous impulse
        (``contact.hold_baseline``), whose own baseline then stands for the quiet level."""
        held = self._last_baseline
        if (
            self.settings.hold_baseline
            and held is not None
            and t_ns - self._last_event_end < self._gap + self._B
        ):
            return held.copy()
        return window.copy()

    def _finalize_until(self, t_ns: int) -> list[Observation]:
        """Decide the closed impulses whose evidence window ended by ``t_ns`` (data time)."""
        out: list[Observation] = []
        while self._closed and self._closed[0].need_ns <= t_ns:
            out += self._evidence(self._closed.pop(0))
        return out

    def _finalize(self, final: bool) -> list[Observation]:
        """Decide the closed impulses whose evidence window has arrived."""
        out: list[Observation] = []
        newest = int(self._c.t[self._c.n - 1])
        while self._closed and (final or newest >= self._closed[0].need_ns):
            out += self._evidence(self._closed.pop(0))
        return out

    def _trim(self) -> None:
        """Drop rows no pending decision can reach (in bulk, to keep appends cheap)."""
        c = self._c
        oldest = self._decided if self._open is None else min(self._open.i_open, self._decided)
        if self._closed:
            oldest = min(oldest, self._closed[0].rows[0])
        row = min(max(oldest - c.base, 0), c.n - 1)
        cut_t = int(c.t[row]) - self._gap - self._B - self._w - int(_KEEP_S * 1e9)
        k = int(np.searchsorted(c.t[: c.n], cut_t, side="left"))
        if k > 4096:
            c.drop_before(c.base + k)

    # -- free space ----------------------------------------------------------------------------
    def _external(self, pos: list[float], ti: int, row: int) -> list[Observation]:
        """A free-space observation at ``pos`` (buffer row ``row``) if one is due (time or
        distance) and the body is level enough to be the map's level disc there
        (``external_max_tilt_deg``; an unknown attitude counts as level). A sample skipped
        for its tilt counts as taken for the schedule: one is due again a period (or a
        spacing) later, so a body lying on its side is counted once per period."""
        s = self.settings
        due = ti - self._last_external_t >= self._external_ns
        if not math.isfinite(pos[0]):
            self.stats.no_pose += due
            return []
        last = self._last_external_pos
        moved = (
            s.external_spacing_m > 0
            and last is not None
            and math.dist(pos, last) >= s.external_spacing_m
        )
        if not (due or moved):
            return []
        self._last_external_t = ti
        self._last_external_pos = pos
        if self._level_cos is not None and tilt_cos(self._c.q[row]) < self._level_cos:
            self.stats.tilted += 1
            return []
        return [self._observe(ti, np.array(pos), LABEL_OUTSIDE, np.zeros(3), -1, 0.0)]

    def _observe(self, t_ns, x, label, normal, event_id, accel_g, **extra) -> Observation:
        obs = Observation(self._next_id, int(t_ns), x, label, normal, event_id, accel_g, **extra)
        self._next_id += 1
        self.stats.observations += 1
        return obs

    # -- closing an impulse --------------------------------------------------------------------
    def _r_world(self, rows: np.ndarray) -> np.ndarray:
        """(k, 3, 3) rotations body FRD -> world ENU of buffer rows."""
        return _C_ENU_NED @ quat_to_matrix(self._c.q[rows])

    def _position_at(self, t_ns: float) -> np.ndarray:
        c = self._c
        t = c.t[: c.n]
        k = int(np.searchsorted(t, t_ns))
        if k <= 0 or k >= c.n:
            return np.full(3, np.nan)
        t0, t1 = t[k - 1], t[k]
        w = (t_ns - t0) / max(t1 - t0, 1)
        return (1 - w) * c.p[k - 1] + w * c.p[k]

    def _velocity(self, t_from: float, t_to: float) -> np.ndarray:
        a, b = self._position_at(t_from), self._position_at(t_to)
        return (b - a) / ((t_to - t_from) / 1e9)

    def _turn_rate(self, t_from: int, t_to: int) -> float:
        """Mean angular speed (rad/s) over [t_from, t_to]: the rotation angles between
        consecutive attitudes summed over the time they span (NaN: fewer than two rows)."""
        c = self._c
        t = c.t[: c.n]
        a = int(np.searchsorted(t, t_from, side="left"))
        b = int(np.searchsorted(t, t_to, side="right"))
        if b - a < 2:
            return math.nan
        with np.errstate(invalid="ignore", divide="ignore"):  # a zero quaternion: NaN
            q = c.q[a:b] / np.linalg.norm(c.q[a:b], axis=1, keepdims=True)
            dots = np.abs(np.einsum("ij,ij->i", q[1:], q[:-1]))
        angle = 2.0 * np.arccos(np.clip(dots, 0.0, 1.0))
        span = (int(t[b - 1]) - int(t[a])) / 1e9
        return float(angle.sum() / span) if span > 0 else math.nan

    def _close(self, ev: _Open, i_close: int) -> None:
        """Geometry of an impulse that ended: direction, peak, onset, end, impulse."""
        c = self._c
        open_row, close_row = ev.i_open - c.base, i_close - c.base
        w_back = open_row - int(np.searchsorted(c.t[: c.n], c.t[open_row] - self._w))
        first = max(1, open_row - w_back - 2)  # the filter starts rising at the onset
        rows = np.arange(first, close_row + 1)
        dts = (c.t[rows] - c.t[rows - 1]) / 1e9
        R = self._r_world(rows)
        raw = np.einsum("kij,kj->ki", R, c.f[rows] - ev.baseline) * dts[:, None]
        smooth = np.einsum("kij,kj->ki", R, c.m[rows] - ev.baseline)
        J = (smooth * dts[:, None])[rows >= open_row].sum(axis=0)
        if not np.isfinite(J).all() or float(np.linalg.norm(J)) < 1e-9:
            J = smooth[-1]
        n = J / max(float(np.linalg.norm(J)), 1e-12)
        proj = smooth @ n
        kp = int(np.argmax(proj))
        peak = float(proj[kp])
        k_on = kp
        while k_on > 0 and proj[k_on - 1] > _ONSET_FRACTION * peak:
            k_on -= 1
        k_end = kp
        while k_end < proj.size - 1 and proj[k_end + 1] > _ONSET_FRACTION * peak:
            k_end += 1
        t_on = int(c.t[rows[k_on]])
        t_end = int(c.t[rows[k_end]])  # the filtered impulse fell back here
        dv_imu = max(float((raw[k_on : k_end + 1] @ n).sum()), peak * float(dts[kp]))
        surface_n = n
        if self.settings.normal_from == "peak":
            at_peak = float(np.linalg.norm(smooth[kp]))
            if np.isfinite(at_peak) and at_peak > 1e-9:
                surface_n = smooth[kp] / at_peak
        lat, ax = self._split((c.m[rows[kp]] - ev.baseline)[None, :])
        t_imp_end = max(t_end - self._w, t_on + 1)
        need = t_imp_end + int((_PRE_GAP_S + self.settings.evidence_window_s) * 1e9)
        self._closed.append(
            _Closed(
                baseline=ev.baseline,
                peak_score=ev.peak_score,
                rows=(int(first) + c.base, i_close),
                normal=n,
                surface_normal=surface_n,
                on=int(rows[k_on]) + c.base,
                t_imp_end=t_imp_end,
                peak=peak,
                dv_imu=dv_imu,
                axial_fraction=float(abs(ax[0]) / max(math.hypot(lat[0], ax[0]), 1e-12)),
                need_ns=need,
            )
        )
        t_close = int(c.t[close_row])
        self._refractory_until = t_close + int(self.settings.refractory_s * 1e9)
        self._refractory_peak = ev.peak_score
        self._last_event_end = t_close
        self._last_baseline = ev.baseline

    def _evidence(self, cl: _Closed) -> list[Observation]:
        """Evidence, p_false, the event and its observations."""
        s, c = self.settings, self._c
        n = cl.normal
        on_row = cl.on - c.base
        t_on = int(c.t[on_row])
        win = int(s.evidence_window_s * 1e9)
        gap = int(_PRE_GAP_S * 1e9)
        v_before = self._velocity(t_on - gap - win, t_on - gap)
        v_after = self._velocity(cl.t_imp_end + gap, cl.t_imp_end + gap + win)
        approach = float(-(v_before @ n))
        rebound = float(v_after @ n)
        turn_rate = self._turn_rate(t_on - gap - win, t_on - gap)
        feats = ImpulseFeatures(
            peak_g=cl.peak / G,
            score=cl.peak_score,
            duration_s=cl.dv_imu / max(cl.peak, 1e-9),
            dv_imu_mps=cl.dv_imu,
            axial_fraction=cl.axial_fraction,
            approach_mps=approach,
            rebound_mps=rebound,
            agreement=(approach + rebound) / cl.dv_imu if cl.dv_imu > 1e-6 else math.nan,
            turn_rate_radps=turn_rate,
        )
        p_impulse = self.model.p_false(feats)
        p_false = p_impulse
        window = int(s.burst_window_s * 1e9)
        self._false_pushes = [(t, d) for t, d in self._false_pushes if t_on - t <= window]
        if s.burst_odds > 1 and any(float(d @ n) > 0.0 for _, d in self._false_pushes):
            p_false = burst_raised(p_impulse, s.burst_odds)
        if p_impulse >= s.reject_p_false:
            self._false_pushes.append((t_on, n))
        clearance = self._floor_clearance(on_row)
        at_floor = -self.vehicle.reach_m <= clearance <= s.floor_margin_m  # NaN: False
        cos_tilt = tilt_cos(c.q[on_row])
        known = math.isfinite(cos_tilt)  # no attitude: no tilt, not upset
        tilt = math.degrees(math.acos(min(1.0, max(-1.0, cos_tilt)))) if known else math.nan
        upset = tilt > s.reject_tilt_deg
        rejected = at_floor or upset or not p_false < s.reject_p_false
        close_row = cl.rows[1] - c.base
        event = ContactEvent(
            self._next_event_id,
            t_on,
            int(c.t[close_row]),
            peak_g=cl.peak / G,
            normal=cl.surface_normal,
            position=c.p[on_row].copy() if np.isfinite(c.p[on_row]).all() else None,
            p_false=p_false,
            features=feats,
            rejected=rejected,
            p_false_impulse=p_impulse,
            floor_clearance_m=clearance,
            at_floor=at_floor,
            tilt_deg=tilt,
            upset=upset,
        )
        self._next_event_id += 1
        self.events.append(event)
        if rejected:
            return []
        return self._contact_observations(event, on_row, close_row, feats)

    def _floor_clearance(self, row: int) -> float:
        """Height of the body's lowest point above ``contact.floor_z_m`` at a buffer row,
        metres: NaN without a floor, a position or a finite attitude."""
        floor, p = self.settings.floor_z_m, self._c.p[row]
        if floor is None or not np.isfinite(p).all():
            return math.nan
        R = self._r_world(np.array([row]))[0] @ _C_FRD_FLU  # body FLU -> world ENU
        if not np.isfinite(R).all():
            return math.nan
        low = contact_offset(self.vehicle, _UP, R)  # the support point facing the floor
        return float(p[2] + low[2] - floor)

    def _left(self, moved: np.ndarray, n: np.ndarray, dt_ns: int) -> bool:
        """Whether a vehicle that has moved by ``moved`` (m) since the onset of a push along
        ``n``, ``dt_ns`` ago, has left the structure: faster than it could slide along it
        (``sustain_speed_mps``), or out along the normal (``sustain_normal_m``)."""
        s = self.settings
        reach = s.sustain_slack_m + s.sustain_speed_mps * dt_ns / 1e9
        if float(np.linalg.norm(moved)) > reach:
            return True
        return s.sustain_normal_m > 0 and float(moved @ n) > s.sustain_normal_m

    def _contact_observations(
        self, ev: ContactEvent, on_row: int, close_row: int, f: ImpulseFeatures
    ) -> list[Observation]:
        s, c, v = self.settings, self._c, self.vehicle
        n = ev.normal
        period = int(1e9 / s.contact_rate_hz)
        rows, t_next = [], int(c.t[on_row])
        for r in range(on_row, close_row + 1):
            if int(c.t[r]) >= t_next:
                rows.append(r)
                t_next = int(c.t[r]) + period
        noise_angle = min(1.0, (min(self._thr) / G / 3.0) / max(f.peak_g, 1e-6))
        approach = f.approach_mps if math.isfinite(f.approach_mps) else 0.0
        sigma = math.sqrt(
            s.position_sigma_m**2
            + (max(approach, 0.0) * 0.005) ** 2
            + (v.reach_m * (1.0 - math.cos(noise_angle))) ** 2
        )
        out: list[Observation] = []
        p_on, t_on = c.p[on_row], int(c.t[on_row])
        spread = math.radians(s.normal_spread_deg)
        for k, r in enumerate(rows):
            pos = c.p[r]
            if not np.isfinite(pos).all():
                self.stats.no_pose += 1
                continue
            if np.isfinite(p_on).all() and self._left(pos - p_on, n, int(c.t[r]) - t_on):
                self.stats.left_contact += len(rows) - k  # flown off: the rest is not contact
                break
            R = self._r_world(np.array([r]))[0] @ _C_FRD_FLU  # body FLU -> world ENU
            xc = pos + contact_offset(v, n, R, spread)
            xin = xc - s.internal_depth_m * n
            extra = dict(p_false=ev.p_false, dv_mps=f.dv_imu_mps, rebound=f.rebound, sigma_m=sigma)
            t_r = int(c.t[r])
            out.append(self._observe(t_r, xc, LABEL_SURFACE, n, ev.id, f.peak_g, **extra))
            out.append(self._observe(t_r, xin, LABEL_INSIDE, n, ev.id, f.peak_g, **extra))
            ev.observations += 2
        return out
