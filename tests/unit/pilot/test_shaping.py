"""Shaping: deadband, expo (QGroundControl's formula), clamp, throttle, slew limit."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from groundstation.pilot.calibration import AxisCalibration, DeviceCalibration
from groundstation.pilot.shaping import (
    SlewLimiter,
    Sticks,
    calibrated_sticks,
    clamp,
    deadband,
    expo,
    shape,
    slew,
    to_manual_units,
)

unit = st.floats(-1, 1, allow_nan=False)


def qgc_expo(v: float, exponential: float) -> float:
    """QGroundControl Joystick::_handleAxis, verbatim maths (its slider value is <= 0)."""
    return -exponential * v**3 + (1 + exponential) * v


def qgc_adjust_range(value, lo, centre, hi, deadband_raw):
    """QGroundControl Joystick::_adjustRange with deadband (raw units), reversed=False."""
    if value > centre:
        basis, norm, length = 1.0, value - centre, hi - centre
    else:
        basis, norm, length = -1.0, centre - value, centre - lo
    pct = (norm - deadband_raw) / (length - deadband_raw) if norm > deadband_raw else 0.0
    return max(-1.0, min(basis * pct, 1.0))


@given(unit, st.floats(0, 1))
def test_expo_matches_qgroundcontrol(v, e):
    assert expo(v, e) == pytest.approx(qgc_expo(v, -e), abs=1e-12)


def test_expo_fixed_points_and_softer_centre():
    for e in (0.0, 0.3, 1.0):
        assert expo(1.0, e) == pytest.approx(1.0) and expo(-1.0, e) == pytest.approx(-1.0)
        assert expo(0.0, e) == 0.0
    assert expo(0.5, 0.5) == pytest.approx(0.5 * 0.125 + 0.25)
    assert abs(expo(0.2, 0.5)) < 0.2
    with pytest.raises(ValueError, match="expo"):
        expo(0.5, 1.5)


@given(st.integers(-32767, 32767))
def test_deadband_after_calibration_matches_qgroundcontrol_adjust_range(raw):
    # A symmetric axis: the normalised deadband d equals QGC's raw deadband d * 32767.
    a = AxisCalibration(-32767, 0, 32767)
    d = 0.1
    ours = deadband(a.signed(raw), d)
    assert ours == pytest.approx(qgc_adjust_range(raw, -32767, 0, 32767, d * 32767), abs=1e-9)


def test_deadband_is_zero_inside_continuous_at_edge_and_keeps_full_scale():
    assert deadband(0.05, 0.1) == 0.0 and deadband(-0.1, 0.1) == 0.0
    assert deadband(0.1 + 1e-9, 0.1) == pytest.approx(0.0, abs=1e-8)
    assert deadband(1.0, 0.1) == 1.0 and deadband(-1.0, 0.1) == -1.0
    assert deadband(0.55, 0.1) == pytest.approx(0.5)
    assert deadband(0.3, 0.0) == 0.3
    with pytest.raises(ValueError, match="deadband"):
        deadband(0.3, 1.0)


@given(unit, unit)
def test_deadband_and_expo_are_odd_and_monotonic(a, b):
    lo, hi = min(a, b), max(a, b)
    for f in (lambda v: deadband(v, 0.07), lambda v: expo(v, 0.4)):
        assert f(lo) <= f(hi) + 1e-12
        assert f(-a) == pytest.approx(-f(a))


def test_clamp_handles_nan_and_bounds():
    assert clamp(2.0, -1, 1) == 1 and clamp(-2.0, -1, 1) == -1 and clamp(0.3, -1, 1) == 0.3
    assert clamp(math.nan, -1, 1) == 0.0 and clamp(math.nan, 0.2, 1) == 0.2


def test_shape_applies_deadband_expo_clamp_and_leaves_throttle_linear():
    s = shape(Sticks(0.03, 1.4, -0.55, 0.02), deadband_width=0.05, expo_e=0.0)
    assert s.roll == 0.0 and s.pitch == 1.0
    assert s.yaw == pytest.approx(-0.5 / 0.95)
    assert s.throttle == 0.02  # no deadband on a down-zero throttle
    s2 = shape(Sticks(0.5, 0, 0, 1.7), deadband_width=0.0, expo_e=0.5)
    assert s2.roll == pytest.approx(0.3125) and s2.throttle == 1.0


def test_calibrated_sticks_uses_roles_reversal_and_down_zero_throttle():
    axes = {
        0: AxisCalibration(-32767, 0, 32767),
        1: AxisCalibration(-32767, 0, 32767, reversed=True),  # Linux: forward is negative Y
        2: AxisCalibration(-32767, 0, 32767),
        5: AxisCalibration(-32767, 0, 32767, reversed=True),  # Linux: up is negative
    }
    cal = DeviceCalibration("Pad", axes, {"roll": 2, "pitch": 1, "yaw": 0, "throttle": 5})
    s = calibrated_sticks({0: -32767, 1: -16384, 2: 32767, 5: -32767}, cal)
    assert s.roll == 1.0 and s.yaw == -1.0 and s.throttle == 1.0
    assert s.pitch == pytest.approx(0.5, abs=1e-4)
    assert calibrated_sticks({0: 0, 1: 0, 2: 0}, cal) is None  # throttle axis never seen


def test_manual_units_mapping_and_ranges():
    assert to_manual_units(Sticks(roll=0.5, pitch=-0.25, yaw=1.0, throttle=0.75)) == (
        -250, 500, 750, 1000,
    )  # fmt: skip
    assert to_manual_units(Sticks(-2, 2, -2, -1)) == (1000, -1000, 0, -1000)


def test_slew_limits_change_per_second_of_given_time():
    assert slew(0.0, 1.0, 100_000_000, 2.0) == pytest.approx(0.2)  # 0.1 s at 2 /s
    assert slew(0.0, -1.0, 100_000_000, 2.0) == pytest.approx(-0.2)
    assert slew(0.0, 0.1, 100_000_000, 2.0) == pytest.approx(0.1)  # within reach
    assert slew(0.3, 1.0, -5, 2.0) == 0.3  # time going backwards moves nothing
    assert slew(0.3, 1.0, 1, None) == 1.0


def test_slew_limiter_follows_tick_times_and_resets():
    lim = SlewLimiter(1.0)
    zero = Sticks(0, 0, 0, 0)
    full = Sticks(1, -1, 1, 1)
    assert lim.step(0, zero) == zero
    out = [lim.step(k * 40_000_000, full) for k in range(1, 30)]
    assert out[0].roll == pytest.approx(0.04) and out[0].pitch == pytest.approx(-0.04)
    assert out[24].roll == pytest.approx(1.0) and out[-1] == full
    diffs = [b.throttle - a.throttle for a, b in zip(out, out[1:], strict=False)]
    assert max(diffs) <= 0.04 + 1e-12
    lim.reset()
    assert lim.step(10**12, zero) == zero  # first step after reset passes through
    assert SlewLimiter(None).step(5, full) == full
