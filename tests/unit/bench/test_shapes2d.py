"""The paper's 2D simulation data: exact signed distances and the data-set protocol."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.path import Path as MplPath
from scipy.spatial import cKDTree

from groundstation.bench import shapes2d
from groundstation.bench.shapes2d import (
    CONTACT,
    EXTERNAL,
    FALSE_CONTACT,
    FALSE_INTERNAL,
    INTERNAL,
    make_dataset,
    make_shape,
)
from groundstation.errors import ConfigError


@pytest.mark.parametrize("name", shapes2d.SHAPES)
def test_sdf_is_exact_against_brute_force(name):
    """Oracle: distance to a dense boundary sampling, signed by a point-in-polygon test."""
    shape = make_shape(name)
    pts = np.random.default_rng(3).uniform(-0.5, 0.5, size=(4000, 2))
    boundary = shape.boundary(0.0005)
    dist = cKDTree(boundary).query(pts)[0]
    inside = MplPath(shape.outline()).contains_points(pts)
    # Sampling error of the oracle <= half the sample spacing (+ chord error on the circle).
    np.testing.assert_allclose(shape.sdf(pts), np.where(inside, -dist, dist), atol=4e-4)


@pytest.mark.parametrize("name", shapes2d.SHAPES)
def test_contacts_every_centimetre_on_the_boundary(name):
    c = make_shape(name).contacts()
    assert c.shape == (120, 2)
    np.testing.assert_allclose(make_shape(name).sdf(c), 0.0, atol=1e-12)
    gaps = np.linalg.norm(np.diff(np.vstack([c, c[:1]]), axis=0), axis=1)
    # 0.01 m of arc between neighbours (chord on the circle: 3 degrees at r = 0.191 m).
    np.testing.assert_allclose(gaps, 0.01, atol=1e-5)


def test_unknown_shape_is_a_config_error():
    with pytest.raises(ConfigError, match="triangle"):
        make_shape("triangle")


@pytest.mark.parametrize("name", shapes2d.SHAPES)
def test_dataset_counts_labels_and_pairs(name):
    shape = make_shape(name)
    d = make_dataset(shape, np.random.default_rng(7))
    n = len(d.y)
    assert d.X.shape == (n, 2) and d.kind.shape == (n,)
    counts = d.counts()
    assert counts["contact"] == 120
    assert counts["false_contact"] == counts["false_internal"]
    # 460 free samples, each replaced outlier adds one row: n ~ 590.
    assert n == 120 + 460 + counts["false_contact"]
    assert 575 <= n <= 605
    # Labels follow the kind; free-space labels follow the true inside/outside.
    np.testing.assert_array_equal(d.y[d.kind == CONTACT], 0.0)
    np.testing.assert_array_equal(d.y[d.kind == FALSE_CONTACT], 0.0)
    np.testing.assert_array_equal(d.y[np.isin(d.kind, (INTERNAL, FALSE_INTERNAL))], -1.0)
    np.testing.assert_array_equal(d.y[d.kind == EXTERNAL], 1.0)
    assert np.all(shape.sdf(d.X[d.kind == INTERNAL]) < 0)
    assert np.all(shape.sdf(d.X[d.kind == EXTERNAL]) >= 0)
    assert np.all(shape.sdf(d.X[d.kind == FALSE_CONTACT]) >= 0)  # replaced external points
    assert np.all(np.abs(d.X) <= 3.0 + 0.1)
    # Each false internal point is paired with a false contact within 0.1 m.
    fi = np.flatnonzero(d.kind == FALSE_INTERNAL)
    assert np.all(d.kind[d.pair[fi]] == FALSE_CONTACT)
    assert np.all(np.linalg.norm(d.X[fi] - d.X[d.pair[fi]], axis=1) <= 0.1 + 1e-12)
    assert np.all(d.pair[d.kind != FALSE_INTERNAL] == -1)
    np.testing.assert_array_equal(d.outlier, d.kind == FALSE_CONTACT)
    assert not np.any(d.normal & (d.kind >= FALSE_CONTACT))


def test_outlier_rate_is_two_percent_of_external_points():
    shape = make_shape("circle")
    pairs = ext = 0
    for seed in range(40):
        c = make_dataset(shape, np.random.default_rng(seed)).counts()
        pairs += c["false_contact"]
        ext += c["external"] + c["false_contact"]
    # Binomial(~18000, 0.02): sd ~ 19 pairs.
    assert abs(pairs - 0.02 * ext) < 5 * np.sqrt(0.02 * 0.98 * ext)


def test_dataset_is_deterministic_from_the_generator():
    shape = make_shape("cross")
    a = make_dataset(shape, np.random.default_rng(11))
    b = make_dataset(shape, np.random.default_rng(11))
    c = make_dataset(shape, np.random.default_rng(12))
    np.testing.assert_array_equal(a.X, b.X)
    np.testing.assert_array_equal(a.kind, b.kind)
    assert a.X.shape != c.X.shape or not np.array_equal(a.X, c.X)


def test_dataset_rejects_bad_rates():
    with pytest.raises(ConfigError):
        make_dataset(make_shape("square"), np.random.default_rng(0), outlier_prob=1.5)
