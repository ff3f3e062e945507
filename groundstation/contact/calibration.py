"""Calibrate the impulse detector from a contact-free stretch of a flight (pure).

Every airframe vibrates differently, and every IMU sits at its own angle to the thrust axis.
Given the accelerometer samples of a segment in which nothing touched the vehicle (a hover, free
flight), :func:`calibrate` measures

- the thrust axis in the IMU frame: the mean direction of the specific force (thrust is the only
  large force a multirotor makes, and it is fixed in the body);
- the distribution of the detector's own lateral and axial residuals (the very quantities it
  triggers on, computed by :class:`~groundstation.contact.impulse.ImpulseDetector`);

and sets each trigger level at ``margin`` times the largest residual seen (rounded up to
0.05 G, never below ``floor_g``). The margin covers what a short segment has not shown yet:
on the real aggressive flights the largest lateral residual of one path was within 1.3x of the
largest of the others.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from groundstation.contact.impulse import ImpulseDetector
from groundstation.contact.settings import ContactSettings, G
from groundstation.errors import InputDataError

_IDENTITY = (1.0, 0.0, 0.0, 0.0)
OUTLIER_RATIO = 3.0


@dataclasses.dataclass(frozen=True)
class ResidualStats:
    """One residual channel over the segment, in G."""

    p99: float
    p999: float
    max: float


@dataclasses.dataclass(frozen=True)
class DetectorCalibration:
    """What :func:`calibrate` measured and the settings it recommends.

    Attributes
    ----------
    samples : int
        IMU samples used (after the detector's warm-up).
    duration_s : float
    thrust_axis : tuple of 3 float
        Unit thrust direction in the IMU frame (FRD).
    lateral, axial : ResidualStats
    lateral_threshold_g, axial_threshold_g : float
    margin : float
    impulses_at_s : tuple of float
        Seconds into the segment where a residual stood out from the rest (above
        ``OUTLIER_RATIO`` times its 99th percentile): something may have touched the vehicle
        there, and then the levels are too high. Choose another segment.
    """

    samples: int
    duration_s: float
    thrust_axis: tuple[float, float, float]
    lateral: ResidualStats
    axial: ResidualStats
    lateral_threshold_g: float
    axial_threshold_g: float
    margin: float
    impulses_at_s: tuple[float, ...] = ()

    def settings(self, base: ContactSettings) -> ContactSettings:
        """``base`` with the calibrated trigger levels and thrust axis."""
        return dataclasses.replace(
            base,
            lateral_threshold_g=self.lateral_threshold_g,
            axial_threshold_g=self.axial_threshold_g,
            thrust_axis=self.thrust_axis,
        )

    def to_toml(self, source: str) -> str:
        """A ``[contact]`` table ``--config`` accepts, with the measurements as comments."""
        ax = ", ".join(f"{v:.4f}" for v in self.thrust_axis)

        def line(name: str, s: ResidualStats, thr: float) -> str:
            return (
                f"# {name} residual: p99 {s.p99:.2f} G, p99.9 {s.p999:.2f} G, max {s.max:.2f} G"
                f" -> trigger {thr:.2f} G (margin {thr / max(s.max, 1e-9):.2f} over the max)"
            )

        warn = (
            [
                "# WARNING: impulses stand out at "
                + ", ".join(f"{x:.2f}" for x in self.impulses_at_s[:10])
                + " s into the segment: was it really contact-free? Choose another segment."
            ]
            if self.impulses_at_s
            else []
        )
        return "\n".join(
            [
                f"# groundstation calibrate detector: {source}",
                *warn,
                f"# contact-free segment: {self.duration_s:.1f} s, {self.samples} IMU samples",
                f"# thrust axis in the IMU frame (FRD): ({ax})",
                line("lateral", self.lateral, self.lateral_threshold_g),
                line("axial", self.axial, self.axial_threshold_g),
                "[contact]",
                f"lateral_threshold_g = {self.lateral_threshold_g:.2f}",
                f"axial_threshold_g = {self.axial_threshold_g:.2f}",
                f"thrust_axis = [{ax}]",
                "",
            ]
        )


def thrust_axis(specific_force_frd: np.ndarray) -> tuple[float, float, float]:
    """Unit mean direction of the specific force, IMU frame (the thrust axis)."""
    f = np.asarray(specific_force_frd, dtype=np.float64)
    m = f.mean(axis=0)
    n = float(np.linalg.norm(m))
    if not math.isfinite(n) or n < 0.5 * G:
        raise InputDataError(
            f"the mean specific force of the segment is {n:.2f} m/s^2, not ~1 G",
            hint="calibrate on a segment where the vehicle hovers or flies (or rests level)",
        )
    return tuple(float(v) for v in m / n)  # type: ignore[return-value]


def _round_up(x: float, step: float = 0.05) -> float:
    return math.ceil(x / step - 1e-9) * step


def calibrate(
    t_ns: np.ndarray,
    specific_force_frd: np.ndarray,
    base: ContactSettings | None = None,
    margin: float = 1.35,
    floor_g: float = 0.3,
) -> DetectorCalibration:
    """Calibrate the impulse detector on a contact-free segment.

    Parameters
    ----------
    t_ns : (n,) int64
        Sample times, ns, increasing.
    specific_force_frd : (n, 3) float64
        Accelerometer samples, body FRD, m/s^2.
    base : ContactSettings
        Settings whose window lengths are used (defaults when None).
    margin : float
        Trigger level over the largest residual seen (> 1).
    floor_g : float
        Lowest trigger level, G.

    Raises
    ------
    InputDataError
        Too few samples, non-finite data, or no thrust to find an axis from.
    """
    base = base or ContactSettings()
    t = np.asarray(t_ns, dtype=np.int64)
    f = np.asarray(specific_force_frd, dtype=np.float64)
    if t.ndim != 1 or f.shape != (t.size, 3):
        raise InputDataError(f"need (n,) times and (n, 3) samples, got {t.shape} and {f.shape}")
    if not np.isfinite(f).all():
        raise InputDataError("the segment holds non-finite accelerometer samples")
    if not margin > 1.0:
        raise InputDataError(f"margin {margin!r} must be > 1")
    warm_ns = int((base.baseline_s + base.baseline_gap_s + base.impulse_window_s) * 1e9)
    if t.size < 50 or int(t[-1] - t[0]) < 2 * warm_ns:
        raise InputDataError(
            f"the segment is too short ({t.size} samples, {(t[-1] - t[0]) / 1e9:.2f} s)",
            hint="give at least a few seconds of contact-free flight",
        )
    u = thrust_axis(f)
    probe = dataclasses.replace(
        base, thrust_axis=u, lateral_threshold_g=1e6, axial_threshold_g=1e6
    )  # never triggers: only the residuals are wanted
    det = ImpulseDetector(probe, batch=256, keep_residuals=True)
    for ti, fi in zip(t.tolist(), f, strict=True):
        det.update(ti, fi, _IDENTITY, None)
    det.flush()
    tr = np.concatenate([r[0] for r in det.residuals])
    lat = np.concatenate([r[1] for r in det.residuals]) / G
    ax = np.abs(np.concatenate([r[2] for r in det.residuals])) / G
    if lat.size == 0:
        raise InputDataError("no sample of the segment got past the detector's warm-up")

    def stats(x: np.ndarray) -> ResidualStats:
        return ResidualStats(
            float(np.percentile(x, 99)), float(np.percentile(x, 99.9)), float(x.max())
        )

    sl, sa = stats(lat), stats(ax)
    out = (lat > OUTLIER_RATIO * max(sl.p99, 1e-6)) | (ax > OUTLIER_RATIO * max(sa.p99, 1e-6))
    times: list[float] = []
    for x in ((tr[out] - t[0]) / 1e9).tolist():
        if not times or x - times[-1] > 0.5:
            times.append(x)
    return DetectorCalibration(
        samples=int(lat.size),
        duration_s=float(t[-1] - t[0]) / 1e9,
        thrust_axis=u,
        lateral=sl,
        axial=sa,
        lateral_threshold_g=max(floor_g, _round_up(margin * sl.max)),
        axial_threshold_g=max(floor_g, _round_up(margin * sa.max)),
        margin=margin,
        impulses_at_s=tuple(times),
    )
