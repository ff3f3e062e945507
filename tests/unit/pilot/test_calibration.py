"""Calibration maths (raw -> -1..1 and 0..1) and the per-device TOML store."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from groundstation.errors import ConfigError
from groundstation.pilot.calibration import (
    AxisCalibration,
    CalibrationError,
    DeviceCalibration,
    dumps,
    find_calibration,
    load_calibrations,
    loads,
    save_calibration,
)

ROLES = {"roll": 0, "pitch": 1, "yaw": 2, "throttle": 3}


def device(name: str = "Pad", **overrides: AxisCalibration) -> DeviceCalibration:
    axes = {i: AxisCalibration(-30000, 1000, 32000) for i in range(4)}
    axes.update({int(k[1:]): v for k, v in overrides.items()})
    return DeviceCalibration(name, axes, ROLES)


def test_signed_maps_min_centre_max_to_minus_one_zero_one():
    a = AxisCalibration(-30000, 1000, 32000)
    assert a.signed(-30000) == -1.0
    assert a.signed(1000) == 0.0
    assert a.signed(32000) == 1.0
    # piecewise linear on each side of an off-centre rest position
    assert a.signed(1000 + 15500) == pytest.approx(0.5)
    assert a.signed(1000 - 15500) == pytest.approx(-0.5)


def test_signed_clamps_beyond_recorded_extremes_and_reversal_flips():
    a = AxisCalibration(-20000, 0, 20000)
    assert a.signed(32767) == 1.0 and a.signed(-32768) == -1.0
    r = AxisCalibration(-20000, 0, 20000, reversed=True)
    assert r.signed(20000) == -1.0 and r.signed(-10000) == pytest.approx(0.5)
    assert a.signed(float("nan")) == 0.0


def test_unit_maps_min_to_zero_and_max_to_one_for_down_zero_throttle():
    a = AxisCalibration(-32767, 0, 32767)
    assert a.unit(-32767) == 0.0 and a.unit(32767) == 1.0
    assert a.unit(0) == pytest.approx(0.5)
    # Linux reports stick-up as negative: reversed throttle is 1 at min, 0 at max
    r = AxisCalibration(-32767, 0, 32767, reversed=True)
    assert r.unit(-32767) == 1.0 and r.unit(32767) == 0.0
    assert a.unit(99999) == 1.0 and a.unit(float("nan")) == 0.0


@given(st.integers(-32768, 32767))
def test_signed_and_unit_stay_in_range_and_are_monotonic(raw):
    a = AxisCalibration(-25000, -2000, 30000)
    assert -1.0 <= a.signed(raw) <= 1.0 and 0.0 <= a.unit(raw) <= 1.0
    assert a.signed(raw) <= a.signed(min(raw + 1, 32767))
    assert a.flipped().signed(raw) == -a.signed(raw)


@pytest.mark.parametrize(
    "args, word",
    [((0, 0, 10), "min < centre < max"), ((10, 0, 20), "min < centre"), ((0, 5, 40000), "max"),
     ((0.5, 1, 2), "min"), ((-1, 0, 1, "yes"), "reversed")],
)  # fmt: skip
def test_bad_axis_calibration_names_the_problem(args, word):
    with pytest.raises(CalibrationError, match=word):
        AxisCalibration(*args)
    assert issubclass(CalibrationError, ConfigError)


def test_device_calibration_checks_roles_and_axes():
    axes = {i: AxisCalibration(-1, 0, 1) for i in range(3)}
    with pytest.raises(CalibrationError, match="throttle is axis 3"):
        DeviceCalibration("Pad", axes, ROLES)
    with pytest.raises(CalibrationError, match="two roles"):
        DeviceCalibration("Pad", axes, {"roll": 0, "pitch": 0, "yaw": 1, "throttle": 2})
    with pytest.raises(CalibrationError, match="exactly the roles"):
        DeviceCalibration("Pad", axes, {"roll": 0, "pitch": 1, "yaw": 2})
    with pytest.raises(CalibrationError, match="name"):
        DeviceCalibration(" ", axes, ROLES)


def test_overrides_remap_and_reverse():
    cal = device(a4=AxisCalibration(-5, 0, 5))
    o = cal.with_overrides(axis_map=(4, 1, 2, 3), reverse=("pitch",))
    assert o.roles["roll"] == 4 and o.axes[1].reversed and not cal.axes[1].reversed
    with pytest.raises(CalibrationError, match="no calibration"):
        cal.with_overrides(axis_map=(7, 1, 2, 3))


def test_store_round_trip_is_keyed_by_device_name(tmp_path):
    path = tmp_path / "sub" / "joystick.toml"
    a = device('Weird "name" \\ with\ttab', a1=AxisCalibration(-32767, 0, 32767, True))
    b = device("Other Pad")
    save_calibration(path, a)
    save_calibration(path, b)
    store = load_calibrations(path)
    assert set(store) == {a.name, b.name}
    assert store[a.name] == a and store[b.name] == b
    assert find_calibration(path, "missing") is None
    # replacing one device keeps the other
    a2 = device(a.name, a0=AxisCalibration(-100, 0, 100))
    save_calibration(path, a2)
    assert load_calibrations(path) == {a.name: a2, b.name: b}
    assert loads(dumps({"x": b})) == {"x": DeviceCalibration("x", b.axes, b.roles)}


def test_missing_store_is_empty_and_bad_store_is_a_clear_error(tmp_path):
    assert load_calibrations(tmp_path / "none.toml") == {}
    bad = tmp_path / "bad.toml"
    bad.write_text("[devices.Pad]\nroll = 0\n")
    with pytest.raises(CalibrationError, match="missing key 'pitch'"):
        load_calibrations(bad)
    bad.write_text("not toml [")
    with pytest.raises(CalibrationError, match="not valid TOML"):
        load_calibrations(bad)
    bad.write_text(
        "[devices.Pad]\nroll=0\npitch=1\nyaw=2\nthrottle=3\n[devices.Pad.axes.0]\nmin=5\ncentre=0\nmax=9\n"
    )
    with pytest.raises(CalibrationError, match="axis 0: .*min < centre < max"):
        load_calibrations(bad)
