"""The contact detector's signal from IMU and attitude samples (pure; time comes with the data).

The detectors do not publish the signal they trigger on. :class:`DetectorSignal` recomputes it
from the same ``samples.imu`` and ``samples.attitude`` messages, with the stage's pairing rule for
attitude (an IMU sample waits until an attitude sample at or after its time has arrived, or until
``max_wait_s`` of IMU data time has passed; ``contact.stage``):

- ``impulse`` detector (default): its trigger score, the body-frame impulse residual over the
  lateral and axial thresholds (1 = a candidate opens), from an
  :class:`~groundstation.contact.impulse.ImpulseDetector` fed the same samples (its residuals);
- ``threshold`` detector: the filtered magnitude of the gravity-compensated, earth-frame
  acceleration in G, with the detector's own pieces (``earth_acceleration``, ``make_filter``,
  the attitude slerp of ``sync.aligner.PoseBuffer``).
"""

from __future__ import annotations

import collections
import math

import numpy as np

from groundstation.contact.filters import make_filter
from groundstation.contact.settings import AlignmentSettings, ContactSettings, G
from groundstation.sync.aligner import PoseBuffer

_ZERO3 = np.zeros(3)


def _accel_ned(f_frd: np.ndarray, q_wxyz: np.ndarray) -> np.ndarray:
    """a = R(q) f + g in NED (``contact.detector.earth_acceleration`` before its NED -> ENU
    axis swap, which changes neither the filter's linear response nor |a|), in plain floats:
    the detector's numpy version costs ~20x more per sample and replay outputs do this for
    every IMU sample of a flight."""
    w, x, y, z = (float(c) for c in q_wxyz)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    vx, vy, vz = (float(c) for c in f_frd)
    # v' = v + 2 w (u x v) + 2 u x (u x v), u = (x, y, z)
    cx, cy, cz = y * vz - z * vy, z * vx - x * vz, x * vy - y * vx
    dx, dy, dz = y * cz - z * cy, z * cx - x * cz, x * cy - y * cx
    return np.array([vx + 2 * (w * cx + dx), vy + 2 * (w * cy + dy), vz + 2 * (w * cz + dz) + G])


class DetectorSignal:
    """The detector's trigger signal per IMU sample (see the module docstring): with the
    ``impulse`` detector (default) its score, the residual impulse over the thresholds (1 = the
    trigger, from :class:`~groundstation.contact.impulse.ImpulseDetector` itself fed the same
    samples); with ``threshold`` the filtered |a| in G.

    Parameters
    ----------
    contact : ContactSettings
        Filter, window and threshold of the detector.
    alignment : AlignmentSettings
        ``attitude_max_gap_s`` and ``max_wait_s`` of the pairing.
    """

    def __init__(
        self, contact: ContactSettings | None = None, alignment: AlignmentSettings | None = None
    ) -> None:
        self.contact = contact or ContactSettings()
        self.alignment = al = alignment or AlignmentSettings()
        c = self.contact
        self._filter = make_filter(c.filter, c.window_s, c.cutoff_hz)
        self._impulse = None
        if c.detector == "impulse":
            from groundstation.contact.impulse import ImpulseDetector

            # the score needs only the IMU samples and the thresholds; events are not used
            self._impulse = ImpulseDetector(c, batch=64, keep_residuals=True)
            self._thr = (c.lateral_threshold_g * G, c.axial_threshold_g * G)
        self._att = PoseBuffer(max_gap_ns=int(al.attitude_max_gap_s * 1e9))
        self._wait_ns = int(al.max_wait_s * 1e9)
        self._queue: collections.deque[tuple[int, np.ndarray]] = collections.deque()
        self._att_wm: int | None = None
        self._imu_wm: int | None = None
        self._last_t: int | None = None
        self.skipped = 0  # IMU samples with no attitude, out of order or not finite

    @property
    def is_score(self) -> bool:
        """The signal is the impulse detector's trigger score (unitless, trigger at 1), not a
        filtered |a| in G."""
        return self._impulse is not None

    @property
    def threshold_g(self) -> float:
        """The trigger level of the signal (impulse: 1, the score's scale; threshold: a0, G)."""
        return 1.0 if self._impulse is not None else float(self.contact.threshold_g)

    @property
    def candidates(self) -> int:
        """Impulse detector: candidates opened so far (score above 1), reported or rejected."""
        return 0 if self._impulse is None else int(self._impulse.stats.contacts)

    @property
    def release_g(self) -> float:
        """The release level of the hysteresis, in the signal's unit."""
        return float(self.contact.release_ratio * self.threshold_g)

    def push_imu(self, t_ns: int, accel_mps2: np.ndarray) -> list[tuple[int, float]]:
        """Queue one IMU sample (body FRD specific force, m/s^2 at station time ``t_ns``).

        Returns
        -------
        list of (int, float)
            ``(t_ns, filtered |a| in G)`` of every sample released, in time order.
        """
        a = np.asarray(accel_mps2, dtype=np.float64).reshape(3)
        if self._last_t is not None and t_ns <= self._last_t:
            self.skipped += 1
            return []
        self._last_t = t_ns
        self._queue.append((int(t_ns), a))
        self._imu_wm = int(t_ns)
        return self._release(final=False)

    def push_attitude(self, t_ns: int, q_wxyz: np.ndarray) -> list[tuple[int, float]]:
        """Add one attitude sample (quaternion body FRD -> NED); returns the released signal."""
        if self._att.insert(int(t_ns), _ZERO3, np.asarray(q_wxyz, dtype=np.float64)):
            if self._att_wm is None or t_ns > self._att_wm:
                self._att_wm = int(t_ns)
        return self._release(final=False)

    def flush(self) -> list[tuple[int, float]]:
        """End of data: release every queued sample."""
        out = self._release(final=True)
        if self._impulse is not None:
            self._impulse.flush()
            out += self._scores()
        return out

    def _scores(self) -> list[tuple[int, float]]:
        """Drain the impulse detector's residuals as (t_ns, score)."""
        res = self._impulse.residuals
        out: list[tuple[int, float]] = []
        for t, lat, ax in res:
            score = np.hypot(lat / self._thr[0], ax / self._thr[1])
            out += zip(t.tolist(), score.tolist(), strict=True)
        res.clear()
        return out

    def _release(self, final: bool) -> list[tuple[int, float]]:
        out: list[tuple[int, float]] = []
        while self._queue:
            t, acc = self._queue[0]
            on_time = self._att_wm is not None and self._att_wm >= t
            if not (on_time or final or self._imu_wm - t >= self._wait_ns):
                break
            self._queue.popleft()
            att = self._att.at(t)
            if not att or not all(math.isfinite(v) for v in acc.tolist()):
                self.skipped += 1
                continue
            if self._impulse is not None:
                self._impulse.update(t, acc, att.quaternion)
                continue
            af = self._filter.update(t, _accel_ned(acc, att.quaternion))
            out.append((t, float(np.linalg.norm(af)) / G))
        if self._impulse is not None:
            out = self._scores()
        if out:
            self._att.drop_before(out[-1][0] - 1_000_000_000)
        return out
