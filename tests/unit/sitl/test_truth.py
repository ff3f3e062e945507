"""Truth a detector benchmark can score by: approach speed and angle, contact point and body
part, rebound; gusts with force, duration and cluster; manoeuvres; engine and airframe."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from firmware_bridge.sitl.gusts import GustParams
from firmware_bridge.sitl.measure import touch_trial
from firmware_bridge.sitl.runner import Simulation
from firmware_bridge.sitl.scene import load_scene
from firmware_bridge.sitl.vehicle import vehicle_settings

ENGINES = ["simple", "mujoco"]
RESTITUTION = {"simple": 0.5, "mujoco": 0.4}


def aimed_touch(physics: str, speed: float, angle_deg: float = 0.0, azimuth: float = 0.0):
    """(vehicle, event) of one touch of the wall's -x face (see measure.touch_trial)."""
    trial, ev = touch_trial(physics, speed, angle_deg, azimuth)
    return trial.vehicle, ev


@pytest.mark.parametrize("physics", ENGINES)
@pytest.mark.parametrize("speed", [0.4, 1.0])
def test_touch_at_a_known_speed_is_in_the_truth(physics, speed):
    v, ev = aimed_touch(physics, speed)
    assert ev.kind == "touch"
    assert ev.normal_speed == pytest.approx(speed, rel=0.1)
    assert ev.approach_angle_deg < 6.0
    assert ev.onset_normal == pytest.approx((-1.0, 0.0, 0.0), abs=1e-6)
    # The true contact point is on the wall's face, in front of the vehicle.
    p = np.array(ev.onset_point)
    assert p[0] == pytest.approx(4.0, abs=1e-3) and abs(p[1] - 2.0) < 0.35
    assert abs(v.scene.signed_distance(p[None])[0]) < 2e-3
    # Where on the body: the front (body x points at the wall, yaw 0).
    body = np.array(ev.body_point)
    a = v.body.airframe
    assert a.reach_min - 0.02 <= body[0] <= a.reach_max + 1e-6 and abs(body[2]) < 0.05
    # It bounces back: restitution as the contact model says.
    assert ev.rebound_speed > 0
    assert ev.restitution == pytest.approx(RESTITUTION[physics], abs=0.1)


@pytest.mark.parametrize("physics", ENGINES)
def test_a_45_degree_approach(physics):
    _, ev = aimed_touch(physics, 0.5, 45.0)
    assert ev.approach_angle_deg == pytest.approx(45.0, abs=4.0)
    assert ev.normal_speed == pytest.approx(0.5, rel=0.12)
    assert ev.approach_speed == pytest.approx(0.5 * math.sqrt(2), rel=0.12)
    assert ev.onset_point[0] == pytest.approx(4.0, abs=1e-3)


def test_truth_document_has_gusts_manoeuvres_engine_and_airframe():
    scene = load_scene("pillar")
    gusts = GustParams.from_forces(
        1.0, force=(5, 15), duration=(0.05, 0.2), rate_per_min=20, cluster_probability=0.5
    )
    sim = Simulation(scene, "script:free", seed=3, duration=40.0,
                     vehicle=vehicle_settings(gusts=gusts))  # fmt: skip
    for _ in sim.outputs():
        pass
    doc = json.loads(json.dumps(sim.truth()))  # JSON-ready
    assert doc["schema"] == "sitl-truth/1" and doc["physics"]["engine"] == "simple"
    assert doc["settings"]["gust_force_n"] == [5, 15]
    assert doc["airframe"]["layout"] == "cylinder" and doc["airframe"]["reach_max"] == 0.2
    gusts_doc = doc["gusts"]
    assert gusts_doc and all(5 <= g["peak_force_n"] <= 15 for g in gusts_doc)
    assert all(g["end"] == pytest.approx(g["start"] + g["duration"]) for g in gusts_doc)
    assert any(g["cluster"] is not None for g in gusts_doc)
    as_events = [c for c in doc["contacts"] if c["kind"] == "gust"]
    assert [c["cluster"] for c in as_events] == [g["cluster"] for g in gusts_doc]
    assert not [c for c in doc["contacts"] if c["kind"] != "gust"]  # free flight: no contact
    kinds = {m["kind"] for m in doc["maneuvers"]}
    assert {"accelerate", "brake"} <= kinds
    for m in doc["maneuvers"]:
        assert m["end"] > m["start"] and m["peak_accel_filtered_g"] > 0.3


def test_contacts_after_a_gust_name_it():
    from firmware_bridge.sitl.gusts import Gust
    from firmware_bridge.sitl.truth import ContactEvent, ContactTracker

    tracker = ContactTracker()
    pilot_touch = ContactEvent("touch", 3.0, 3.02, 0, (1, 0, 0), (-1, 0, 0), (0.8, 0, 0), 1, 9)
    pushed = ContactEvent("touch", 10.4, 10.42, 0, (1, 0, 0), (-1, 0, 0), (0.8, 0, 0), 3, 30)
    tracker.events = [pilot_touch, pushed]
    gusts = [Gust(1.0, 0.1, 10.0, (1, 0, 0)), Gust(10.0, 0.2, 40.0, (1, 0, 0))]
    events = tracker.all_events(gusts)
    assert pilot_touch.gust is None and pushed.gust == 1
    assert [e.kind for e in events] == ["gust", "touch", "gust", "touch"]
