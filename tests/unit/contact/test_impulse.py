"""The impulse detector on synthetic flights whose physics is known exactly.

A synthetic flight: a level vehicle (attitude FRD == NED turned by ``yaw``) at 200 Hz with
white accelerometer noise, moving at constant velocity except where an impulse (half-sine
specific force along a world direction) changes its velocity by exactly the impulse. Positions are
the integral of that motion, so mocap approach and rebound speeds are exact too.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from firmware_bridge.frames import quat_from_axis_angle
from groundstation.contact.detector import LABEL_INSIDE, LABEL_OUTSIDE, LABEL_SURFACE
from groundstation.contact.evidence import (
    EvidenceModel,
    ImpulseFeatures,
    Logistic,
    design,
    model_inputs,
    n_terms,
)
from groundstation.contact.impulse import ImpulseDetector, burst_raised
from groundstation.contact.settings import ContactSettings, G
from groundstation.contact.vehicle import VehicleSettings, contact_offset
from groundstation.errors import ConfigError

RATE = 200
ENU_TO_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def flight(duration=6.0, impulses=(), v0=(0.0, 0.0, 0.0), noise=0.3, yaw=0.0, seed=0,
           thrust=None):  # fmt: skip
    """(t_ns, f_frd, q_frd_ned, pos_enu) of a synthetic flight.

    impulses: (t0 s, duration s, dv m/s, unit direction ENU); v0: velocity ENU before the first.
    thrust(t) -> extra specific force along the thrust axis (m/s^2), for manoeuvres.
    """
    n = int(duration * RATE)
    t = np.arange(n) / RATE
    rng = np.random.default_rng(seed)
    q = quat_from_axis_angle([0.0, 0.0, 1.0], yaw)  # FRD -> NED: yaw about down
    R_ned_frd = np.array(
        [[math.cos(yaw), -math.sin(yaw), 0.0], [math.sin(yaw), math.cos(yaw), 0.0], [0, 0, 1]]
    )
    a_world = np.zeros((n, 3))
    for t0, T, dv, d in impulses:
        on = (t >= t0) & (t < t0 + T)
        shape = np.sin(math.pi * (t[on] - t0) / T) * (math.pi / (2 * T)) * dv
        a_world[on] += shape[:, None] * np.asarray(d, float)
    v = np.asarray(v0, float) + np.cumsum(a_world, axis=0) / RATE
    pos = np.array([2.0, 1.0, 1.0]) + np.cumsum(v, axis=0) / RATE
    a_frd = (ENU_TO_NED @ a_world.T).T @ R_ned_frd  # world ENU -> NED -> body FRD
    f = a_frd + np.array([0.0, 0.0, -G]) + rng.normal(0.0, noise, (n, 3))
    if thrust is not None:
        f[:, 2] -= np.array([thrust(x) for x in t])
    t_ns = (1_000_000_000 + t * 1e9).astype(np.int64)
    return t_ns, f, np.tile(q, (n, 1)), pos


def run(data, settings=None, vehicle=None, batch=1, pose=True, model=None):
    t, f, q, pos = data
    det = ImpulseDetector(settings or ContactSettings(), vehicle or VehicleSettings(),
                          model=model, batch=batch)  # fmt: skip
    obs = []
    for i in range(t.size):
        obs += det.update(int(t[i]), f[i], q[i], pos[i] if pose else None)
    obs += det.flush()
    return det, obs


WALL = np.array([1.0, 0.0, 0.0])  # outward normal of a wall facing +x


def touch(t0=3.0, speed=0.3, e=0.4, T=0.022, normal=WALL, angle=0.0):
    """Approach at ``speed`` along -normal (tilted by ``angle`` in the horizontal plane), bounce
    with restitution ``e``: the impulse along the normal is (1 + e) * normal speed."""
    n = np.asarray(normal, float)
    side = np.cross(n, [0.0, 0.0, 1.0])
    if np.linalg.norm(side) < 1e-9:
        side = np.array([0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    v0 = speed * (-math.cos(angle) * n + math.sin(angle) * side)
    vn = speed * math.cos(angle)
    return dict(impulses=[(t0, T, (1 + e) * vn, n)], v0=v0)


def test_a_slow_touch_is_one_event_with_its_normal_onset_and_rebound():
    det, obs = run(flight(**touch(speed=0.3)))
    assert len(det.events) == 1
    ev = det.events[0]
    assert ev.normal @ WALL > 0.99
    assert abs(ev.t_start_ns / 1e9 - 1.0 - 3.0) < 0.011  # back-dated to the onset
    f = ev.features
    assert f.approach_mps == pytest.approx(0.3, abs=0.02)
    assert f.rebound_mps == pytest.approx(0.12, abs=0.02)
    assert f.dv_imu_mps == pytest.approx(0.42, rel=0.15)
    assert f.rebound and f.axial_fraction < 0.2
    labels = [o.label for o in obs if o.event_id == ev.id]
    assert labels[:2] == [LABEL_SURFACE, LABEL_INSIDE]


def test_the_contact_point_is_the_body_point_facing_the_wall_at_the_onset():
    t, f, q, pos = data = flight(**touch(speed=0.5))
    det, obs = run(data)
    ev = det.events[0]
    on = int(np.searchsorted(t, ev.t_start_ns))
    wall_x = pos[on, 0] - 0.2  # the cylinder's radius ahead of the centre at the onset
    xc = next(o for o in obs if o.label == LABEL_SURFACE).position
    assert abs(xc[0] - wall_x) < 0.01
    xin = next(o for o in obs if o.label == LABEL_INSIDE).position
    assert xin[0] == pytest.approx(xc[0] - 0.1, abs=2e-3)  # d_in behind it, along -n


def test_guarded_body_places_the_contact_on_the_guard_rim_whatever_the_yaw():
    body = VehicleSettings(shape="guards")
    for yaw in (0.0, 0.4, math.pi / 4):
        t, f, q, pos = data = flight(**touch(speed=0.6), yaw=yaw)
        det, obs = run(data, vehicle=body)
        ev = det.events[0]
        on = int(np.searchsorted(t, ev.t_start_ns))
        xc = next(o for o in obs if o.label == LABEL_SURFACE).position
        # level body: FLU -> ENU is a rotation about z; the rim point facing -x
        yaw_enu = math.pi / 2 - yaw  # FRD yaw from north -> FLU heading from east
        R = np.array([[math.cos(yaw_enu), -math.sin(yaw_enu), 0], [math.sin(yaw_enu),
                      math.cos(yaw_enu), 0], [0, 0, 1]])  # fmt: skip
        spread = math.radians(ContactSettings().normal_spread_deg)
        expected = pos[on] + contact_offset(body, WALL, R, spread)
        assert np.linalg.norm(xc - expected) < 0.01
        reach = -(expected - pos[on]) @ WALL
        assert 0.235 < reach < 0.30  # the guard rims reach 0.24-0.29 m (the cap mean: <1 mm less)


def test_body_support_points():
    cyl = VehicleSettings()
    assert np.allclose(contact_offset(cyl, WALL, np.eye(3)), [-0.2, 0.0, 0.0])
    assert np.allclose(contact_offset(cyl, [0, 0, 1.0], np.eye(3)), [0.0, 0.0, -0.05])
    g = VehicleSettings(shape="guards", layout="+", leg_length_m=0.0)
    # "+" layout, facing -x: the front rotor's guard rim at arm + ring radius
    assert np.allclose(contact_offset(g, WALL, np.eye(3)), [-(0.17 + 0.12), 0.0, 0.0])
    with pytest.raises(ConfigError):
        VehicleSettings(shape="sphere")


def _tilted(normal, axis, deg):
    """``normal`` turned by ``deg`` about ``axis`` (Rodrigues)."""
    n, k, a = np.asarray(normal, float), np.asarray(axis, float), math.radians(deg)
    return n * math.cos(a) + np.cross(k, n) * math.sin(a) + k * (k @ n) * (1 - math.cos(a))


def test_a_flat_part_of_the_body_touches_at_its_middle_not_at_an_end_the_normal_tilts_to():
    spread = math.radians(10.0)
    cyl = VehicleSettings()
    # A wall (outward normal +x) measured 2 deg tilted up or down: the exact support point
    # jumps to the cylinder's top or bottom rim; the cap mean stays at mid-height on its side.
    for deg in (-2.0, 2.0):
        n = _tilted(WALL, [0, 1, 0], deg)
        assert abs(contact_offset(cyl, n, np.eye(3))[2]) == pytest.approx(0.05)
        off = contact_offset(cyl, n, np.eye(3), spread)
        assert abs(off[2]) < 0.015 and off[0] == pytest.approx(-0.2, abs=0.005)
    # A floor touched from above, the normal 3 deg off vertical: the rim of the bottom end
    # (0.2 m out) against a point near its centre.
    n = _tilted([0, 0, 1.0], [1, 0, 0], 3.0)
    assert np.hypot(*contact_offset(cyl, n, np.eye(3))[:2]) == pytest.approx(0.2)
    off = contact_offset(cyl, n, np.eye(3), spread)
    assert np.hypot(*off[:2]) < 0.1 and off[2] == pytest.approx(-0.05)
    # "x" layout facing a wall head-on: two guard rings touch it; the exact support point is
    # one of them (0.12 m aside), the cap mean lies between them, on the wall.
    g = VehicleSettings(shape="guards", layout="x", leg_length_m=0.0)
    reach = 0.17 * math.cos(math.pi / 4) + 0.12
    exact = contact_offset(g, WALL, np.eye(3))
    assert abs(exact[1]) == pytest.approx(0.17 * math.sin(math.pi / 4), abs=1e-9)
    off = contact_offset(g, WALL, np.eye(3), spread)
    assert abs(off[1]) < 0.01 and off[0] == pytest.approx(-reach, abs=0.005)
    # Where the body is curved (the cylinder's side on a pillar) the mean stays on the rim.
    assert contact_offset(cyl, WALL, np.eye(3), spread) == pytest.approx([-0.2, 0, 0], abs=0.003)


def test_cap_directions_are_unit_and_within_the_cap():
    from groundstation.contact.vehicle import cap_directions

    for d in (np.array([0, 0, 1.0]), np.array([1.0, 0, 0]), np.array([0.6, -0.64, 0.48])):
        dirs = cap_directions(d, math.radians(10.0))
        assert np.allclose(np.linalg.norm(dirs, axis=1), 1.0)
        assert np.all(dirs @ d >= math.cos(math.radians(10.0)) - 1e-12)
        assert np.linalg.norm(dirs.mean(axis=0) - d * (dirs @ d).mean()) < 1e-2  # centred on d


def test_manoeuvres_along_the_thrust_axis_make_no_candidate():
    # thrust ramps of 1 G up and down in 0.3 s each (hard climbs and stops)
    def thrust(x):
        ph = x % 1.5
        return G * float(np.clip(min(ph, 0.9 - ph) / 0.3, 0, 1)) if x > 1 else 0.0

    det, _ = run(flight(duration=8.0, thrust=thrust, noise=0.4))
    assert det.events == []


def test_the_peak_normal_leaves_out_the_manoeuvre_around_the_impact():
    # a touch on the wall (+x) at 1 m/s as the vehicle brakes hard sideways (4 m/s along +y in
    # 0.5 s, up to 1.3 G): the candidate stays open through the braking, so the impulse
    # integrated over it leans towards +y; the filtered residual at its peak is the impact's.
    # Only where the contact is placed changes: the evidence is the same (measured along the
    # integral, it doubts this touch; nothing is rejected here so that both are placed).
    data = flight(impulses=[(3.0, 0.022, 1.5, WALL), (2.95, 0.5, 4.0, (0.0, 1.0, 0.0))],
                  v0=(-1.0, 0.0, 0.0))  # fmt: skip
    whole, obs_whole = run(data, ContactSettings(reject_p_false=1.0))
    peak, obs_peak = run(data, ContactSettings(reject_p_false=1.0, normal_from="peak"))
    assert len(whole.events) == len(peak.events) == 1
    ew, ep = whole.events[0], peak.events[0]
    assert math.degrees(math.acos(float(ew.normal @ WALL))) > 45.0
    assert math.degrees(math.acos(float(ep.normal @ WALL))) < 10.0
    assert ep.p_false == ew.p_false and ep.features == ew.features
    t, _, _, pos = data
    on = int(np.searchsorted(t, ep.t_start_ns))
    wall_x = pos[on, 0] - 0.2  # the cylinder's radius ahead of the centre at the onset
    placed = [o.position for o in obs_peak if o.label == LABEL_SURFACE]
    assert placed and abs(placed[0][0] - wall_x) < 0.02
    assert abs([o.position for o in obs_whole if o.label == LABEL_SURFACE][0][0] - wall_x) > 0.05


def test_an_impact_right_after_a_gust_is_measured_from_the_baseline_before_the_gust():
    # a gust (4 m/s sideways, +y, over 0.27 s) throws the vehicle, flying at the wall (+x) at
    # 1 m/s, and ends 30 ms before the impact. The impact's own baseline window holds the
    # gust's push; measured from it, the residual after the impact reads as the gust pushing
    # back (-y, 2 G), the candidate stays open for most of a second, its direction is the
    # gust's and the touch is nearly rejected. Measured from the baseline the gust's candidate
    # was measured from, it is the impact: its onset, the wall's normal, a touch's evidence.
    data = flight(impulses=[(2.76, 0.27, 4.0, (0.0, 1.0, 0.0)), (3.06, 0.022, 1.4, WALL)],
                  v0=(-1.0, 0.0, 0.0))  # fmt: skip
    t, _, _, pos = data
    window, _ = run(data, ContactSettings(reject_p_false=1.0, hold_baseline=False))
    held, obs_held = run(data, ContactSettings(reject_p_false=1.0))  # the default
    assert len(window.events) == len(held.events) == 2
    gust_w, impact_w = window.events
    gust_h, impact_h = held.events
    assert gust_h.features == gust_w.features  # the first impulse is measured as before
    assert math.degrees(math.acos(float(impact_w.normal @ WALL))) > 60.0
    assert impact_w.features.duration_s > 0.5 and impact_w.p_false > 0.9
    assert math.degrees(math.acos(float(impact_h.normal @ WALL))) < 5.0
    assert abs(impact_h.t_start_ns / 1e9 - 1.0 - 3.06) < 0.011
    assert impact_h.features.duration_s < 0.05 and impact_h.p_false < 0.1
    wall_x = pos[int(np.searchsorted(t, impact_h.t_start_ns)), 0] - 0.2
    placed = [o.position for o in obs_held if o.label == LABEL_SURFACE and o.event_id == 1]
    assert placed and abs(placed[0][0] - wall_x) < 0.02


def test_a_later_impulse_keeps_its_own_baseline_once_the_window_is_clear():
    # the same gust, the impact 0.4 s after it: its window no longer holds the gust, and
    # holding the baseline changes nothing
    data = flight(impulses=[(2.76, 0.27, 4.0, (0.0, 1.0, 0.0)), (3.43, 0.022, 1.4, WALL)],
                  v0=(-1.0, 0.0, 0.0))  # fmt: skip
    window, _ = run(data, ContactSettings(reject_p_false=1.0, hold_baseline=False))
    held, _ = run(data, ContactSettings(reject_p_false=1.0))
    assert len(window.events) == len(held.events) == 2
    assert window.events[1].features == held.events[1].features


def test_an_unknown_normal_source_is_refused():
    with pytest.raises(ValueError, match="normal_from"):
        ContactSettings(normal_from="mean")


def test_a_gust_is_long_and_pushes_without_an_approach():
    det, _ = run(flight(impulses=[(3.0, 0.2, 1.5, (0.0, 1.0, 0.0))]))
    assert len(det.events) == 1
    f = det.events[0].features
    assert f.duration_s > 0.1  # a touch's is about the 30 ms filter window
    assert abs(f.approach_mps) < 0.05 and not f.rebound


def test_batching_does_not_change_anything():
    data = flight(duration=10.0, impulses=[(3.0, 0.022, 0.6, WALL), (6.0, 0.15, 1.0, (0, 1, 0))],
                  v0=(-0.4, 0.0, 0.0))  # fmt: skip
    a, oa = run(data, batch=1)
    b, ob = run(data, batch=97)
    assert [(e.t_start_ns, e.t_end_ns, e.p_false) for e in a.events] == [
        (e.t_start_ns, e.t_end_ns, e.p_false) for e in b.events
    ]
    assert [(o.id, o.t_ns, o.position.tobytes()) for o in oa] == [
        (o.id, o.t_ns, o.position.tobytes()) for o in ob
    ]


@pytest.mark.parametrize("quiet_s", [0.0, 0.05, 0.1, 0.5])
def test_batching_does_not_change_the_order_of_free_space_and_contacts(quiet_s):
    # A fast vehicle (a free-space point every 0.05 s of path) and a short pause: free space is
    # due while an impulse waits for its evidence window, on either side of where it ends.
    s = ContactSettings(quiet_s=quiet_s)
    data = flight(duration=8.0, impulses=[(3.0, 0.022, 0.6, WALL), (5.0, 0.03, 0.8, (0, 1, 0))],
                  v0=(-2.0, 0.0, 0.0))  # fmt: skip
    runs = [run(data, settings=s, batch=b) for b in (1, 7, 64, 97)]
    seqs = [[(o.id, o.t_ns, o.label, o.event_id) for o in obs] for _, obs in runs]
    assert all(seq == seqs[0] for seq in seqs[1:])
    assert sum(o[2] == LABEL_SURFACE for o in seqs[0]) >= 2  # both impulses made contacts


def test_without_a_pose_the_event_is_kept_but_nothing_is_placed():
    det, obs = run(flight(**touch(speed=0.5)), pose=False)
    assert len(det.events) == 1 and obs == []
    assert not det.events[0].features.has_mocap
    assert det.stats.no_pose > 0


def test_bad_samples_are_rejected_and_counted():
    det = ImpulseDetector()
    q = (1.0, 0.0, 0.0, 0.0)
    assert det.update(10, (0.0, 0.0, -G), q) == []
    assert det.update(10, (0.0, 0.0, -G), q) == []  # same time
    assert det.update(20, (math.nan, 0.0, -G), q) == []
    assert det.update(30, (0.0, 0.0), q) == []  # wrong shape
    assert det.update(40, (0.0, 0.0, -G), (1.0, math.inf, 0, 0)) == []
    assert det.stats.rejected == 4


def test_free_space_follows_time_and_path_and_pauses_after_an_impulse():
    # 0.05 m/s: a point every 2 s of data time (the paper's 0.5 Hz); then 0.55 m/s after the
    # impulse: a point every 0.1 m of path
    data = flight(duration=12.0, v0=(0.05, 0.0, 0.0), impulses=[(7.0, 0.022, 0.5, WALL)])
    det, obs = run(data)
    ext = [o for o in obs if o.label == LABEL_OUTSIDE]
    t = np.array([o.t_ns for o in ext]) / 1e9 - 1.0
    quiet = det.settings.quiet_s
    assert quiet > 0
    ev = det.events[0]
    end = ev.t_end_ns / 1e9 - 1.0
    before, after = t[t < 7.0], t[t > end + quiet]
    assert np.allclose(np.diff(before), 2.0, atol=0.01)
    assert np.allclose(np.diff(after), 0.1 / 0.55, atol=0.01)
    assert [x for x in t if 7.0 - 0.01 < x < end + quiet] == []
    assert after[0] < end + quiet + 0.1 / 0.55 + 0.01  # sampling resumes once the pause is over


def _tilted_during(data, t0, t1, deg, axis=(1.0, 0.0, 0.0)):
    """``data`` with the attitude turned ``deg`` about a horizontal body axis from t0 to t1 s."""
    t, f, q, pos = data
    q = q.copy()
    s = (t - t[0]) / 1e9
    q[(s >= t0) & (s < t1)] = quat_from_axis_angle(list(axis), math.radians(deg))
    return t, f, q, pos


@pytest.mark.parametrize("deg, axis", [(90.0, (1, 0, 0)), (60.0, (0, 1, 0)), (180.0, (1, 0, 0))])
def test_no_free_space_while_the_body_is_tilted_past_the_limit(deg, axis):
    # 0.5 m/s: a free-space sample every 0.1 m (0.2 s); tilted from 4 to 8 s (a flip, a crash)
    data = _tilted_during(flight(duration=12.0, v0=(0.5, 0.0, 0.0)), 4.0, 8.0, deg, axis)
    det, obs = run(data, ContactSettings(external_max_tilt_deg=45.0))
    t = np.array([o.t_ns for o in obs if o.label == LABEL_OUTSIDE]) / 1e9 - 1.0
    assert obs and all(o.label == LABEL_OUTSIDE for o in obs)
    assert [x for x in t if 4.0 <= x < 8.0] == []
    assert t[t < 4.0].size >= 19 and t[t >= 8.0].size >= 19
    assert t[t >= 8.0][0] < 8.0 + 0.2 + 0.01  # sampling resumes once the body is level again
    # the skipped ones count once per due slot, not per IMU sample
    assert det.stats.tilted == pytest.approx(4.0 / 0.2, abs=1)


def test_free_space_at_a_tilt_within_the_limit_and_with_no_limit_the_default():
    data = flight(duration=12.0, v0=(0.5, 0.0, 0.0))
    level = [o.t_ns for o in run(data)[1]]
    det, obs = run(
        _tilted_during(data, 4.0, 8.0, 44.0), ContactSettings(external_max_tilt_deg=45.0)
    )
    assert [o.t_ns for o in obs] == level and det.stats.tilted == 0
    for no_limit in (ContactSettings(), ContactSettings(external_max_tilt_deg=180.0)):
        det, obs = run(_tilted_during(data, 4.0, 8.0, 180.0), no_limit)  # upside down
        assert [o.t_ns for o in obs] == level and det.stats.tilted == 0
    with pytest.raises(ValueError, match="external_max_tilt_deg"):
        ContactSettings(external_max_tilt_deg=0.0)


def test_tilt_cos_matches_the_rotation_matrix():
    from firmware_bridge.frames import quat_to_matrix
    from groundstation.contact.impulse import tilt_cos

    rng = np.random.default_rng(3)
    for q in rng.normal(size=(50, 4)) * 2.0:
        assert tilt_cos(q) == pytest.approx(quat_to_matrix(q)[2, 2], abs=1e-12)
    assert math.isnan(tilt_cos(np.zeros(4))) and math.isnan(tilt_cos([math.nan, 0, 0, 1]))


def test_rejected_candidates_make_no_observations():
    always_false = Logistic(("log_peak_g",), (0.0,), (1.0,), (0.0,), 10.0)
    model = EvidenceModel(always_false, always_false, "test")
    det, obs = run(flight(**touch(speed=0.5)), model=model)
    assert det.events[0].rejected and det.events[0].p_false > 0.99
    assert [o for o in obs if o.label != LABEL_OUTSIDE] == []


def test_model_inputs_and_probability():
    f = ImpulseFeatures(2.0, 2.5, 0.03, 0.42, 0.1, 0.3, 0.12, 1.4)
    z = model_inputs(f)
    assert z["log_duration_ms"] == pytest.approx(math.log(30.0))
    assert z["reversal"] == pytest.approx(0.12)
    assert "approach" not in model_inputs(ImpulseFeatures(2.0, 2.5, 0.03, 0.42, 0.1))
    lg = Logistic(("log_duration_ms",), (3.0,), (1.0,), (2.0,), 0.0)
    assert lg.probability({"log_duration_ms": 3.0}) == pytest.approx(0.5)
    assert lg.probability({"log_duration_ms": 5.0}) > 0.95


def test_a_missing_input_counts_as_its_training_mean():
    lg = Logistic(("log_duration_ms", "log_turn_rate"), (3.0, -1.0), (1.0, 1.0), (2.0, 1.5), 0.3)
    assert lg.probability({"log_duration_ms": 4.0}) == pytest.approx(
        lg.probability({"log_duration_ms": 4.0, "log_turn_rate": -1.0})
    )
    no_rate = ImpulseFeatures(2.0, 2.5, 0.03, 0.42, 0.1)
    assert "log_turn_rate" not in model_inputs(no_rate)
    fast = model_inputs(ImpulseFeatures(2.0, 2.5, 0.03, 0.42, 0.1, turn_rate_radps=40.0))
    still = model_inputs(ImpulseFeatures(2.0, 2.5, 0.03, 0.42, 0.1, turn_rate_radps=0.0))
    assert fast["log_turn_rate"] == pytest.approx(math.log(3.0))  # capped
    assert still["log_turn_rate"] == pytest.approx(math.log(0.3))  # floored


def test_a_second_degree_model_weighs_products_of_two_inputs():
    names = ("log_duration_ms", "rebound")
    # p = sigmoid(2 x0 x1): false when both are high or both low, true otherwise
    lg = Logistic(names, (3.0, 0.5), (1.0, 0.5), (0.0, 0.0, 0.0, 2.0, 0.0), 0.0, degree=2)
    assert lg.probability({"log_duration_ms": 4.0, "rebound": 1.0}) == pytest.approx(
        1.0 / (1.0 + math.exp(-2.0))
    )
    assert lg.probability({"log_duration_ms": 2.0, "rebound": 1.0}) < 0.5
    # a missing input is its training mean: it and every product with it are 0
    assert lg.probability({"log_duration_ms": 9.0}) == pytest.approx(0.5)
    # the terms are the inputs, then x_i x_j for i <= j, in one order for fit and prediction
    assert design(np.array([[2.0, 3.0]]), 2).tolist() == [[2.0, 3.0, 4.0, 6.0, 9.0]]
    assert n_terms(2, 2) == 5 and n_terms(10, 2) == 65 and n_terms(3, 1) == 3


def test_clipping_bounds_an_input_far_outside_the_training_flights():
    squared = Logistic(("log_peak_g",), (0.0,), (1.0,), (0.0, 1.0), -4.0, degree=2, clip_sd=2.0)
    assert squared.probability({"log_peak_g": 50.0}) == pytest.approx(0.5)  # 2^2 - 4
    free = dataclasses.replace(squared, clip_sd=None)
    assert free.probability({"log_peak_g": 50.0}) > 0.999


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"coef": (1.0, 2.0)}, "need 5 coefficients"),
        ({"degree": 3}, "degree must be 1 or 2"),
        ({"clip_sd": 0.0}, "clip_sd must be positive"),
    ],
)
def test_a_malformed_second_degree_model_is_refused(kwargs, match):
    base = {"names": ("a", "b"), "mean": (0.0, 0.0), "scale": (1.0, 1.0), "intercept": 0.0,
            "coef": (0.0,) * 5, "degree": 2}  # fmt: skip
    with pytest.raises(ConfigError, match=match):
        Logistic(**{**base, **kwargs})


def test_a_model_written_before_the_degree_existed_loads_as_linear():
    block = {"names": ["a"], "mean": [1.0], "scale": [2.0], "coef": [3.0], "intercept": 0.5}
    lg = Logistic.from_dict(block)
    assert (lg.degree, lg.clip_sd) == (1, None)
    assert Logistic.from_dict(lg.to_dict()) == lg
    shipped = EvidenceModel.load()
    assert Logistic.from_dict(shipped.with_mocap.to_dict()) == shipped.with_mocap


def turning_before(data, t_stop, rate, t_start):
    """``data`` with the vehicle yawing at ``rate`` rad/s over [t_start, t_stop] s (flight time)
    and still before and after; specific force is unchanged while the velocity is constant."""
    t, f, q, pos = data
    ts = (t - t[0]) / 1e9
    yaw = -rate * np.clip(t_stop - ts, 0.0, t_stop - t_start)  # ends at the flight's yaw, 0
    q = np.array([quat_from_axis_angle([0.0, 0.0, 1.0], float(y)) for y in yaw])
    return t, f, q, pos


@pytest.mark.parametrize("rate", [0.8, 2.0])
def test_the_turn_rate_before_the_onset_is_measured_from_the_attitude(rate):
    steady, _ = run(flight(**touch(speed=0.3)))
    assert steady.events[0].features.turn_rate_radps == pytest.approx(0.0, abs=1e-6)
    turned = turning_before(flight(**touch(speed=0.3)), 2.99, rate, 2.0)
    det, _ = run(turned)
    assert len(det.events) == 1
    assert det.events[0].features.turn_rate_radps == pytest.approx(rate, rel=0.05)
    # a turn that ended well before the window is not counted
    det, _ = run(turning_before(flight(**touch(speed=0.3)), 2.5, rate, 2.0))
    assert det.events[0].features.turn_rate_radps == pytest.approx(0.0, abs=1e-6)


def test_the_bundled_model_doubts_an_impulse_that_came_to_a_turning_vehicle():
    model = EvidenceModel.load()
    assert "log_turn_rate" in model.with_mocap.names and "log_turn_rate" in model.imu_only.names
    weak = dict(peak_g=1.1, score=1.3, duration_s=0.035, dv_imu_mps=0.35, axial_fraction=0.3)
    touch = dict(approach_mps=0.15, rebound_mps=0.05, agreement=0.6)
    for extra in (touch, {}):  # with mocap, and from the IMU alone
        steady = model.p_false(ImpulseFeatures(**weak, **extra, turn_rate_radps=0.05))
        braking = model.p_false(ImpulseFeatures(**weak, **extra, turn_rate_radps=2.0))
        assert braking > steady + 0.1


def test_the_bundled_evidence_model_loads_and_bad_files_are_named(tmp_path):
    EvidenceModel.load()
    bad = tmp_path / "m.json"
    bad.write_text("{")
    with pytest.raises(ConfigError, match="m.json"):
        EvidenceModel.load(bad)
    with pytest.raises(ConfigError, match="does not exist"):
        EvidenceModel.load(tmp_path / "none.json")


def test_a_push_stops_making_contacts_once_the_vehicle_has_flown_off():
    # a 0.6 s push of 15 m/s^2 peak along +y: pressed on a wall the vehicle stays put and every
    # 25 Hz sample is a contact; free to move it flies off at up to 6 m/s, and what holds the
    # impulse open is wind, not a structure (the SITL's gust-after-touch trails)
    always_true = Logistic(("log_peak_g",), (0.0,), (1.0,), (0.0,), -10.0)
    model = EvidenceModel(always_true, always_true, "test")
    t, f, q, pos = flight(impulses=[(3.0, 0.6, 6.0, (0.0, 1.0, 0.0))])
    pressed = pos.copy()
    pressed[t >= t[0] + int(3.0e9)] = pos[t >= t[0] + int(3.0e9)][0]
    det_p, obs_p = run((t, f, q, pressed), model=model)
    det_f, obs_f = run((t, f, q, pos), model=model)
    kept = [o for o in obs_p if o.label == LABEL_SURFACE]
    flown = [o for o in obs_f if o.label == LABEL_SURFACE]
    assert len(det_p.events) == len(det_f.events) == 1
    assert len(kept) >= 12 and det_p.stats.left_contact == 0
    assert 1 <= len(flown) < len(kept) // 2
    assert det_f.stats.left_contact == len(kept) - len(flown)
    spread = max(np.linalg.norm(np.asarray(o.position) - flown[0].position) for o in flown)
    assert spread < 0.3  # nothing laid along the flight path


@pytest.mark.parametrize("normal_m", [0.05, 0.0])
def test_a_push_stops_making_contacts_once_the_vehicle_moves_out_along_its_normal(normal_m):
    # a long push (one event of ~1 s); the vehicle, still until the event opens, then moves at
    # 0.3 m/s, well within the sliding reach: along the structure every 25 Hz sample is a
    # contact; out along the event's normal it has left once it is 0.05 m out, and the rest
    # would lie in free space (a MuJoCo dock touch's 1 s event followed the vehicle 0.7 m off
    # a pillar)
    always_true = Logistic(("log_peak_g",), (0.0,), (1.0,), (0.0,), -10.0)
    model = EvidenceModel(always_true, always_true, "test")
    t, f, q, pos = flight(impulses=[(3.0, 0.6, 6.0, (0.0, 1.0, 0.0))])
    still = np.tile(pos[0], (t.size, 1))
    (ev,) = run((t, f, q, still), model=model)[0].events
    n = np.asarray(ev.normal)
    tangent = np.cross(n, [0.0, 0.0, 1.0])
    after = t >= ev.t_start_ns
    dt = (t[after] - ev.t_start_ns) / 1e9

    def moving(direction):
        p = still.copy()
        p[after] += 0.3 * dt[:, None] * (direction / np.linalg.norm(direction))
        return (t, f, q, p)

    settings = ContactSettings(sustain_normal_m=normal_m)
    det_s, obs_s = run(moving(tangent), settings=settings, model=model)
    det_o, obs_o = run(moving(n), settings=settings, model=model)
    slid = [o for o in obs_s if o.label == LABEL_SURFACE]
    out = [o for o in obs_o if o.label == LABEL_SURFACE]
    assert len(det_s.events) == len(det_o.events) == 1
    assert len(slid) >= 12 and det_s.stats.left_contact == 0
    if normal_m:
        assert 2 <= len(out) <= 6  # 0.05 m at 0.3 m/s: ~0.17 s of 25 Hz samples
        assert det_o.stats.left_contact == len(slid) - len(out)
        moved = max((np.asarray(o.position) - out[0].position) @ n for o in out)
        assert moved <= normal_m + 1e-9
    else:
        assert len(out) == len(slid)


def test_a_negative_normal_reach_is_refused():
    with pytest.raises(ValueError, match="sustain_normal_m"):
        ContactSettings(sustain_normal_m=-0.1)


def _by_duration(coef=4.0, intercept=-14.5):
    """A model that reads only the duration: a 0.2 s push ~0.99 false, a touch ~0.1."""
    block = Logistic(("log_duration_ms",), (0.0,), (1.0,), (coef,), intercept)
    return EvidenceModel(block, block, "test")


@pytest.mark.parametrize(
    "gap_s, push, odds, raised",
    [
        (1.0, WALL, 4.0, True),  # pushed the same way again: a burst
        (1.0, -WALL, 4.0, False),  # a gust threw it at the wall, the wall pushed back: a touch
        (2.5, WALL, 4.0, False),  # past the window
        (1.0, WALL, 1.0, False),  # off
    ],
)
def test_a_candidate_pushed_the_same_way_soon_after_a_clearly_false_one_is_doubted(
    gap_s, push, odds, raised
):
    t_next = 2.5 + 0.2 + gap_s  # the gust's onset is at 2.5 s, the window counts onsets
    hit = touch(t0=t_next, speed=0.5)
    data = flight(duration=8.0, impulses=[(2.5, 0.2, 1.5, push), *hit["impulses"]], v0=hit["v0"])
    settings = ContactSettings(burst_window_s=2.0, burst_odds=odds)
    det, _ = run(data, settings=settings, model=_by_duration())
    gust, contact = det.events
    assert gust.rejected and gust.p_false_impulse >= settings.reject_p_false
    assert 0.02 < contact.p_false_impulse < 0.5
    expected = burst_raised(contact.p_false_impulse, odds) if raised else contact.p_false_impulse
    assert contact.p_false == pytest.approx(expected)
    assert (contact.p_false > contact.p_false_impulse) == raised


def test_the_burst_context_is_the_earlier_impulse_alone_not_a_chain():
    # a gust at 2.5 s; 1.2 s later a shorter push the same way, doubtful on its own (~0.9) and
    # raised past reject_p_false by the gust (dropped); 1.5 s after that a touch pushed the
    # same way: within 2 s of the second, 2.7 s after the gust. The second was not false on
    # its own impulse, so it is no context and the touch keeps its p_false.
    a = touch(t0=5.2, speed=0.5)
    data = flight(duration=9.0, impulses=[(2.5, 0.2, 1.5, WALL), (3.7, 0.1, 0.8, WALL),
                                          *a["impulses"]], v0=a["v0"])  # fmt: skip
    settings = ContactSettings(burst_window_s=2.0, burst_odds=8.0)
    det, _ = run(data, settings=settings, model=_by_duration())
    assert len(det.events) == 3 and det.events[0].rejected
    second, third = det.events[1], det.events[2]
    assert second.p_false_impulse < settings.reject_p_false <= second.p_false
    assert second.rejected
    assert third.p_false == pytest.approx(third.p_false_impulse)


def test_burst_odds_arithmetic_and_settings():
    assert burst_raised(0.2, 4.0) == pytest.approx(0.5)
    assert burst_raised(0.0, 4.0) == 0.0 and burst_raised(1.0, 4.0) == 1.0
    assert burst_raised(0.3, 1.0) == pytest.approx(0.3)
    with pytest.raises(ValueError, match="burst_odds"):
        ContactSettings(burst_odds=0.5)
    with pytest.raises(ValueError, match="burst_window_s"):
        ContactSettings(burst_window_s=-1.0)


def _lowest_body_point(body: VehicleSettings, r_world_flu: np.ndarray) -> float:
    """Oracle: the lowest of a dense sampling of the body's parts (world z offset, m)."""
    if body.shape == "cylinder":
        return -0.5 * body.height_m  # the cylinder stays vertical whatever the attitude
    ang = np.linspace(0.0, 2 * math.pi, 3600, endpoint=False)
    ring = body.guard_radius_m * np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1)
    rims = (body.rotor_centres()[:, None, :] + ring[None]).reshape(-1, 3)
    corners = np.array(np.meshgrid(*[(-h, h) for h in body.body_half_m])).reshape(3, -1).T
    pts = np.concatenate([rims, corners, body.leg_points()])
    return float((pts @ r_world_flu.T)[:, 2].min())


@pytest.mark.parametrize("body", [VehicleSettings(), VehicleSettings(shape="guards")],
                         ids=["cylinder", "guards"])  # fmt: skip
@pytest.mark.parametrize("roll_deg", [0.0, 35.0, 90.0])
def test_the_floor_clearance_is_the_bodys_lowest_point_above_the_floor(body, roll_deg):
    t, f, q, pos = flight(**touch(speed=0.6))
    roll = math.radians(roll_deg)
    r_x = np.array([[1, 0, 0], [0, math.cos(roll), -math.sin(roll)],
                    [0, math.sin(roll), math.cos(roll)]])  # fmt: skip
    q = np.tile(quat_from_axis_angle([1.0, 0.0, 0.0], roll), (t.size, 1))  # FRD -> NED, yaw 0
    f = f @ r_x  # the same specific force, read by the rolled body: R^T f for each sample
    det, _ = run((t, f, q, pos), ContactSettings(floor_z_m=0.3), body)
    ev = det.events[0]
    on = int(np.searchsorted(t, ev.t_start_ns))
    r_world_flu = ENU_TO_NED @ r_x @ np.diag([1.0, -1.0, -1.0])
    expected = pos[on, 2] + _lowest_body_point(body, r_world_flu) - 0.3
    assert ev.floor_clearance_m == pytest.approx(expected, abs=2e-3)
    assert not ev.at_floor and not ev.rejected  # 0.5-0.9 m above the floor


@pytest.mark.parametrize(
    ("clearance", "at_floor"),
    [(0.0, True), (0.049, True), (0.051, False), (-0.2, True), (-0.25, False), (None, False)],
)
def test_a_candidate_begun_with_the_body_at_the_floor_is_rejected(clearance, at_floor):
    """The cylinder's bottom lies 0.05 m below its centre; the touch's onset sits 1.0 m up
    (``flight``), so the floor is placed to give the body the clearance wanted. Within the
    margin, or below the floor by less than the body's reach (0.206 m), the candidate is
    rejected and makes no observation; farther below, the floor is not this frame's."""
    data = flight(**touch(speed=0.6))
    t, _, _, pos = data
    on = int(np.searchsorted(t, int(1e9 + 3.0 * 1e9)))
    floor = None if clearance is None else float(pos[on, 2]) - 0.05 - clearance
    det, obs = run(data, ContactSettings(floor_z_m=floor))
    ev = det.events[0]
    assert ev.at_floor is at_floor and ev.rejected is at_floor
    assert ev.p_false < 0.5  # the impulse alone says touch: only the floor rejects it
    surface = [o for o in obs if o.label == LABEL_SURFACE]
    assert (len(surface) == 0) is at_floor
    if clearance is None:
        assert math.isnan(ev.floor_clearance_m)
    else:
        assert ev.floor_clearance_m == pytest.approx(clearance, abs=0.01)


@pytest.mark.parametrize(("deg", "line", "upset"), [(90.0, 60.0, True), (45.0, 60.0, False),
                                                   (170.0, 180.0, False)])  # fmt: skip
def test_a_candidate_begun_with_the_body_upset_is_rejected(deg, line, upset):
    # the body lies tilted by ``deg`` from before the touch until after it
    data = _tilted_during(flight(**touch(speed=0.6)), 2.5, 4.0, deg)
    det, obs = run(data, ContactSettings(reject_tilt_deg=line))
    ev = det.events[0]
    assert ev.tilt_deg == pytest.approx(deg, abs=0.5)
    assert ev.upset is upset and ev.rejected is upset
    assert ev.p_false < 0.5  # the impulse alone says touch: only the tilt rejects it
    assert (len([o for o in obs if o.label == LABEL_SURFACE]) == 0) is upset


def test_the_tilt_line_is_checked():
    for bad in (0.0, -10.0, 181.0, math.nan):
        with pytest.raises(ValueError, match="reject_tilt_deg"):
            ContactSettings(reject_tilt_deg=bad)


def test_floor_settings_are_checked():
    for bad in (math.inf, math.nan):  # NaN would also make two equal settings unequal
        with pytest.raises(ValueError, match="floor_z_m"):
            ContactSettings(floor_z_m=bad)
    assert ContactSettings() == ContactSettings()  # "unknown" is None, which equals itself
    with pytest.raises(ValueError, match="floor_margin_m"):
        ContactSettings(floor_margin_m=-0.01)
