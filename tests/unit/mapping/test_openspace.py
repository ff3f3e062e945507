"""The open-space offset (mapping/openspace.py) and the field the map engine draws with it
(mapping/model.py)."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.contact.detector import Observation
from groundstation.mapping.model import SurfaceModel
from groundstation.mapping.openspace import OpenSpaceOffset
from groundstation.mapping.settings import MappingSettings, SurfaceSettings

S = 1_000_000_000


def _line(d: np.ndarray) -> np.ndarray:
    return np.column_stack([d, np.zeros_like(d), np.zeros_like(d)])


def test_the_offset_is_zero_by_the_anchors_full_beyond_and_a_smooth_step_between():
    b = OpenSpaceOffset(0.7, 0.1, 0.3, np.zeros((1, 3)))
    v = b(_line(np.array([0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 7.0])))
    np.testing.assert_allclose(v[[0, 1, 2]], 0.0)
    np.testing.assert_allclose(v[3], 0.35)  # half-way: the step's midpoint
    np.testing.assert_allclose(v[[4, 5, 6]], 0.7)
    m = b(_line(np.linspace(0.0, 0.4, 401)))
    assert np.all(np.diff(m) >= -1e-12)  # monotone
    assert np.max(np.abs(np.diff(m, 2))) < 1e-3  # no kink (C1) at either end of the rise


def test_the_nearest_anchor_decides_and_no_offset_is_zero_everywhere():
    b = OpenSpaceOffset(1.0, 0.0, 1.0, np.array([[0.0, 0, 0], [2.0, 0, 0]]))
    np.testing.assert_allclose(b(np.array([[1.9, 0.0, 0.0]])), 0.028)  # 0.1 from (2, 0, 0)
    for zero in (OpenSpaceOffset.none(), OpenSpaceOffset(0.0, 0.1, 0.2, np.zeros((2, 3)))):
        assert zero.is_zero
        np.testing.assert_allclose(zero(np.random.default_rng(0).normal(size=(5, 3))), 0.0)
    with pytest.raises(ValueError, match="start_m < end_m"):
        OpenSpaceOffset(0.7, 0.4, 0.4, np.zeros((1, 3)))


def test_a_tile_sees_the_anchors_that_shape_its_offset():
    A = np.array([[0.5, 0.5, 0.5], [1.2, 0.5, 0.5], [3.0, 0.5, 0.5]])
    b = OpenSpaceOffset(0.7, 0.1, 0.4, A)
    near = b.digest_near(np.zeros(3), np.ones(3))
    np.testing.assert_allclose(near, A[:2].ravel())  # 0.2 m outside the box counts, 2 m not
    moved = OpenSpaceOffset(0.7, 0.1, 0.4, A + [0.0, 0.0, 0.01])
    assert not np.array_equal(moved.digest_near(np.zeros(3), np.ones(3)), near)


def test_the_offset_applies_only_in_front_of_the_touches_near_a_point():
    # a 0.8 m cube touched on its six faces: its centre is 0.4 m from every touch but behind
    # all of them (inside), a point 0.4 m out from a face is in front of one
    c = np.full(3, 0.4)
    n = np.vstack([np.eye(3), -np.eye(3)])
    touches = c + 0.4 * n
    b = OpenSpaceOffset(0.7, 0.1, 0.3, touches, touches, n, reach_m=0.8, front_m=0.1)
    inside, outside = c, c + [0.8, 0.0, 0.0]
    np.testing.assert_allclose(b(np.array([inside, outside])), [0.0, 0.7])
    alone = c + [5.0, 0.0, 0.0]  # no touch within reach: open space
    np.testing.assert_allclose(b(alone[None]), 0.7)
    on_face = c + [0.4, 0.0, 0.2]  # on the +x face 0.2 m from its touch: in front of none
    assert b(on_face[None])[0] == pytest.approx(0.0)


def test_deep_behind_the_nearest_touch_is_inside_unless_the_vehicle_was_nearer():
    # a box top touched at z = 0.9 (normal up) and, 0.6 m away, a wall face at y = 0 (normal +y)
    # whose touches the point (0.5 m in front of them) faces; the point is 0.25 m below the top
    top, wall = np.array([[0.0, 0.5, 0.9]]), np.array([[0.0, 0.0, 0.65]])
    faces = np.vstack([top, wall])
    normals = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    p = np.array([[0.0, 0.5, 0.65]])
    shut = OpenSpaceOffset(0.7, 0.1, 0.2, faces, faces, normals, inside_m=0.1)
    assert shut(p)[0] == pytest.approx(0.0)  # inside the box, whatever the wall says
    flown = OpenSpaceOffset(0.7, 0.1, 0.2, faces, faces, normals, inside_m=0.1,
                            free=np.array([[0.0, 0.55, 0.5]]))  # fmt: skip
    assert flown(p)[0] == pytest.approx(0.7)  # the vehicle was there: it is open space
    solid = OpenSpaceOffset(0.7, 0.1, 0.2, faces, faces, normals, inside_m=0.1, solid=True)
    assert solid(p)[0] == pytest.approx(0.0)  # the wall's face is not one of the box's


def test_past_an_edge_of_one_solid_is_open_space_however_deep_behind_the_nearest_touch():
    # a deck touched on its side (y = 0, normal -y) at mid-height and on its top (z = 1.2) 0.6 m
    # in: 0.15 m over the top and 0.25 m in from the side, the point is deeper behind the side
    # touch (its nearest) than 2 d_in, and in front of the top touch, a face of the same solid
    faces = np.array([[0.0, 0.0, 1.1], [0.0, 0.6, 1.2]])
    normals = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, 1.0]])
    p = np.array([[0.0, 0.25, 1.35]])
    kw = dict(reach_m=0.8, front_m=0.1, inside_m=0.1)
    assert OpenSpaceOffset(0.7, 0.1, 0.3, faces, faces, normals, **kw)(p)[0] == 0.0
    past = OpenSpaceOffset(0.7, 0.1, 0.3, faces, faces, normals, solid=True, **kw)
    assert past(p)[0] == pytest.approx(0.7)
    under = np.array([[0.0, 0.25, 1.05]])  # inside the deck: behind both faces
    assert past(under)[0] == pytest.approx(0.0)


def _open_per_point(b: OpenSpaceOffset, X: np.ndarray) -> np.ndarray:
    """The front test of the module docstring written point by point, every touch within reach
    looked at (the oracle for ``OpenSpaceOffset``'s shortcut and pair table)."""
    from groundstation.mapping.openspace import _step
    from groundstation.mapping.training import one_solid

    tree, n = b._faces
    out = np.ones(len(X))
    for m, x in enumerate(X):
        d = np.linalg.norm(tree.data - x, axis=1)
        near = np.argsort(d, kind="stable")[:16]
        near = near[d[near] <= b.reach_m]
        if near.size == 0:
            continue
        front = np.einsum("kd,kd->k", x - tree.data[near], n[near])
        inside = _step((-front[0] - b.inside_m) / b.inside_m)
        if b.solid:
            first = np.repeat(near[:1], near.size)
            one = one_solid(tree.data[first], n[first], tree.data[near], n[near])
            one[0] = False
            inside *= 1.0 - np.max(np.where(one, _step(front / b.front_m), 0.0))
        if b._free is not None:
            d_free = min(np.min(np.linalg.norm(b._free.data - x, axis=1)), b.reach_m)
            inside *= _step((d_free - d[near[0]]) / b.inside_m)
        out[m] = _step(front.max() / b.front_m) * (1.0 - inside)
    return out


def test_the_offset_is_the_per_point_front_test_of_every_touch_within_reach():
    # two boxes and a wall touched on their faces, free samples between them: points in open
    # space, on and behind the faces, past edges, out of reach (the fast path answers most
    # of them from the nearest touch alone, and tests each pair of touches once)
    rng = np.random.default_rng(7)
    faces, normals = [], []
    for centre, half in (([0.0, 0.0, 0.5], 0.4), ([1.3, 0.2, 0.6], 0.3)):
        for ax in range(3):
            for sign in (-1.0, 1.0):
                nrm = np.zeros(3)
                nrm[ax] = sign
                for _ in range(6):
                    p = np.asarray(centre) + half * nrm
                    q = rng.uniform(-half, half, 3)
                    q[ax] = 0.0
                    faces.append(p + q)
                    normals.append(nrm)
    for _ in range(10):  # a thin wall at y = 1.2, touched from -y
        faces.append([rng.uniform(-0.5, 1.5), 1.2, rng.uniform(0.0, 1.2)])
        normals.append([0.0, -1.0, 0.0])
    for x in np.arange(4.0, 6.0, 0.3):  # a deck touched on its side and 0.6 m in on its top
        faces += [[x, 0.0, 1.1], [x + 0.1, 0.6, 1.2]]
        normals += [[0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]
    faces, normals = np.asarray(faces), np.asarray(normals)
    free = rng.uniform([-1.0, -1.0, 0.0], [2.0, 1.0, 1.5], (200, 3))
    X = np.vstack([  # anywhere, round the first box (its edges, inside it), over the deck's edge
        rng.uniform([-1.5, -1.5, -0.5], [2.5, 2.5, 2.0], (3000, 3)),
        rng.uniform([-0.7, -0.7, -0.2], [0.7, 0.7, 1.2], (3000, 3)),
        rng.uniform([4.0, 0.0, 1.0], [6.0, 0.6, 1.6], (2000, 3)),
    ])  # fmt: skip
    wants = []
    for solid in (False, True):
        b = OpenSpaceOffset(0.7, 0.1, 0.3, faces, faces, normals, reach_m=0.8, front_m=0.1,
                            inside_m=0.1, free=free, solid=solid)  # fmt: skip
        wants.append(_open_per_point(b, X))
        np.testing.assert_allclose(b._open(X), wants[-1], rtol=0.0, atol=1e-12)
        # asked in pieces (as a mesh asks, tile by tile), the pair rows worked out for one
        # piece serve the next: the same answer in any order
        b = OpenSpaceOffset(0.7, 0.1, 0.3, faces, faces, normals, reach_m=0.8, front_m=0.1,
                            inside_m=0.1, free=free, solid=solid)  # fmt: skip
        for piece in np.array_split(rng.permutation(len(X)), 7):
            np.testing.assert_allclose(b._open(X[piece]), wants[-1][piece], rtol=0.0, atol=1e-12)
        assert 0.1 < np.mean(wants[-1] == 1.0) < 0.9
        assert np.any((wants[-1] > 0.0) & (wants[-1] < 1.0))
    assert np.sum(wants[1] > wants[0] + 0.01) > 200  # past an edge of one solid: open


def _deck_flight():
    """A deck (z 1.0-1.2, y 0-1) touched on its side face y = 0 at mid-height every 0.3 m and
    on its top 0.6 m in from that edge every 0.5 m; the approach paths are free space."""
    out, i, t = [], 0, 0.0
    up, side = np.array([0.0, 0.0, 1.0]), np.array([0.0, -1.0, 0.0])
    touches = [(np.array([x, 0.6, 1.2]), up) for x in np.arange(0.3, 2.8, 0.5)]
    touches += [(np.array([x, 0.0, 1.1]), side) for x in np.arange(0.4, 2.8, 0.3)]
    for e, (c, n) in enumerate(touches):
        for k in range(5):  # the approach along the normal
            out.append(Observation(i, int(t * S), c + (0.7 - 0.1 * k) * n, 1.0, np.zeros(3),
                                   -1, 0.0))  # fmt: skip
            i, t = i + 1, t + 0.1
        out.append(Observation(i, int(t * S), c, 0.0, n, e, 3.0, p_false=0.02, sigma_m=0.005))
        out.append(Observation(i + 1, int(t * S), c - 0.1 * n, -1.0, n, e, 3.0, p_false=0.02,
                               sigma_m=0.005))  # fmt: skip
        i, t = i + 2, t + 2.0
    return out


NONE, OPEN = MappingSettings(open_offset=0.0), MappingSettings()  # the default: 0.5
NO_SOLID = MappingSettings(open_solid=False)


def _edge_top(model: SurfaceModel) -> float:
    """Median height where the field first turns positive above the deck, 8 cm in from its
    touched side (the truth: its top, 1.2)."""
    z = np.linspace(1.1, 1.6, 101)
    tops = []
    for x in (1.0, 1.5, 2.0):
        f = model.predict(np.column_stack([np.full_like(z, x), np.full_like(z, 0.08), z]))
        tops.append(z[np.argmax(f > 0.0)])
    return float(np.median(tops))


@pytest.fixture(scope="module")
def deck_maps():
    """The deck flight, fitted without the offset, with the default one, and with it fading
    behind the nearest touch past an edge too."""
    obs = _deck_flight()
    maps = [SurfaceModel(s, SurfaceSettings()) for s in (NONE, OPEN, NO_SOLID)]
    for m in maps:
        m.fit(obs, learn_kernel=True)
    return obs, *maps


def test_a_deck_touched_on_its_side_is_not_drawn_above_its_top_with_the_offset(deck_maps):
    _, flat, opened, _ = deck_maps
    assert _edge_top(flat) > 1.27  # the side face carried on up past the edge
    assert _edge_top(opened) < _edge_top(flat) - 0.03
    inside = np.array([[x, y, 1.1] for x in (1.0, 2.0) for y in (0.1, 0.5, 0.8)])
    assert np.all(opened.predict(inside) < -0.1)  # the deck is still a solid


def test_the_offset_leaves_the_fit_and_the_field_at_the_touches_as_they_were(deck_maps):
    obs, a, b, _ = deck_maps
    assert a.lengthscale_ == b.lengthscale_ and a.signal_var_ == b.signal_var_
    np.testing.assert_array_equal(a.posterior_false_, b.posterior_false_)
    C = np.array([o.position for o in obs if o.label == 0.0])
    np.testing.assert_array_equal(b.predict(C), a.predict(C))  # no offset at the evidence
    far = np.array([[1.0, 0.5, 4.0]])  # 2.8 m above every touch: the prior plus the offset
    assert b.predict(far)[0] == pytest.approx(a.predict(far)[0] + OPEN.open_offset)
    high = [float(np.mean(m.mesh().vertices[:, 2] > 1.28)) for m in (a, b)]
    assert high[1] < 0.5 * high[0]  # less drawn above the deck's top (1.2) past the data


def test_past_the_deck_edge_the_offset_holds_deeper_than_d_in_behind_the_side(deck_maps):
    _, _, opened, faded = deck_maps
    high = [float(np.mean(m.mesh().vertices[:, 2] > 1.28)) for m in (faded, opened)]
    assert high[1] < 0.5 * high[0]  # 0.25 m in from the side the top was still drawn high
