"""Scripted pilots: the survey covers every reachable face of every named scene, safely."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_bridge.sitl.pilots import PilotError, Planner, make_pilot, plan_survey
from firmware_bridge.sitl.scene import load_scene, named_scenes
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
}  # fmt: skip


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_plan_covers_the_reachable_faces(name):
    scene = load_scene(name)
    faces = {t.face for t in plan_survey(scene, R, H)}
    assert faces == EXPECTED[name]
    assert not any(f[1] == "zmin" for f in faces if name != "pier")


@pytest.mark.parametrize("name", named_scenes())
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
