"""Scene loading/validation and the geometry oracles (hand-computed distances and normals)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from firmware_bridge.errors import BridgeError
from firmware_bridge.sitl.scene import (
    Box,
    Cylinder,
    Scene,
    SceneError,
    Sphere,
    load_scene,
    named_scenes,
    parse_scene,
)

REGION = {"min": [0, 0, 0], "max": [8, 4, 2]}


def _scene(objects, **extra):
    return {"region": REGION, "objects": objects, **extra}


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"objects": []}, "region"),
        ({"region": {"min": [0, 0], "max": [8, 4, 2]}}, "region.min"),
        ({"region": {"min": [0, 0, 0], "max": [8, 4, "x"]}}, "region.max[2]"),
        ({"region": {"min": [0, 0, 0], "max": [8, 0.1, 2]}}, "region.max[1]"),
        (_scene([{"type": "cone"}]), "objects[0].type"),
        (_scene([{"type": "box", "min": [1, 1, 0], "max": [0.5, 2, 1]}]), "objects[0].max[0]"),
        (_scene([{"type": "cylinder", "center": [4, 2, 0], "radius": -1, "height": 1}]),
         "objects[0].radius"),
        (_scene([{"type": "box", "min": [1, 1, 0], "max": [2, 2, 1]},
                 {"type": "cylinder", "center": [4, 2, 0], "radius": 0.3}]), "objects[1].height"),
        (_scene([{"type": "sphere", "center": [4, 2, float("nan")], "radius": 1}]),
         "objects[0].center[2]"),
        (_scene([], start=[9, 1, 1]), "start"),
        (_scene([{"type": "box", "min": [0, 0, 0], "max": [2, 2, 2]}], start=[1, 1, 1]), "start"),
        ([1, 2], "expected a JSON object"),
    ],
)  # fmt: skip
def test_validation_errors_name_the_field(data, field):
    with pytest.raises(SceneError) as err:
        parse_scene(data)
    assert field in str(err.value)
    assert isinstance(err.value, BridgeError)


def test_load_errors(tmp_path):
    with pytest.raises(SceneError, match="no such named scene"):
        load_scene("no-such-scene")
    bad = tmp_path / "bad.json"
    bad.write_text("{ not json", encoding="utf-8")
    with pytest.raises(SceneError, match="line 1"):
        load_scene(bad)


def test_scenes_around_and_far_from_the_origin():
    yard, dock = load_scene("yard"), load_scene("dock")
    assert yard.region_min == (-4.0, -2.0, 0.0) and yard.region_max == (4.0, 2.0, 2.0)
    assert min(dock.region_min[:2]) <= -10.0 and dock.region_min[0] >= 30.0
    for scene in (yard, dock):
        assert len(scene.objects) >= 3
        kinds = {type(o).__name__ for o in scene.objects}
        assert {"Box", "Cylinder"} <= kinds
        lo, hi = np.array(scene.region_min), np.array(scene.region_max)
        pts = scene.sample_surface(np.random.default_rng(0), 400)
        assert np.all(pts >= lo - 1e-9) and np.all(pts <= hi + 1e-9)  # inside the region
    # Structures on both sides of the origin (negative coordinates).
    xs = [o.closest((0.0, 0.0, 1.0))[1][0] for o in yard.objects]
    assert min(xs) < 0 < max(xs)


def test_named_scenes_load_and_round_trip(tmp_path):
    names = named_scenes()
    assert {"wall", "pillar", "pier", "paper", "yard", "dock"} <= set(names)
    for name in names:
        scene = load_scene(name)
        assert scene.objects
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps(scene.to_dict()), encoding="utf-8")
        again = load_scene(path)
        assert again.objects == scene.objects and again.start == scene.start


def test_box_distance_normal_by_hand():
    b = Box((0.0, 0.0, 0.0), (2.0, 1.0, 1.0))
    d, q, n = b.closest((3.0, 0.5, 0.5))  # in front of the +x face
    assert d == pytest.approx(1.0) and q == pytest.approx((2, 0.5, 0.5)) and n == (1, 0, 0)
    d, q, n = b.closest((3.0, 2.0, 0.5))  # beside the (+x, +y) edge
    assert d == pytest.approx(math.sqrt(2)) and q == pytest.approx((2, 1, 0.5))
    assert n == pytest.approx((math.sqrt(0.5), math.sqrt(0.5), 0))
    d, q, n = b.closest((3.0, 2.0, 2.0))  # corner
    assert d == pytest.approx(math.sqrt(3)) and q == pytest.approx((2, 1, 1))
    d, q, n = b.closest((1.0, 0.5, 0.9))  # inside, nearest face is the top
    assert d == pytest.approx(-0.1) and q == pytest.approx((1, 0.5, 1)) and n == (0, 0, 1)


def test_cylinder_distance_normal_by_hand():
    c = Cylinder((4.0, 2.0, 0.0), 0.5, 1.5)
    d, q, n = c.closest((4.0, 3.0, 1.0))  # side, +y
    assert (
        d == pytest.approx(0.5)
        and q == pytest.approx((4, 2.5, 1))
        and n == pytest.approx((0, 1, 0))
    )
    d, q, n = c.closest((4.3, 2.0, 2.0))  # above the top disc
    assert (
        d == pytest.approx(0.5)
        and q == pytest.approx((4.3, 2, 1.5))
        and n == pytest.approx((0, 0, 1))
    )
    d, q, n = c.closest((5.5, 2.0, 2.5))  # beyond the rim: distance to the circle edge
    assert d == pytest.approx(math.hypot(1.0, 1.0)) and q == pytest.approx((4.5, 2, 1.5))
    d, q, n = c.closest((4.0, 2.4, 0.75))  # inside, nearest is the side
    assert d == pytest.approx(-0.1) and n == pytest.approx((0, 1, 0))


def test_sphere_distance_normal_by_hand():
    s = Sphere((1.0, 1.0, 1.0), 0.5)
    d, q, n = s.closest((1.0, 1.0, 3.0))
    assert (
        d == pytest.approx(1.5)
        and q == pytest.approx((1, 1, 1.5))
        and n == pytest.approx((0, 0, 1))
    )


def test_surface_samples_lie_on_the_surface():
    scene = load_scene("pier")
    pts = scene.sample_surface(np.random.default_rng(3), 400)
    assert pts.shape == (400, 3)
    assert np.max(np.abs(scene.signed_distance(pts))) < 1e-9


def test_surface_samples_are_the_exposed_surface_uniform_by_area():
    # A deck on a pillar, both on the floor, and a free-standing cube: the pillar's top under
    # the deck, the deck's underside over the pillar and every bottom face on the floor are no
    # surface; what is left is sampled in proportion to its area.
    scene = parse_scene(
        _scene(
            [
                {"type": "cylinder", "center": [2, 2, 0], "radius": 0.2, "height": 1},
                {"type": "box", "min": [1, 1, 1], "max": [3, 3, 1.2]},
                {"type": "box", "min": [5, 1, 0], "max": [6, 2, 1]},
            ]
        )
    )
    pts = scene.sample_surface(np.random.default_rng(0), 40000)
    assert pts.shape == (40000, 3)
    assert np.max(np.abs(scene.signed_distance(pts))) < 1e-9
    assert not np.any(pts[:, 2] < 1e-9)  # nothing on the floor
    under_deck = (pts[:, 2] == pytest.approx(1.0)) & (np.hypot(pts[:, 0] - 2, pts[:, 1] - 2) < 0.2)
    assert not under_deck.any()  # neither the pillar's top nor the deck's underside above it
    held = sum(o.holds(pts).astype(int) for o in scene.objects)
    assert np.all(held == 1)
    deck_under = 4 - math.pi * 0.2**2
    areas = {
        "pillar": 2 * math.pi * 0.2 * 1,
        "deck": 4 + deck_under + 8 * 0.2,
        "cube": 5.0,
    }
    total = sum(areas.values())
    on_cube = np.mean(pts[:, 0] >= 5 - 1e-9)
    on_pillar = np.mean((pts[:, 2] < 1 - 1e-9) & (pts[:, 0] < 4))
    assert on_cube == pytest.approx(areas["cube"] / total, abs=0.01)
    assert on_pillar == pytest.approx(areas["pillar"] / total, abs=0.01)
    # the exposed area is the same surface's: no floor faces, nothing under the deck
    assert scene.exposed_area(np.random.default_rng(1), 100_000) == pytest.approx(total, rel=0.01)
    assert parse_scene(_scene([])).exposed_area(np.random.default_rng(1)) == 0.0


def test_primitives_hold_their_inside_and_surface_only():
    box = Box((0, 0, 0), (1, 1, 1))
    cyl = Cylinder((0, 0, 0), 0.5, 1.0)
    ball = Sphere((0, 0, 0), 0.5)
    pts = np.array([[0.5, 0.5, 0.5], [1.0, 0.5, 0.5], [1.01, 0.5, 0.5], [0.0, 0.0, 1.0]])
    assert box.holds(pts).tolist() == [True, True, False, True]
    assert cyl.holds(pts).tolist() == [False, False, False, True]
    assert ball.holds(np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.51]])).tolist() == [True, False]
    assert box.area == pytest.approx(6.0)
    assert cyl.area == pytest.approx(2 * math.pi * 0.5 * 1.5)
    assert ball.area == pytest.approx(math.pi)


def test_signed_distance_vectorised_matches_closest():
    scene = load_scene("paper")
    rng = np.random.default_rng(0)
    pts = rng.uniform(scene.region_min, scene.region_max, (50, 3))
    sd = scene.signed_distance(pts)
    for p, d in zip(pts, sd, strict=True):
        assert d == pytest.approx(scene.closest(tuple(p))[0])
    assert (sd < 0).any() or (sd > 0).all()


@pytest.mark.parametrize(
    "obj",
    [Box((-0.5, 0.2, 0.0), (0.7, 1.0, 1.5)), Cylinder((0.3, -0.2, 0.1), 0.4, 1.2),
     Sphere((0.1, 0.1, 0.8), 0.6)],
    ids=["box", "cylinder", "sphere"],
)  # fmt: skip
def test_each_primitive_signed_distances_match_closest_inside_on_and_outside(obj):
    """The vectorised distances the scorer uses (phantom surface, missing surface) are the
    per-point ``closest`` distances: outside, inside (negative, through the nearest face),
    on the surface, on a cylinder's axis and at a box's centre."""
    rng = np.random.default_rng(7)
    pts = np.concatenate([
        rng.uniform(-1.5, 2.0, (400, 3)),
        obj.area_points(rng, 100),  # on the surface
        obj.area_points(rng, 100) * 0.9 + 0.1 * np.asarray(
            obj.center if hasattr(obj, "center") else np.add(obj.min, obj.max) / 2),  # inside
        [[0.3, -0.2, 0.5], [0.1, 0.6, 0.75]],  # a cylinder's axis, the box's centre
    ])  # fmt: skip
    got = obj.signed_distances(pts)
    want = np.array([obj.closest(tuple(float(x) for x in p))[0] for p in pts])
    np.testing.assert_allclose(got, want, atol=1e-12)
    assert (want < 0).any() and (want > 0).any()
    scene = Scene((-2, -2, -2), (3, 3, 3), (obj, Sphere((1.5, 1.5, 1.5), 0.3)), (0, 0, 0))
    both = [scene.closest(tuple(float(x) for x in p))[0] for p in pts]
    np.testing.assert_allclose(scene.signed_distance(pts), both, atol=1e-12)
    empty = Scene((-2, -2, -2), (3, 3, 3), (), (0, 0, 0))
    assert np.isinf(empty.signed_distance(pts[:3])).all()
