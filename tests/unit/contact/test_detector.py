"""Contact detector core: frames, filters, threshold, hysteresis, localisation, rates."""

from __future__ import annotations

import math

import numpy as np
import pytest

from groundstation.contact import (
    ContactDetector,
    ContactSettings,
    G,
    contact_point,
    earth_acceleration,
)
from groundstation.contact.filters import Butterworth2, MovingAverage, make_filter

DT = 5_000_000  # 200 Hz in ns


def run(detector, accels, position=(1.0, 2.0, 1.0), t0=0):
    obs = []
    for k, a in enumerate(accels):
        obs += detector.update(t0 + k * DT, a, None if position is None else np.array(position))
    return obs


def pulse(n_before, n_pulse, n_after, vec_g):
    a = np.zeros((n_before + n_pulse + n_after, 3))
    a[n_before : n_before + n_pulse] = np.asarray(vec_g) * G
    return a


def quat_from_euler_frd(roll, pitch, yaw):
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
    )


@pytest.mark.parametrize("roll,pitch,yaw", [(0, 0, 0), (0.3, -0.2, 1.0), (-0.5, 0.4, -2.5)])
def test_a_vehicle_at_rest_has_zero_earth_acceleration(roll, pitch, yaw):
    q = quat_from_euler_frd(roll, pitch, yaw)
    # specific force at rest = -g expressed in body: R^T (0, 0, -g) in NED
    w, x, y, z = q
    r = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )
    f_body = r.T @ np.array([0, 0, -G])
    np.testing.assert_allclose(earth_acceleration(f_body, q), 0, atol=1e-12)


def test_earth_acceleration_is_in_enu():
    # Level, heading north (identity FRD->NED). A push towards north-east-up in NED terms:
    # forward (north) 1 m/s^2 -> world +y (ENU north); right (east) 2 -> world +x; up 3 -> +z.
    f_body = np.array([1.0, 2.0, -G - 3.0])
    np.testing.assert_allclose(earth_acceleration(f_body, [1, 0, 0, 0]), [2.0, 1.0, 3.0])


def test_a_bump_is_one_event_with_outward_normal_and_paper_geometry():
    s = ContactSettings()
    det = ContactDetector(s)
    obs = run(det, pulse(40, 30, 200, [1.5, 0, 0]))  # wall on the -x side pushes us to +x
    assert det.stats.contacts == 1 and len(det.events) == 1
    contacts = [o for o in obs if o.label == 0.0]
    internals = [o for o in obs if o.label == -1.0]
    assert contacts and len(contacts) == len(internals)
    for c, i in zip(contacts, internals, strict=True):
        np.testing.assert_allclose(c.normal, [1, 0, 0], atol=1e-9)
        np.testing.assert_allclose(c.position, [1.0 - s.drone_radius_m, 2.0, 1.0], atol=1e-9)
        np.testing.assert_allclose(i.position, c.position - [s.internal_depth_m, 0, 0], atol=1e-9)
    # at most 25 Hz while in contact: the pulse lasts 150 ms (+ filter tail)
    times = np.array([c.t_ns for c in contacts])
    assert np.all(np.diff(times) >= 40_000_000)
    assert 3 <= len(contacts) <= 6


def test_vertical_normal_uses_the_height():
    s = ContactSettings(drone_height_m=0.07)
    n = np.array([0.1, 0.0, 0.99])
    n /= np.linalg.norm(n)
    np.testing.assert_allclose(contact_point(np.zeros(3), n, s), -0.07 * n)


def test_hysteresis_keeps_a_noisy_contact_as_one_event():
    rng = np.random.default_rng(0)
    mags = 0.62 + 0.05 * rng.standard_normal(120)  # hovers around the 0.6 G threshold
    a = np.zeros((400, 3))
    a[50:170, 0] = mags * G
    det = ContactDetector(ContactSettings(filter="none", threshold_g=0.6))
    run(det, a)
    assert det.stats.contacts == 1


def test_refractory_time_merges_a_double_bump():
    a = pulse(40, 10, 0, [1.2, 0, 0])
    gap = np.zeros((20, 3))  # 100 ms apart: inside the 250 ms refractory time
    a = np.vstack([a, gap, pulse(0, 10, 200, [1.2, 0, 0])])
    det = ContactDetector(ContactSettings(filter="none", threshold_g=0.6))
    run(det, a)
    assert det.stats.contacts == 1
    det2 = ContactDetector(ContactSettings(filter="none", threshold_g=0.6, refractory_s=0.0))
    run(det2, a)
    assert det2.stats.contacts == 2


def test_vibration_fires_unfiltered_but_not_through_the_moving_average():
    rng = np.random.default_rng(1)
    t = np.arange(2000) * DT * 1e-9
    # propeller-like vibration: 0.5 G at 90 Hz plus 0.25 G broadband noise
    vib = 0.5 * G * np.sin(2 * np.pi * 90 * t)[:, None] * np.array([0.6, 0.3, 0.74])
    vib = vib + 0.25 * G * rng.standard_normal((2000, 3))
    raw = ContactDetector(ContactSettings(filter="none", threshold_g=0.6, refractory_s=0.0))
    run(raw, vib)
    filt = ContactDetector(ContactSettings(threshold_g=0.6))
    run(filt, vib)
    assert raw.stats.contacts > 20
    assert filt.stats.contacts == 0


def test_external_points_follow_the_data_clock_at_half_a_hertz():
    det = ContactDetector(ContactSettings())
    obs = run(det, np.zeros((200 * 10, 3)))  # 10 s of quiet flight
    ext = [o for o in obs if o.label == 1.0]
    assert len(ext) == 5
    np.testing.assert_allclose(ext[0].position, [1, 2, 1])
    assert np.diff([o.t_ns for o in ext]).min() == 2_000_000_000


def test_external_points_also_follow_the_path_flown():
    """Moving at 0.5 m/s with a 0.1 m spacing: one point per 0.1 m of path (5 Hz), not the
    clock's 0.5 Hz; hovering falls back to the clock; spacing 0 is the paper's rule."""
    n = 200 * 10
    path = [np.array([1.0 + 0.5 * k * DT / 1e9, 2.0, 1.0]) for k in range(n)]

    def external(settings, positions):
        det = ContactDetector(settings)
        obs = []
        for k, p in enumerate(positions):
            obs += det.update(k * DT, np.zeros(3), p)
        return [o for o in obs if o.label == 1.0]

    moving = external(ContactSettings(external_spacing_m=0.1), path)
    gaps = np.linalg.norm(np.diff([o.position for o in moving], axis=0), axis=1)
    assert 45 <= len(moving) <= 51 and gaps.min() >= 0.1 - 1e-9 and gaps.max() < 0.11
    hover = external(ContactSettings(external_spacing_m=0.1), [path[0]] * n)
    assert len(hover) == 5  # the 0.5 Hz clock alone
    paper = external(ContactSettings(external_spacing_m=0.0), path)
    assert len(paper) == 5


def test_no_external_points_right_after_a_contact():
    det = ContactDetector(ContactSettings(quiet_s=1.0, external_rate_hz=50.0))
    obs = run(det, pulse(20, 20, 400, [2.0, 0, 0]))
    start, end = det.events[0].t_start_ns, det.events[0].t_end_ns
    after = [o.t_ns for o in obs if o.label == 1.0 and o.t_ns > start]
    assert after and min(after) >= end + 1_000_000_000 - DT


def test_missing_pose_is_counted_and_bad_samples_rejected():
    det = ContactDetector(ContactSettings(filter="none"))
    obs = run(det, pulse(10, 20, 10, [2.0, 0, 0]), position=None)
    assert obs == [] and det.stats.contacts == 1 and det.stats.no_pose > 0
    det2 = ContactDetector()
    assert det2.update(0, [np.nan, 0, 0], np.zeros(3)) == []
    det2.update(10, [0, 0, 0], np.zeros(3))
    assert det2.update(5, [0, 0, 0], np.zeros(3)) == []  # time going backwards
    assert det2.stats.rejected == 2


def test_observation_ids_are_unique_and_increasing_from_first_id():
    det = ContactDetector(ContactSettings(), first_id=100)
    obs = run(det, np.vstack([np.zeros((600, 3)), pulse(0, 30, 600, [0, 1.0, 0])]))
    ids = [o.id for o in obs]
    assert ids == list(range(100, 100 + len(ids)))


def test_moving_average_and_butterworth_pass_dc_and_cut_vibration():
    for f in (MovingAverage(0.05), Butterworth2(8.0)):
        t = np.arange(400) * DT
        dc = [f.update(int(k), np.array([1.0, -2.0, 3.0])) for k in t][-1]
        np.testing.assert_allclose(dc, [1.0, -2.0, 3.0], atol=1e-9)
        f.reset()
        out = np.array(
            [f.update(int(k), np.array([math.sin(2 * math.pi * 80 * k * 1e-9), 0, 0])) for k in t]
        )
        assert np.abs(out[200:, 0]).max() < 0.2
    with pytest.raises(ValueError, match="unknown contact filter"):
        make_filter("kalman")


def test_moving_average_resets_after_a_dropout():
    f = MovingAverage(0.05, reset_gap_s=0.1)
    f.update(0, np.array([10.0, 0, 0]))
    out = f.update(500_000_000, np.array([0.0, 0, 0]))
    np.testing.assert_allclose(out, 0)


@pytest.mark.parametrize("name", ["moving_average", "butterworth2"])
def test_no_contact_before_the_filter_has_settled(name):
    # The first sample passes a filter unfiltered: a spike there (or right after a dropout)
    # must not start a contact (it did on a real flight: a 1.5 G 'contact' at t = 0).
    det = ContactDetector(ContactSettings(filter=name))
    run(det, pulse(0, 2, 300, [3.0, 0, 0]))
    assert det.stats.contacts == 0
    det2 = ContactDetector(ContactSettings(filter=name))
    run(det2, pulse(200, 30, 300, [3.0, 0, 0]))
    assert det2.stats.contacts == 1
