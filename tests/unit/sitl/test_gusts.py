"""Gusts: forces and durations as configured, clusters of gusts at one spot, defaults unchanged."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firmware_bridge.sitl.gusts import GustParams, GustSchedule
from firmware_bridge.sitl.physics import GRAVITY
from firmware_bridge.sitl.pilots import make_pilot
from firmware_bridge.sitl.scene import load_scene
from firmware_bridge.sitl.vehicle import Vehicle, vehicle_settings

REAL_WIND = dict(force=(5.0, 40.0), duration=(0.05, 0.3), rate_per_min=30.0)


def _pulses(params: GustParams, seconds: float, seed: int = 0, dt: float = 0.001):
    """Run a schedule far from structures; return its history and the measured pulses
    (start, end, peak |force| in N on a 1 kg vehicle)."""
    sched = GustSchedule(params, np.random.default_rng(seed), mass=1.0)
    pulses, cur = [], None
    for k in range(int(seconds / dt)):
        t = k * dt
        a = math.sqrt(sum(v * v for v in sched.force(t, math.inf, (0.0, 0.0, 1.0))))
        if a > 0 and cur is None:
            cur = [t, t, a]
        elif a > 0:
            cur[1], cur[2] = t, max(cur[2], a)
        elif cur is not None:
            pulses.append(tuple(cur))
            cur = None
    return sched.history, pulses


def test_forces_and_durations_as_configured():
    params = GustParams.from_forces(1.0, **REAL_WIND)
    history, pulses = _pulses(params, 120.0)
    done = [g for g in history if g.end < 119.0]
    pulses = [q for q in pulses if q[1] < 119.0]
    assert len(done) >= 30 and len(pulses) == len(done)
    for g, (t0, t1, peak) in zip(done, pulses, strict=True):
        assert 5.0 <= g.peak_force_n <= 40.0 and g.peak_force_n == pytest.approx(g.peak)
        assert 0.05 <= g.duration <= 0.3 and g.end == pytest.approx(g.start + g.duration)
        assert t0 == pytest.approx(g.start, abs=0.0011)
        assert t1 - t0 == pytest.approx(g.duration, abs=0.0021)  # the pulse, sampled at 1 kHz
        assert peak == pytest.approx(g.peak_force_n, rel=0.01)  # the half-sine's top
        assert g.cluster is None
    forces = np.array([g.peak_force_n for g in done])
    assert forces.min() < 12 and forces.max() > 30  # the range is covered, not one value


def test_force_range_is_converted_with_the_mass():
    p = GustParams.from_forces(2.0, force=(10.0, 20.0))
    assert (p.peak_min, p.peak_max) == (5.0, 10.0)
    assert (p.duration_min, p.duration_max) == (GustParams().duration_min, 0.06)
    assert GustParams.from_forces(1.0) == GustParams()


@pytest.mark.parametrize("physics", ["simple", "mujoco"])
def test_clusters_of_gusts_within_seconds_at_one_spot(physics):
    scene = load_scene("paper")
    gusts = GustParams.from_forces(
        1.0, force=(5.0, 15.0), duration=(0.05, 0.2), rate_per_min=12.0, cluster_probability=0.6
    )
    vs = vehicle_settings(physics, gusts=gusts)
    v = Vehicle(scene, make_pilot("hover", scene, 0.2, 0.1), 11, vs)
    while v.t < 40.0:
        v.step()
    history = [g for g in v.gusts.history if g.end < v.t - 1.0]
    ids = {g.cluster for g in history if g.cluster is not None}
    assert len(ids) >= 2 and any(g.cluster is None for g in history)
    for cid in ids:
        members = [g for g in history if g.cluster == cid]
        if members[-1] is history[-1]:
            continue  # may still be growing
        assert 3 <= len(members) <= 5
        for a, b in zip(members, members[1:], strict=False):
            assert 0.2 - 1e-9 <= b.start - a.end <= 1.0 + 2e-3  # gap, to the physics step
        assert members[-1].end - members[0].start < 5.0  # several within a few seconds
        pos = np.array([g.position for g in members])
        assert np.max(np.linalg.norm(pos - pos[0], axis=1)) < 0.75  # one spot (pushed, held)
        az = np.array([math.atan2(g.direction[1], g.direction[0]) for g in members])
        spread = np.angle(np.exp(1j * (az - az[0])))
        assert np.max(np.abs(spread)) <= math.radians(60.0) + 1e-9  # the same wind
    # Truth: every member carries its cluster id, isolated gusts None.
    assert all(g.cluster in ids or g.cluster is None for g in history)


def test_default_gusts_draw_nothing_new():
    """Clustering off draws no extra numbers: the default schedule is the old one."""
    a, _ = _pulses(GustParams(rate_per_min=30.0), 60.0, seed=4)
    b, _ = _pulses(GustParams(rate_per_min=30.0, cluster_size=(2, 9)), 60.0, seed=4)
    key = [(g.start, g.peak, g.direction) for g in a]
    assert key == [(g.start, g.peak, g.direction) for g in b]
    assert all(2.5 * GRAVITY <= g.peak <= 4.0 * GRAVITY for g in a)
