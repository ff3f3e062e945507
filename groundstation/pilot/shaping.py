"""Stick shaping: pure functions of value (and, for the slew limiter, of a given time).

Pipeline per control tick (QGroundControl ``Joystick::_handleAxis`` is the reference model):

1. calibration: raw -> -1..1 for roll/pitch/yaw, raw -> 0..1 for a down-zero throttle
   (:mod:`groundstation.pilot.calibration`);
2. deadband on roll/pitch/yaw, rescaled so the output is continuous (``_adjustRange``);
3. expo on roll/pitch/yaw: ``e v^3 + (1 - e) v`` (QGC's ``-exp*v^3 + (1+exp)*v`` with
   ``exp = -e``);
4. clamp;
5. optional slew limit: each axis moves at most ``rate * dt`` per tick, dt from the tick times
   passed in (integer ns, monotonic) -- nothing here reads a clock (STYLE.md item 16).

Sign conventions (MAVLink MANUAL_CONTROL): roll + = right, pitch + = forward (nose down, x
forward), yaw + = clockwise seen from above (right), thrust 0 = stick down.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

from groundstation.pilot.calibration import DeviceCalibration


@dataclasses.dataclass(frozen=True)
class Sticks:
    """Normalised stick positions: roll/pitch/yaw in -1..1, throttle (thrust) in 0..1."""

    roll: float
    pitch: float
    yaw: float
    throttle: float

    def to_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)


def clamp(v: float, lo: float, hi: float) -> float:
    """``v`` limited to [lo, hi]; NaN becomes the value nearest zero in the range."""
    if math.isnan(v):
        return min(max(0.0, lo), hi)
    return max(lo, min(hi, v))


def deadband(v: float, width: float) -> float:
    """Centre deadband of half-width ``width`` (normalised), rescaled to keep +-1 at +-1.

    ``|v| <= width -> 0``, else ``sign(v) (|v| - width) / (1 - width)``; continuous at the edge
    (QGroundControl ``_adjustRange`` with deadband, expressed in normalised units).
    """
    if not 0 <= width < 1:
        raise ValueError(f"deadband width must be in [0, 1), got {width!r}")
    a = abs(v)
    if a <= width:
        return 0.0
    return math.copysign((a - width) / (1.0 - width), v)


def expo(v: float, e: float) -> float:
    """RC-style exponential: ``e v^3 + (1 - e) v`` for e in [0, 1].

    Odd, monotonic, fixes -1, 0, 1; slope at centre 1 - e (finer control near centre).
    """
    if not 0 <= e <= 1:
        raise ValueError(f"expo must be in [0, 1], got {e!r}")
    return e * v * v * v + (1.0 - e) * v


def slew(previous: float, target: float, dt_ns: int, rate_per_s: float | None) -> float:
    """Move from ``previous`` toward ``target`` by at most ``rate_per_s * dt`` (dt in ns).

    ``rate_per_s`` None: no limit. A non-positive ``dt_ns`` (same or earlier tick) moves nothing.
    """
    if rate_per_s is None:
        return target
    step = rate_per_s * max(dt_ns, 0) * 1e-9
    return previous + clamp(target - previous, -step, step)


def calibrated_sticks(axes: Mapping[int, int], calibration: DeviceCalibration) -> Sticks | None:
    """Raw device axes -> calibrated (unshaped) sticks, or None if a mapped axis was never seen.

    Parameters
    ----------
    axes : mapping of int to int
        Latest raw value (-32767..32767) per device axis number.
    calibration : DeviceCalibration
        Per-axis calibration and role map.
    """
    roles = calibration.roles
    try:
        raw = {r: axes[roles[r]] for r in ("roll", "pitch", "yaw", "throttle")}
    except KeyError:
        return None
    cal = calibration.axes
    return Sticks(
        roll=cal[roles["roll"]].signed(raw["roll"]),
        pitch=cal[roles["pitch"]].signed(raw["pitch"]),
        yaw=cal[roles["yaw"]].signed(raw["yaw"]),
        throttle=cal[roles["throttle"]].unit(raw["throttle"]),
    )


def shape(sticks: Sticks, deadband_width: float, expo_e: float) -> Sticks:
    """Deadband + expo + clamp on roll/pitch/yaw; clamp only on the down-zero throttle.

    QGroundControl applies no deadband to a down-zero throttle (its low end is not a centre).
    """

    def axis(v: float) -> float:
        return clamp(expo(deadband(clamp(v, -1.0, 1.0), deadband_width), expo_e), -1.0, 1.0)

    return Sticks(
        roll=axis(sticks.roll),
        pitch=axis(sticks.pitch),
        yaw=axis(sticks.yaw),
        throttle=clamp(sticks.throttle, 0.0, 1.0),
    )


class SlewLimiter:
    """Per-axis slew limit across ticks; time comes in with each call (integer ns).

    The first call after construction or :meth:`reset` passes its input through unchanged (the
    commander resets it on every arm, when the sticks are centred and the throttle low).
    """

    def __init__(self, rate_per_s: float | None):
        self.rate_per_s = rate_per_s
        self._last: Sticks | None = None
        self._t_ns: int | None = None

    def reset(self) -> None:
        self._last = None
        self._t_ns = None

    def step(self, t_ns: int, target: Sticks) -> Sticks:
        """The limited sticks at tick time ``t_ns``."""
        if self._last is None or self._t_ns is None or self.rate_per_s is None:
            out = target
        else:
            dt = t_ns - self._t_ns
            prev = self._last
            out = Sticks(
                *(
                    slew(getattr(prev, f), getattr(target, f), dt, self.rate_per_s)
                    for f in ("roll", "pitch", "yaw", "throttle")
                )
            )
        self._last, self._t_ns = out, t_ns
        return out


def to_manual_units(sticks: Sticks) -> tuple[int, int, int, int]:
    """Shaped sticks -> MANUAL_CONTROL (x, y, z, r): x pitch, y roll, z thrust, r yaw.

    x/y/r in -1000..1000, z in 0..1000 (common.xml MANUAL_CONTROL), rounded to nearest.
    """

    def s(v: float, lo: int) -> int:
        return int(clamp(round(v * 1000.0), lo, 1000))

    return (
        s(sticks.pitch, -1000),
        s(sticks.roll, -1000),
        s(sticks.throttle, 0),
        s(sticks.yaw, -1000),
    )
