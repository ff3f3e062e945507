"""Truth scores of a replay without a mesh (``pipeline/scoring.py``)."""

from __future__ import annotations

import dataclasses
import math

import pytest

from groundstation.pipeline.scoring import surface_scores


def _grid_faces(n):
    """Triangles of an n x n grid of vertices numbered row by row."""
    import numpy as np

    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            faces += [[a, b, d], [a, d, c]]
    return np.asarray(faces)


def test_without_a_mesh_all_touched_surface_is_missing_and_an_untouched_flight_misses_none():
    touched = {"contacts": [{"kind": "touch", "point": [1.0, 0.0, 1.0], "start": 3.0}]}
    gusts_only = {"contacts": [{"kind": "gust", "point": None, "start": 3.0}]}
    assert surface_scores(None, touched)["missing_share"] == 1.0
    assert math.isnan(surface_scores(None, gusts_only)["missing_share"])
    assert math.isnan(surface_scores(None, {"contacts": []})["missing_share"])
    assert math.isnan(surface_scores(None, touched)["chamfer_m"])


def test_near_missing_counts_only_the_surface_around_the_touches():
    import numpy as np

    from groundstation.mapping.surface import SurfaceMesh

    # a wall x = 1 (a thin box), touched once at (1, 0, 1); the mesh is a 0.5 m square on the
    # wall around the touch: all of the surface within 0.2 m is there, not all within 0.5 m
    scene = {
        "region": {"min": [-1, -2, 0], "max": [3, 2, 2]},
        "objects": [{"type": "box", "min": [1.0, -2.0, 0.0], "max": [1.2, 2.0, 2.0]}],
    }
    truth = {"scene": scene, "contacts": [{"kind": "touch", "point": [1.0, 0.0, 1.0]}]}
    n = 11
    yy, zz = np.meshgrid(np.linspace(-0.25, 0.25, n), np.linspace(0.75, 1.25, n))
    v = np.column_stack([np.ones(n * n), yy.ravel(), zz.ravel()])
    faces = _grid_faces(n)
    mesh = SurfaceMesh(v, faces, np.tile([-1.0, 0.0, 0.0], (n * n, 1)))
    s = surface_scores(mesh, truth)
    assert s["missing_share_near"] < 0.02
    assert s["missing_share"] > 0.3  # the wall's other face and the disk beyond 0.25 m
    # the touched surface within 0.2 m: a disc of 0.2 m on the wall's face, and the part of it
    # missing; without a mesh all of it is missing
    assert s["touched_area_near_m2"] == pytest.approx(math.pi * 0.2**2, rel=0.1)
    assert s["missing_area_near_m2"] == pytest.approx(
        s["missing_share_near"] * s["touched_area_near_m2"]
    )
    bare = surface_scores(None, truth)
    assert bare["missing_area_near_m2"] == bare["touched_area_near_m2"] > 0.1
    untouched = surface_scores(None, {"scene": scene, "contacts": []})
    assert untouched["touched_area_near_m2"] == 0.0
    assert math.isnan(untouched["missing_area_near_m2"])


def test_the_surface_near_touches_the_detector_missed_is_counted_apart():
    import numpy as np

    from groundstation.mapping.surface import SurfaceMesh
    from groundstation.pipeline.scoring import DetectedEvent, reported_touches, score

    # a wall x = 1 touched at y = 0 (reported by an event) and at y = 1.5 (no event: the
    # detector missed it); the map drew a 0.5 m square round the first only
    scene = {
        "region": {"min": [-1, -2, 0], "max": [3, 2, 2]},
        "objects": [{"type": "box", "min": [1.0, -2.0, 0.0], "max": [1.2, 2.0, 2.0]}],
    }
    truth = {
        "scene": scene,
        "contacts": [
            {"kind": "touch", "start": 1.0, "end": 1.05, "point": [1.0, 0.0, 1.0]},
            {"kind": "touch", "start": 9.0, "end": 9.05, "point": [1.0, 1.5, 1.0]},
        ],
    }
    events = [DetectedEvent(0, int(1e9), points=((1.0, 0.0, 1.0),))]
    np.testing.assert_allclose(reported_touches(events, truth), [[1.0, 0.0, 1.0]])
    n = 11
    yy, zz = np.meshgrid(np.linspace(-0.25, 0.25, n), np.linspace(0.75, 1.25, n))
    v = np.column_stack([np.ones(n * n), yy.ravel(), zz.ravel()])
    mesh = SurfaceMesh(v, _grid_faces(n), np.tile([-1.0, 0.0, 0.0], (n * n, 1)))
    s = score(mesh, events, truth)
    assert s["missing_share_near"] == pytest.approx(0.5, abs=0.05)  # the missed touch's disc
    assert s["missing_share_near_detected"] < 0.02  # what the map was told, it drew
    assert s["touched_area_near_detected_m2"] == pytest.approx(math.pi * 0.2**2, rel=0.1)
    assert s["missing_area_near_detected_m2"] < 0.01 * s["touched_area_near_detected_m2"] + 1e-9
    none = score(None, [], truth)  # no event: nothing was reported, nothing to judge the map on
    assert math.isnan(none["missing_share_near_detected"])
    assert none["touched_area_near_detected_m2"] == 0.0
    bare = score(None, events, truth)  # reported and not drawn: all of it missing
    assert bare["missing_share_near_detected"] == 1.0


def test_a_mesh_on_the_floor_is_real_surface_and_one_below_it_is_phantom():
    import numpy as np

    from groundstation.mapping.surface import SurfaceMesh

    # a 1 m square drawn at height z0 far from the only structure: on the floor (z = 0, the
    # region's bottom, which both engines' drones can touch) it exists; 0.5 m below, it does not
    scene = {
        "region": {"min": [-1, -2, 0], "max": [3, 2, 2]},
        "objects": [{"type": "box", "min": [1.0, -2.0, 0.0], "max": [1.2, 2.0, 2.0]}],
    }
    truth = {"scene": scene, "contacts": [{"kind": "touch", "point": [1.0, 0.0, 1.0]}]}
    n = 11
    xx, yy = np.meshgrid(np.linspace(-0.9, 0.1, n), np.linspace(-1.0, 0.0, n))
    faces = _grid_faces(n)

    def square(z0):
        v = np.column_stack([xx.ravel(), yy.ravel(), np.full(n * n, z0)])
        return SurfaceMesh(v, faces, np.tile([0.0, 0.0, 1.0], (n * n, 1)))

    assert surface_scores(square(0.02), truth)["phantom_max_patch_m2"] == 0.0
    below = surface_scores(square(-0.5), truth)
    assert below["phantom_max_patch_m2"] > 0.9
    (where,) = below["phantom_patches"]  # one patch, listed with where it lies
    assert abs(where["centre"][2] + 0.5) < 1e-9 and where["area_m2"] > 0.9
    assert below["mesh_to_truth_median_m"] > 0.4


def test_touches_placed_off_the_surface_are_counted_apart_from_those_on_it():
    import numpy as np

    from groundstation.pipeline.scoring import DetectedEvent, false_positive_scores

    # a wall x = 1 and four touches; the detector put the third's contacts 0.3 m in front of
    # the wall (a mislocated touch: drawing it would draw phantom surface), and gave the
    # fourth no contact points (counted on the surface)
    scene = {
        "region": {"min": [-1, -2, 0], "max": [3, 2, 2]},
        "objects": [{"type": "box", "min": [1.0, -2.0, 0.0], "max": [1.2, 2.0, 2.0]}],
    }
    starts = [1.0, 2.0, 3.0, 4.0]
    truth = {
        "scene": scene,
        "contacts": [
            {"kind": "touch", "start": t, "end": t + 0.05, "point": [1.0, 0.0, 1.0]} for t in starts
        ],
    }
    on = ((1.01, 0.0, 1.0), (0.99, 0.05, 1.0))
    off = ((0.7, 0.0, 1.0), (0.72, 0.1, 1.0), (1.0, 0.0, 1.0))  # median 0.28 m off
    events = [
        DetectedEvent(0, int(1e9), flagged=True, points=on),
        DetectedEvent(1, int(2e9), flagged=False, points=on),
        DetectedEvent(2, int(3e9), flagged=True, points=off),
        DetectedEvent(3, int(4e9), flagged=False),
    ]
    s = false_positive_scores(events, truth)
    assert s["touch_events_flagged"] == 0.5
    assert s["events_touch_mislocated"] == 1
    assert s["touch_events_flagged_on_surface"] == 1 / 3
    assert s["mislocated_touches_flagged"] == 1.0
    # at a looser limit nothing is mislocated and the split is the plain share
    loose = false_positive_scores(events, truth, mislocated_m=0.5)
    assert loose["events_touch_mislocated"] == 0
    assert loose["touch_events_flagged_on_surface"] == 0.5
    assert np.isnan(loose["mislocated_touches_flagged"])


def test_slow_touches_are_scored_apart_from_touches_and_gusts():
    import numpy as np

    from groundstation.pipeline.scoring import DetectedEvent, false_positive_scores

    # a touch, two slow touches (one flagged) and a gust: the slow touches are real contacts
    # but not ``touch`` events, so they get their own share and leave the others as they are
    kinds = [("touch", 1.0), ("slow_touch", 2.0), ("slow_touch", 3.0), ("gust", 4.0)]
    truth = {"contacts": [{"kind": k, "start": t, "end": t + 0.3} for k, t in kinds]}
    flagged = [False, True, False, True]
    events = [DetectedEvent(i, int(t * 1e9), flagged=f) for i, ((_, t), f) in
              enumerate(zip(kinds, flagged, strict=True))]  # fmt: skip
    s = false_positive_scores(events, truth)
    assert s["events_slow_touch"] == 2 and s["slow_touch_events_flagged"] == 0.5
    assert s["touch_events_flagged"] == 0.0 and s["gust_events_flagged"] == 1.0
    assert s["fp_precision"] == 0.5  # the flagged slow touch is a wrong flag
    none = false_positive_scores(events[:1], truth)
    assert none["events_slow_touch"] == 0 and np.isnan(none["slow_touch_events_flagged"])


def _wall_truth(*more):
    """Truth of a wall at x = 1-1.2 m touched at (1, 0, 1) at t = 1 s, a gust at t = 3 s, and
    ``more`` contacts, in start order."""
    scene = {
        "region": {"min": [-1, -2, 0], "max": [3, 2, 2]},
        "objects": [{"type": "box", "min": [1.0, -2.0, 0.0], "max": [1.2, 2.0, 2.0]}],
    }
    contacts = [
        {"kind": "touch", "start": 1.0, "end": 1.05, "point": [1.0, 0.0, 1.0]},
        {"kind": "gust", "start": 3.0, "end": 3.2},
        *more,
    ]
    return {"scene": scene, "contacts": sorted(contacts, key=lambda c: c["start"])}


def test_a_phantom_patch_names_the_kept_contacts_that_drew_it():
    from groundstation.pipeline.scoring import DetectedEvent, patch_sources

    # a wall x = 1 touched at t = 1 and 2, a gust at t = 3 and a floor impact at t = 4; one
    # patch in front of the wall at x 0.75-0.85 (the blob a contact at x 0.7 would draw)
    truth = _wall_truth(
        {"kind": "touch", "start": 2.0, "end": 2.05, "point": [1.0, 0.5, 1.0]},
        {"kind": "ground", "start": 4.0, "end": 4.05, "point": [0.5, 0.0, 0.0]},
    )
    patch = {"area_m2": 0.2, "centre": [0.8, 0.0, 1.0], "lo": [0.75, -0.2, 0.8],
             "hi": [0.85, 0.2, 1.2], "farthest_m": 0.25}  # fmt: skip
    on_wall = DetectedEvent(0, int(1e9), points=((1.0, 0.0, 1.0), (0.99, 0.05, 1.0)))
    far_touch = DetectedEvent(1, int(2e9), points=((1.0, 1.5, 1.0),))  # 1.3 m from the patch
    off_wall = DetectedEvent(1, int(2e9), points=((0.75, 0.1, 1.0),))  # placed 0.25 m off
    gust = DetectedEvent(2, int(3e9), points=((0.7, 0.0, 1.0),))
    floor = DetectedEvent(3, int(4e9), points=((0.6, 0.0, 0.6),))

    def cause(*events):
        (p,) = patch_sources([patch], list(events), truth)
        assert {k: p[k] for k in patch} == patch  # the patch itself is kept as it was
        return p["cause"], [(e["id"], e["kind"], e["flagged"]) for e in p["events"]]

    assert cause(on_wall, far_touch) == ("touches", [(0, "touch", False)])
    assert cause(on_wall, off_wall)[0] == "touch placed off the surface"
    assert cause(on_wall, off_wall, gust) == (
        "false contact",
        [(0, "touch", False), (1, "touch", False), (2, "gust", False)],
    )
    # a flagged gust is left out of the map: listed, but it drew nothing
    flagged = dataclasses.replace(gust, flagged=True)
    assert cause(on_wall, flagged) == ("touches", [(0, "touch", False), (2, "gust", True)])
    assert cause(flagged)[0] == "no kept contact"
    assert cause(far_touch)[0] == "no kept contact"
    # the floor is real surface: an impact drawn 0.6 m above it is a false contact here
    assert cause(on_wall, floor)[0] == "false contact"
    # a detected event no truth contact explains (a detector false alarm) too
    stray = DetectedEvent(4, int(9e9), points=((0.5, 0.0, 1.0),))
    assert cause(on_wall, stray) == ("false contact", [(0, "touch", False), (4, None, False)])


def test_score_says_what_drew_the_largest_patch():
    import numpy as np

    from groundstation.mapping.surface import SurfaceMesh
    from groundstation.pipeline.scoring import DetectedEvent, score

    # a 1 m square 0.25 m in front of a wall touched at t = 1, where a gust's contact lies
    truth = _wall_truth()
    n = 11
    yy, zz = np.meshgrid(np.linspace(-0.5, 0.5, n), np.linspace(0.5, 1.5, n))
    v = np.column_stack([np.full(n * n, 0.75), yy.ravel(), zz.ravel()])
    mesh = SurfaceMesh(v, _grid_faces(n), np.tile([-1.0, 0.0, 0.0], (n * n, 1)))
    touch = DetectedEvent(0, int(1e9), points=((1.0, 0.0, 1.0),))
    gust = DetectedEvent(1, int(3e9), points=((0.7, 0.0, 1.0),))
    out = score(mesh, [touch, gust], truth)
    assert out["phantom_max_patch_m2"] > 0.9
    assert out["phantom_max_patch_cause"] == "false contact"
    assert [e["id"] for e in out["phantom_patches"][0]["events"]] == [0, 1]
    kept = score(mesh, [touch, dataclasses.replace(gust, flagged=True)], truth)
    assert kept["phantom_max_patch_cause"] == "touches"  # the wall's touch 0.25 m behind it
    assert score(None, [touch], truth)["phantom_max_patch_cause"] is None


def test_a_later_event_after_a_touch_ended_is_its_echo_not_a_touch():
    import numpy as np

    from groundstation.pipeline.scoring import (
        DetectedEvent,
        false_positive_scores,
        match_events,
        patch_sources,
    )

    # a 50 ms touch at t = 1 detected at its onset (event 0); the vehicle's reaction detected
    # 0.2 s after the touch ended (event 1, placed 0.3 m off the wall, flagged); a slide at
    # t = 5-5.6 s detected twice while it lasts (events 2 and 3); a gust at 3 s, detected twice
    truth = _wall_truth(
        {"kind": "touch", "start": 5.0, "end": 5.6, "point": [1.0, 0.5, 1.0]},
    )
    on = ((1.0, 0.0, 1.0),)
    echo = DetectedEvent(1, int(1.25e9), flagged=True, points=((0.7, 0.0, 1.0),))
    events = [
        DetectedEvent(0, int(1.003e9), points=on),
        echo,
        DetectedEvent(2, int(5.01e9), points=on),
        DetectedEvent(3, int(5.4e9), points=on),
        DetectedEvent(4, int(3.0e9), flagged=True),
        DetectedEvent(5, int(3.3e9), flagged=True),
    ]
    m = match_events(events, truth)
    assert m == {0: (0, "touch"), 1: (0, "echo"), 2: (2, "touch"), 3: (2, "touch"),
                 4: (1, "gust"), 5: (1, "gust")}  # fmt: skip
    s = false_positive_scores(events, truth)
    assert s["events_echo"] == 1 and s["echo_events_flagged"] == 1.0
    assert s["touch_events_flagged"] == 0.0 and s["events_touch"] == 3
    assert s["events_touch_mislocated"] == 0  # the echo is not a touch placed off the wall
    assert s["detection_recall"] == 1.0
    # within ECHO_AFTER_S of the touch's end it is still the touch, and alone it is the touch
    assert match_events([events[0], dataclasses.replace(echo, t_start_ns=int(1.09e9))], truth)[
        1
    ] == (0, "touch")
    assert match_events([echo], truth) == {1: (0, "touch")}
    # kept, an echo draws its patch as a false contact
    patch = {"area_m2": 0.2, "centre": [0.8, 0.0, 1.0], "lo": [0.75, -0.2, 0.8],
             "hi": [0.85, 0.2, 1.2], "farthest_m": 0.25}  # fmt: skip
    (p,) = patch_sources([patch], [events[0], dataclasses.replace(echo, flagged=False)], truth)
    assert p["cause"] == "false contact"
    assert np.isnan(false_positive_scores(events[:1], truth)["echo_events_flagged"])


def test_a_stricter_mask_trades_phantom_surface_for_missing_surface():
    import numpy as np

    from groundstation.errors import InputDataError
    from groundstation.mapping.surface import SurfaceMesh, confident_part
    from groundstation.pipeline.scoring import CURVE_KEYS, mask_curve

    # the wall x = 1 touched at (1, 0, 1), meshed on its face over y, z in [-0.5, 0.5] x
    # [0.5, 1.5] with a std that grows away from the touch, and a 0.25 m x 1 m flap 0.3 m in
    # front of it (phantom surface), the least certain part of the mesh
    scene = {
        "region": {"min": [-1, -2, 0], "max": [3, 2, 2]},
        "objects": [{"type": "box", "min": [1.0, -2.0, 0.0], "max": [1.2, 2.0, 2.0]}],
    }
    truth = {"scene": scene, "contacts": [{"kind": "touch", "point": [1.0, 0.0, 1.0]}]}
    n = 21
    yy, zz = np.meshgrid(np.linspace(-0.5, 0.5, n), np.linspace(0.5, 1.5, n))
    wall = np.column_stack([np.ones(n * n), yy.ravel(), zz.ravel()])
    flap = wall.copy()
    flap[:, 0] = 0.7
    flap[:, 1] = 0.25 + (flap[:, 1] + 0.5) / 4.0  # y in [0.25, 0.5]
    v = np.vstack([wall, flap])
    faces = np.vstack([_grid_faces(n), len(wall) + _grid_faces(n)])
    dist = np.linalg.norm(v - [1.0, 0.0, 1.0], axis=1)
    std = np.where(v[:, 0] < 0.9, 0.55, 0.45 * dist / dist.max())
    mesh = SurfaceMesh(v, faces, np.tile([-1.0, 0.0, 0.0], (len(v), 1)), std)
    full = surface_scores(mesh, truth)
    assert full["phantom_max_patch_m2"] == pytest.approx(0.25, rel=0.05)  # the flap
    rows = mask_curve(mesh, truth, 1.0, (0.5, 0.05))
    assert [r["max_std_fraction"] for r in rows] == [0.5, 0.05]
    assert set(rows[0]) == {"max_std_fraction", *CURVE_KEYS}
    assert rows[0]["phantom_max_patch_m2"] == 0.0  # the flap (std 0.55) is gone at 0.5
    assert rows[0]["missing_share_near"] == pytest.approx(full["missing_share_near"])
    # at 0.05 only the wall within 0.08 m of the touch is kept: touched surface goes missing
    assert rows[1]["missing_share"] > rows[0]["missing_share"] + 0.1
    assert rows[1]["missing_share_near"] > rows[0]["missing_share_near"]
    # in sigma_f units: the same curve for a kernel of prior std 2 and a std twice as large
    doubled = SurfaceMesh(v, faces, mesh.normals, 2.0 * std)
    assert mask_curve(doubled, truth, 2.0, (0.5,))[0] == rows[0]
    # one sample of the mesh and the truth serves every row: a mask that keeps every face
    # scores the mesh exactly as surface_scores does
    loose = mask_curve(mesh, truth, 1.0, (1.0,))[0]
    assert loose == {"max_std_fraction": 1.0, **{k: full[k] for k in CURVE_KEYS}}
    kept = surface_scores(confident_part(mesh, 0.5), truth)
    for k in ("missing_share", "missing_share_near", "chamfer_m", "mesh_to_truth_median_m"):
        assert rows[0][k] == pytest.approx(kept[k], abs=0.01)  # a fresh sample agrees
    assert rows[0]["phantom_area_m2"] == kept["phantom_area_m2"]
    assert mask_curve(mesh, {"contacts": []}, 1.0, (0.5,)) == []
    assert mask_curve(SurfaceMesh(v, faces, mesh.normals), truth, 1.0, (0.5,)) == []
    with pytest.raises(InputDataError, match="sigma_f"):
        mask_curve(mesh, truth, float("nan"), (0.5,))
