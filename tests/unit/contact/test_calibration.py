"""Detector calibration on contact-free segments."""

from __future__ import annotations

import math

import numpy as np
import pytest

from groundstation.contact.calibration import calibrate, thrust_axis
from groundstation.contact.settings import ContactSettings, G
from groundstation.errors import InputDataError

from .test_impulse import WALL, flight, run, touch


def test_thrust_axis_of_a_tilted_imu():
    tilt = math.radians(9.0)
    u = np.array([math.sin(tilt), 0.0, -math.cos(tilt)])
    f = G * u + np.random.default_rng(0).normal(0, 0.5, (2000, 3))
    assert np.dot(thrust_axis(f), u) > 0.9999
    with pytest.raises(InputDataError, match="not ~1 G"):
        thrust_axis(np.zeros((100, 3)))


def test_levels_are_the_margin_over_the_largest_residual_and_work_on_the_rest():
    t, f, _, _ = flight(duration=20.0, noise=3.0, seed=3)  # ~0.3 G of vibration
    cal = calibrate(t, f, margin=1.4)
    assert cal.lateral.p99 <= cal.lateral.p999 <= cal.lateral.max
    assert cal.lateral_threshold_g >= 1.4 * cal.lateral.max - 1e-9
    assert cal.lateral_threshold_g - 1.4 * cal.lateral.max < 0.05 + 1e-9
    assert np.dot(cal.thrust_axis, (0.0, 0.0, -1.0)) > 0.999
    s = cal.settings(ContactSettings())
    # the calibrated detector: quiet on another stretch of the same noise, sees a 0.3 m/s touch
    quiet, _ = run(flight(duration=20.0, noise=3.0, seed=4), settings=s)
    assert quiet.events == []
    hit, _ = run(flight(noise=3.0, seed=5, **touch(speed=0.3)), settings=s)
    assert len(hit.events) == 1 and hit.events[0].normal @ WALL > 0.95
    text = cal.to_toml("test")
    assert "[contact]" in text and "lateral_threshold_g" in text and "margin" in text


def test_too_short_or_bad_segments_are_named():
    t, f, _, _ = flight(duration=0.2)
    with pytest.raises(InputDataError, match="too short"):
        calibrate(t, f)
    t, f, _, _ = flight(duration=5.0)
    f[10, 0] = np.nan
    with pytest.raises(InputDataError, match="non-finite"):
        calibrate(t, f)


def test_an_impulse_in_the_segment_is_pointed_out():
    t, f, _, _ = flight(duration=20.0, noise=3.0, seed=6, **touch(t0=9.0, speed=1.0))
    cal = calibrate(t, f)
    assert cal.impulses_at_s and abs(cal.impulses_at_s[0] - 9.0) < 0.1
    assert "WARNING" in cal.to_toml("test")
    assert not calibrate(*flight(duration=20.0, noise=3.0, seed=7)[:2]).impulses_at_s
