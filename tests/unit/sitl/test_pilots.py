"""Scripted pilots: the survey covers every reachable face of every named scene, safely."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_bridge.sitl.pilots import (
    PilotError,
    Planner,
    ScriptPilot,
    _touch_actions,
    make_pilot,
    plan_survey,
)
from firmware_bridge.sitl.scene import load_scene, named_scenes
from firmware_bridge.sitl.vehicle import planning_cylinder, vehicle_settings
from tests.unit.sitl.flight import fly

R, H = 0.2, 0.1

# Faces a survey must touch in each shipped scene (a box resting on the floor cannot be touched
# from below; the pier deck's underside can).
EXPECTED = {
    "wall": {(0, "xmin"), (0, "xmax"), (0, "ymin"), (0, "ymax"), (0, "zmax")},
    "pillar": {(0, "side"), (0, "top")},
    "pier": {(0, "xmin"), (0, "xmax"), (0, "ymin"), (0, "ymax"), (0, "zmax"), (0, "zmin"),
             (1, "side"), (2, "side"), (3, "side")},
    # The paper scene's cylinder top (1.6 m) leaves no room below the 2 m ceiling to approach.
    "paper": {(0, "xmin"), (0, "xmax"), (0, "ymin"), (0, "ymax"), (0, "zmax"), (1, "side")},
    # Around the origin: wall, pillar (top 1.6 m: no room), crate, sphere.
    "yard": {(0, "xmin"), (0, "xmax"), (0, "ymin"), (0, "ymax"), (0, "zmax"), (1, "side"),
             (2, "xmin"), (2, "xmax"), (2, "ymin"), (2, "ymax"), (2, "zmax"), (3, "surface")},
    # Far from the origin (x 30-38, y -14..-10): wall, two pillars, box.
    "dock": {(0, "xmin"), (0, "xmax"), (0, "ymin"), (0, "ymax"), (0, "zmax"), (1, "side"),
             (1, "top"), (2, "side"), (2, "top"), (3, "xmin"), (3, "xmax"), (3, "ymin"),
             (3, "ymax"), (3, "zmax")},
}  # fmt: skip
# The MuJoCo airframe (rims 0.305 m, 0.22 m tall) needs more room: what it can still touch.
EXPECTED_GUARDED = {
    "yard": {(0, "xmin"), (0, "xmax"), (0, "ymin"), (0, "ymax"), (1, "side"), (2, "xmin"),
             (2, "xmax"), (2, "ymin"), (2, "ymax"), (2, "zmax"), (3, "surface")},
    "dock": {(0, "xmin"), (0, "xmax"), (0, "ymin"), (0, "ymax"), (0, "zmax"), (1, "side"),
             (2, "side"), (2, "top"), (3, "ymin"), (3, "ymax"), (3, "zmax")},
}  # fmt: skip
NEW_SCENES = ("yard", "dock")


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_plan_covers_the_reachable_faces(name):
    scene = load_scene(name)
    faces = {t.face for t in plan_survey(scene, R, H)}
    assert faces == EXPECTED[name]
    assert not any(f[1] == "zmin" for f in faces if name != "pier")


@pytest.mark.parametrize("name", sorted(EXPECTED_GUARDED))
def test_plan_for_the_guarded_airframe(name):
    r, h = planning_cylinder(vehicle_settings("mujoco"))
    faces = {t.face for t in plan_survey(load_scene(name), r, h)}
    assert faces == EXPECTED_GUARDED[name]


@pytest.mark.parametrize(
    "name",
    [n if n not in NEW_SCENES else pytest.param(n, marks=pytest.mark.soak) for n in named_scenes()],
)
def test_survey_touches_every_planned_face_and_stays_inside(name):
    scene = load_scene(name)
    pilot = make_pilot("survey", scene, R, H)
    planned = {a[1].face for a in pilot.actions if a[0] == "touch"}
    f = fly(scene, pilot, 400.0, seed=1, until_done=True)
    assert pilot.done, f"survey of {name} did not finish in 400 s"
    assert f.outside_region == 0
    events = f.vehicle.tracker.events
    touched = {(e.object_index, None) for e in events}
    assert {(o, None) for o, _ in planned} <= touched
    assert set(pilot.touched) == planned
    # Every contact is a deliberate touch at speed (no grazing while flying between faces).
    assert all(e.kind == "touch" for e in events), [e for e in events if e.kind != "touch"]
    assert len(events) == sum(1 for a in pilot.actions if a[0] == "touch")
    # Truth contact points lie on the structures.
    pts = np.array([e.point for e in events])
    assert np.max(np.abs(scene.signed_distance(pts))) < 1e-6


def test_path_goes_around_a_structure():
    scene = load_scene("wall")
    planner = Planner(scene, R, H)
    a, b = (3.2, 2.0, 1.0), (5.0, 2.0, 1.0)  # opposite sides of the wall
    assert not planner.segment_free(a, b)
    path = planner.path(a, b)
    assert path and path[-1] == b
    prev = a
    for w in path:
        assert planner.segment_free(prev, w)
        prev = w


def test_unknown_pilot_name():
    with pytest.raises(PilotError, match="unknown pilot script"):
        make_pilot("loop", load_scene("wall"), R, H)


def test_slow_touch_pilot_produces_a_slow_then_a_fast_touch():
    scene = load_scene("pillar")
    f = fly(scene, make_pilot("slow_touch", scene, R, H), 60.0, until_done=True)
    kinds = [e.kind for e in f.vehicle.tracker.events]
    assert kinds == ["slow_touch", "touch"]


@pytest.mark.parametrize(("name", "seed"), [("wall", 0), ("pillar", 1)])
def test_free_pilot_flies_fast_brakes_hard_and_never_touches(name, seed):
    scene = load_scene(name)
    pilot = make_pilot("free", scene, R, H, seed=seed)
    dashes = [a[1] for a in pilot.actions if a[0] == "dash"]
    assert len(dashes) >= 4 and sum(d.speed >= 3.0 for d in dashes) >= len(dashes) / 2
    assert any(len(d.points) == 3 for d in dashes)  # some legs turn at speed
    f = fly(scene, pilot, 200.0, seed=seed, until_done=True)
    assert pilot.done and f.outside_region == 0
    assert f.vehicle.tracker.events == []  # no structure, no floor
    speed = np.linalg.norm(np.diff(f.position, axis=0), axis=1) * 200.0
    assert speed.max() > 3.0
    kinds = [m.kind for m in pilot.maneuvers.records]
    assert kinds.count("brake") == len(dashes) and "turn" in kinds
    brakes = [m for m in pilot.maneuvers.records if m.kind == "brake"]
    for m in brakes:
        # The 50 ms-filtered true deceleration reaches the drawn braking level (0.8-2 G).
        assert m.peak_accel_filtered == pytest.approx(m.target_accel, rel=0.1), m
        assert m.end - m.start < 1.5
    assert max(m.peak_accel_filtered for m in brakes) / 9.80665 > 1.2


def test_varied_pilot_draws_speed_angle_and_pause_from_the_seed():
    scene = load_scene("paper")
    a = make_pilot("varied", scene, R, H, seed=5)
    touches = [x for x in a.actions if x[0] == "touch"]
    assert len(touches) == len(plan_survey(scene, R, H))
    normal_speed, angle = [], []
    for _, tgt, speed in touches:
        cos = -float(np.dot(tgt.direction, tgt.normal))
        normal_speed.append(speed * cos)
        angle.append(np.degrees(np.arccos(min(1.0, cos))))
    assert 0.2 <= min(normal_speed) and max(normal_speed) <= 1.2
    assert max(normal_speed) - min(normal_speed) > 0.5
    assert max(angle) <= 45.0 + 1e-9 and max(angle) > 25.0
    b = make_pilot("varied", scene, R, H, seed=5)
    assert [x[1:] for x in b.actions if x[0] == "touch"] == [x[1:] for x in touches]
    c = make_pilot("varied", scene, R, H, seed=6)
    assert [x[2] for x in c.actions if x[0] == "touch"] != [x[2] for x in touches]


@pytest.mark.parametrize("physics", ["simple", "mujoco"])
@pytest.mark.parametrize("name", NEW_SCENES)
def test_new_scenes_fly_touches_of_three_structures(name, physics):
    """Around and far from the origin: the planner's first touches of three different
    structures are flown and land on the planned faces (full surveys: soak)."""
    scene = load_scene(name)
    r, h = planning_cylinder(vehicle_settings(physics))
    planner = Planner(scene, r, h)
    targets, seen = [], set()
    for tgt in plan_survey(scene, r, h):
        if tgt.face[0] not in seen:
            seen.add(tgt.face[0])
            targets.append(tgt)
    targets = targets[:3]
    assert len(targets) == 3
    acts, here = [("hover", 0.5)], scene.start
    for tgt in targets:
        acts += _touch_actions(planner, here, tgt, 0.8)
        here = tgt.standoff
    pilot = ScriptPilot(scene, acts)
    f = fly(scene, pilot, 120.0, seed=3, until_done=True, physics=physics)
    assert pilot.done and f.outside_region == 0
    assert pilot.touched == [t.face for t in targets]
    events = f.vehicle.tracker.events
    assert [e.object_index for e in events] == [t.face[0] for t in targets]
    pts = np.array([e.onset_point for e in events])
    assert np.max(np.abs(scene.signed_distance(pts))) < 2e-3
