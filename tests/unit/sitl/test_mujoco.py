"""The MuJoCo engine: the model's geometry, hover, landing, determinism, free flight, gusts."""

from __future__ import annotations

import hashlib
import math

import mujoco
import numpy as np
import pytest

from firmware_bridge.sitl.airframe import Airframe
from firmware_bridge.sitl.gusts import GustParams
from firmware_bridge.sitl.measure import gust_trial
from firmware_bridge.sitl.pilots import Planner, ScriptPilot, _free_actions
from firmware_bridge.sitl.runner import Simulation
from firmware_bridge.sitl.scene import load_scene
from firmware_bridge.sitl.vehicle import (
    LANDED,
    Vehicle,
    planning_cylinder,
    vehicle_settings,
)
from tests.unit.sitl.flight import fly

G = 9.80665


def _mujoco_vehicle(scene_name="paper", pilot=None, seed=0, **gusts):
    scene = load_scene(scene_name)
    vs = vehicle_settings("mujoco", gusts=GustParams(rate_per_min=0.0, **gusts))
    return Vehicle(scene, pilot, seed, vs)


def test_model_is_the_airframe():
    v = _mujoco_vehicle()
    b = v.body
    a = Airframe()
    m, d = b.model, b.data
    assert b.mass == pytest.approx(a.mass, abs=1e-6)
    names = [m.geom(i).name for i in range(m.ngeom)]
    assert sum(n.startswith("guard") for n in names) == 4 * a.guard_segments
    assert sum(n.startswith("leg") for n in names) == 4 and "body" in names
    assert {m.sensor(i).name for i in range(m.nsensor)} == {"accel", "gyro"}
    assert m.nu == 4 and m.opt.timestep == pytest.approx(0.001)
    # The rims' outline (sampled from the compiled geoms) is the airframe's reach.
    q = m.body("quad").id
    reach = []
    for az in np.radians(np.arange(0.0, 360.0, 1.0)):
        u = np.array([math.cos(az), math.sin(az), 0.0])
        best = 0.0
        for i in range(m.ngeom):
            if m.geom_bodyid[i] != q or not m.geom(i).name.startswith("guard"):
                continue
            half = m.geom_size[i][1]
            axis = d.geom_xmat[i].reshape(3, 3)[:, 2]
            c = d.geom_xpos[i] - d.xpos[q]
            ends = [c + half * axis, c - half * axis]
            best = max(best, max(e @ u for e in ends) + m.geom_size[i][0])
        reach.append(best)
    assert min(reach) == pytest.approx(a.reach_min, abs=0.005)
    assert max(reach) == pytest.approx(a.reach_max, abs=1e-6)
    assert 0.25 <= a.reach_min < a.reach_max <= 0.31


def test_hover_is_still_and_the_imu_reads_gravity():
    scene = load_scene("paper")
    f = fly(scene, ScriptPilot(scene, []), 3.0, seed=4, physics="mujoco")
    assert np.max(np.linalg.norm(f.position - np.array(scene.start), axis=1)) < 1e-3
    assert np.mean(f.accel, axis=0) == pytest.approx([0, 0, -G], abs=0.3)  # FRD, bias ~0.1
    assert not f.vehicle.tracker.events


def test_failsafe_lands_on_the_legs():
    v = _mujoco_vehicle()
    v.manual_control(0, 0, 500, 0)
    while v.t < 12.0:
        v.step()
    assert v.mode == LANDED
    kinds = [e.kind for e in v.tracker.events]
    assert kinds and set(kinds) == {"ground"}
    assert {e.body_part for e in v.tracker.events} == {"leg"}
    assert v.body.z == pytest.approx(v.body.airframe.bottom, abs=0.01)  # resting on its feet


def _digest(seed: int) -> str:
    """Hash of every output of a 5.5 s flight with a touch (at ~5.2 s) and gusts."""
    vs = vehicle_settings("mujoco", gusts=GustParams(rate_per_min=20.0))
    sim = Simulation(load_scene("wall"), "script:survey", seed=seed, duration=5.5, vehicle=vs)
    h = hashlib.sha256()
    for item in sim.outputs():
        h.update(item.t_ns.to_bytes(8, "little") + item.channel.encode() + item.data)
    return h.hexdigest()


def test_same_seed_same_bytes_different_seed_differs():
    first = _digest(7)
    assert _digest(7) == first
    assert _digest(8) != first


def test_free_flight_never_touches_anything():
    scene = load_scene("pillar")
    vs = vehicle_settings("mujoco")
    planner = Planner(scene, *planning_cylinder(vs))
    acts, _ = _free_actions(planner, np.random.default_rng([5, 2]), legs=3)
    pilot = ScriptPilot(scene, [("hover", 0.5), *acts])
    f = fly(scene, pilot, 60.0, seed=5, until_done=True, physics="mujoco")
    assert pilot.done and f.outside_region == 0
    assert f.vehicle.tracker.events == []
    brakes = [m for m in pilot.maneuvers.records if m.kind == "brake"]
    assert len(brakes) == 3
    for m in brakes:
        assert 0.75 * m.target_accel <= m.peak_accel_filtered <= 1.15 * m.target_accel, m


@pytest.mark.parametrize("physics", ["simple", "mujoco"])
@pytest.mark.parametrize(("force", "duration"), [(5.0, 0.1), (15.0, 0.2), (40.0, 0.05)])
def test_gust_force_and_duration_as_configured(physics, force, duration):
    trial, gust = gust_trial(physics, force, duration)
    assert gust.peak_force_n == pytest.approx(force) and gust.duration == pytest.approx(duration)
    # The body feels the gust: its true acceleration peaks at about F / m (the controller only
    # starts to push back within the pulse).
    assert trial.truth_raw_peak == pytest.approx(force / 1.0, rel=0.15)
    assert not trial.vehicle.tracker.events


def test_mujoco_is_pinned():
    assert mujoco.__version__ == "4.0.0"  # results (and SITL bytes) vary between releases
