"""3D synthetic observation sets: sizes, geometry against the scene's truth, determinism."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_bridge.sitl.scene import load_scene
from groundstation.bench import scenes3d
from groundstation.bench.shapes2d import (
    CONTACT,
    EXTERNAL,
    FALSE_CONTACT,
    FALSE_INTERNAL,
    INTERNAL,
)
from groundstation.errors import ConfigError


@pytest.fixture(scope="module")
def paper():
    return scenes3d.paper3d(0)


@pytest.fixture(scope="module")
def session():
    return scenes3d.session40(0)


def test_vectorised_sdf_equals_the_scene_reference():
    scene = load_scene("paper")
    pts = np.random.default_rng(1).uniform([0, 0, 0], [8, 4, 2], (300, 3))
    np.testing.assert_allclose(
        scenes3d.scene_sdf(scene, pts), scene.signed_distance(pts), atol=1e-12
    )


def test_paper3d_size_labels_and_geometry(paper):
    n = len(paper.y)
    assert 2300 <= n <= 2700  # ~2,300 plus the external points of the gusts' paths
    c = paper.counts()
    assert c["contact"] == c["internal"] == 900 and 450 <= c["external"] <= 800
    # 2 % of 900 isolated gusts plus 3 clusters of 6-10: 18 + 18..30, give or take the draw
    assert 25 <= c["false_contact"] == c["false_internal"] <= 70
    expect = np.select(
        [paper.kind == EXTERNAL, np.isin(paper.kind, (INTERNAL, FALSE_INTERNAL))], [1.0, -1.0], 0.0
    )
    np.testing.assert_array_equal(paper.y, expect)
    d = paper.sdf(paper.X)
    assert np.abs(d[paper.kind == CONTACT]).mean() < 0.03  # ~1.5 cm noise
    assert np.abs(d[paper.kind == CONTACT]).max() < 0.1
    assert -0.13 < d[paper.kind == INTERNAL].mean() < -0.07  # 0.1 m behind the face
    assert d[paper.kind == EXTERNAL].min() >= scenes3d.DRONE_RADIUS  # free space
    assert d[paper.kind == FALSE_CONTACT].min() > 0.05  # gusts happen in free space
    np.testing.assert_array_equal(paper.ids, np.arange(n))
    assert np.all(np.diff(paper.t_ns) >= 0)  # a contact and its internal point share a time


def test_truth_samples_lie_on_reachable_faces_only(paper):
    t = paper.truth_samples
    assert t.shape == (20000, 3)
    assert np.abs(paper.sdf(t)).max() < 1e-9
    assert not np.any(t[:, 2] < 1e-9)  # no sample on the floor (bottom faces are unreachable)


def test_generators_are_deterministic_per_seed():
    a, b, c = scenes3d.paper3d(3), scenes3d.paper3d(3), scenes3d.paper3d(4)
    np.testing.assert_array_equal(a.X, b.X)
    assert a.X.shape != c.X.shape or not np.array_equal(a.X, c.X)


def test_session40_is_a_long_time_ordered_stream(session):
    n = len(session.y)
    assert 5.0e4 <= n <= 7.0e4
    assert np.all(np.diff(session.t_ns) >= 0) and session.t_ns[-1] < 2400 * 10**9
    assert 0 < session.covered_s < 1200  # every patch touched in the first half
    # 25 Hz sliding, 4-12 mm apart (plus 1.5 cm noise): heavy near-duplicates, i.e. far
    # fewer occupied 5 cm voxels than contacts.
    xc = session.X[session.kind == CONTACT]
    voxels = np.unique(np.floor(xc / 0.05).astype(np.int64), axis=0)
    assert len(voxels) < len(xc) / 4
    # External points at 0.5 Hz during free flight: ~one per 2 s of non-contact time.
    n_ext = session.counts()["external"]
    assert 300 < n_ext < 1200
    assert session.sdf(session.X[session.kind == EXTERNAL]).min() >= 0.29


def test_session40_gusts_are_clusters_of_5_to_50(session):
    fc = session.kind == FALSE_CONTACT
    # Runs of false contacts in time order (internal points interleave): split by time gaps.
    t = session.t_ns[fc] * 1e-9
    gaps = np.flatnonzero(np.diff(t) > 0.05) + 1
    sizes = np.diff(np.concatenate([[0], gaps, [t.size]]))
    assert sizes.size >= 10
    assert sizes.min() >= 5 and sizes.max() <= 100  # two gusts may overlap in time
    # Within a gust the drone barely moves: members lie within ~10 cm of each other.
    first = session.X[fc][: sizes[0]]
    assert np.ptp(first, axis=0).max() < 0.15


def test_upto_is_a_prefix(session):
    part = session.upto(600.0)
    k = len(part.y)
    assert 0 < k < len(session.y)
    np.testing.assert_array_equal(part.X, session.X[:k])
    assert part.t_ns[-1] <= 600 * 10**9 < session.t_ns[k]


@pytest.mark.parametrize(
    "kwargs",
    [dict(n_contacts=0), dict(false_rate=1.5), dict(stroke_len=0)],
)
def test_bad_settings_are_refused(kwargs):
    with pytest.raises(ConfigError):
        scenes3d.paper3d(0, **kwargs)


def test_bad_session_settings_are_refused():
    with pytest.raises(ConfigError, match="contact_fraction"):
        scenes3d.session40(0, contact_fraction=1.0)
