"""Accuracy measures on hand-checkable geometry."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.errors import InputDataError
from groundstation.mapping.grid import Grid
from groundstation.mapping.metrics import (
    chamfer_distance,
    distance_to,
    false_positive_clarity,
    phantom_length,
    phantom_patches,
    polyline_length,
    sample_mesh_surface,
    sample_polylines,
    shape_error,
)


def circle(radius: float, n: int = 2000, center=(0.0, 0.0)) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n + 1)
    return np.stack([center[0] + radius * np.cos(t), center[1] + radius * np.sin(t)], axis=1)


def test_chamfer_concentric_circles_is_radius_gap():
    a = sample_polylines([circle(1.0)], 0.002)
    b = sample_polylines([circle(1.3)], 0.002)
    assert chamfer_distance(a, b) == pytest.approx(0.3, abs=1e-4)
    assert chamfer_distance(a, a) == 0.0
    assert np.isnan(chamfer_distance(a, np.zeros((0, 2))))


def test_chamfer_charges_missing_surface():
    full = sample_polylines([circle(1.0)], 0.002)
    half = full[full[:, 1] > 0]
    # half -> full is 0. full -> half: the upper half is at 0, a lower point at angle -phi
    # (phi <= pi/2) is 2 sin(phi/2) from the nearest end (1, 0); its mean over phi is
    # (8/pi)(1 - cos(pi/4)). Chamfer = (0 + (0 + that) / 2) / 2.
    expected = 0.25 * (8 / np.pi) * (1 - np.cos(np.pi / 4))
    assert chamfer_distance(half, full) == pytest.approx(expected, abs=1e-3)


def test_sample_polylines_uniform_and_length():
    line = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.5]])
    assert polyline_length([line]) == pytest.approx(1.5)
    pts = sample_polylines([line], 0.01)
    assert len(pts) == 150
    assert polyline_length([circle(2.0, 4000)]) == pytest.approx(2 * np.pi * 2.0, rel=1e-5)


def test_sample_mesh_surface_is_area_uniform_and_deterministic():
    # Two triangles forming the unit square in z = 0, one 3x larger than the other.
    v = np.array([[0, 0, 0], [3, 0, 0], [3, 1, 0], [0, 1, 0]], dtype=float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    p = sample_mesh_surface(v, f, 20000, seed=1)
    assert p.shape == (20000, 3)
    np.testing.assert_array_equal(p, sample_mesh_surface(v, f, 20000, seed=1))
    assert np.all((p[:, 0] >= 0) & (p[:, 0] <= 3) & (p[:, 1] >= 0) & (p[:, 1] <= 1))
    # Uniform over the rectangle: the mean is its centre, a third of the points lie in x < 1.
    np.testing.assert_allclose(p[:, :2].mean(axis=0), [1.5, 0.5], atol=0.02)
    assert np.mean(p[:, 0] < 1) == pytest.approx(1 / 3, abs=0.02)
    assert sample_mesh_surface(np.zeros((0, 3)), np.zeros((0, 3), int), 10).shape == (0, 3)
    with pytest.raises(InputDataError):
        sample_mesh_surface(v, np.array([[0, 1, 9]]), 5)


def test_shape_error_band_and_truth_forms():
    g = Grid.from_bounds((-2, -2), (2, 2), 0.01)
    pts = g.points()
    r = np.linalg.norm(pts, axis=1)
    # An estimate whose zero set is the circle of radius 1.1 around a true circle of radius 1.
    mean = r - 1.1
    truth_fn = lambda p: np.linalg.norm(p, axis=1) - 1.0  # noqa: E731
    e = shape_error(mean, pts, truth_fn, band=0.01)
    assert e == pytest.approx(0.1, abs=0.005)
    e_samples = shape_error(mean, pts, circle(1.0, 20000), band=0.01)
    assert e_samples == pytest.approx(e, abs=1e-3)
    # Only the band counts: an error far from the band changes nothing.
    mean2 = mean.copy()
    mean2[r > 1.8] = 5.0
    assert shape_error(mean2, pts, truth_fn) == e
    assert np.isnan(shape_error(np.ones_like(mean), pts, truth_fn))
    with pytest.raises(InputDataError):
        shape_error(mean[:-1], pts, truth_fn)


def test_distance_to_rejects_wrong_dims():
    with pytest.raises(InputDataError):
        distance_to(np.zeros((5, 3)), np.zeros((2, 2)))


def test_false_positive_clarity_hand_case():
    X = np.array([[0, 0], [0.3, 0], [0, 0.4], [5, 5], [5.2, 5], [9, 9], [0.1, 0.1]], dtype=float)
    u = np.array([8.0, 1.0, 3.0, 2.0, 4.0, 1.0, 100.0])
    outlier = np.array([True, False, False, True, False, True, False])
    normal = np.array([False, True, True, False, True, False, False])  # row 6: a pair's interior
    c = false_positive_clarity(X, u, outlier, normal=normal, radius=0.5)
    # o=0: normal neighbours rows 1, 2 -> mean 2 / 8; o=3: row 4 -> 4 / 2; o=5: none -> skipped.
    np.testing.assert_allclose(c.per_outlier[:2], [0.25, 2.0])
    assert np.isnan(c.per_outlier[2]) and c.n_skipped == 1
    assert c.mean == pytest.approx(1.125)
    # Default normal = not outlier: row 6 then joins o=0's neighbours.
    c2 = false_positive_clarity(X, u, outlier, radius=0.5)
    assert c2.per_outlier[0] == pytest.approx((1 + 3 + 100) / 3 / 8)
    with pytest.raises(InputDataError, match="u must be"):
        false_positive_clarity(X, -u, outlier)


def test_phantom_length_counts_only_far_contour():
    true_circle = lambda p: np.linalg.norm(p, axis=1) - 1.0  # noqa: E731
    near = circle(1.05)  # within 0.1 m of the truth
    far = circle(0.2, center=(2.5, 0.0))  # a phantom blob 1.3..1.7 m away
    straddling = np.array([[1.0, 0.0], [1.4, 0.0]])  # 0.1 m of it is near, 0.3 m is far
    assert phantom_length([near], true_circle, threshold=0.1) == 0.0
    assert phantom_length([far], true_circle) == pytest.approx(2 * np.pi * 0.2, rel=1e-4)
    assert phantom_length([straddling], true_circle, threshold=0.1, step=0.001) == pytest.approx(
        0.3, abs=2e-3
    )
    assert phantom_length([], true_circle) == 0.0


def _square(x0, y0, z, side, n=5):
    """An n x n vertex grid of a horizontal square (corner x0, y0; height z), as triangles."""
    xx, yy = np.meshgrid(np.linspace(x0, x0 + side, n), np.linspace(y0, y0 + side, n))
    v = np.column_stack([xx.ravel(), yy.ravel(), np.full(n * n, z)])
    f = [
        [i * n + j, i * n + j + 1, (i + 1) * n + j + 1] for i in range(n - 1) for j in range(n - 1)
    ]
    f += [
        [i * n + j, (i + 1) * n + j + 1, (i + 1) * n + j]
        for i in range(n - 1)
        for j in range(n - 1)
    ]
    return v, np.asarray(f)


def test_phantom_patches_are_separate_pieces_largest_first_with_where_they_lie():
    floor = lambda p: p[:, 2]  # noqa: E731 - the true surface is the plane z = 0
    on_it = _square(0.0, 0.0, 0.05, 1.0)  # within 0.15 m of the truth: not phantom
    big = _square(3.0, 0.0, 0.5, 1.0)  # 1 m^2 floating 0.5 m up
    small = _square(-2.0, -2.0, -0.3, 0.5)  # 0.25 m^2 sunk 0.3 m
    v = np.vstack([on_it[0], big[0], small[0]])
    f = np.vstack([on_it[1], big[1] + 25, small[1] + 50])
    patches = phantom_patches(v, f, floor, threshold=0.15)
    assert [round(p.area_m2, 6) for p in patches] == [1.0, 0.25]
    assert patches[0].centre == pytest.approx((3.5, 0.5, 0.5), abs=0.05)
    assert patches[0].farthest_m == pytest.approx(0.5)
    assert patches[1].lo[2] == pytest.approx(-0.3) and patches[1].hi[0] <= -1.5
    assert patches[0].as_dict()["area_m2"] == pytest.approx(1.0)
    assert phantom_patches(*on_it, floor, threshold=0.15) == ()
    sliver = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [2.0, 0.0, 1.0]])  # no area, still there
    (flat,) = phantom_patches(sliver, np.array([[0, 1, 2]]), floor)
    assert flat.area_m2 == 0.0 and flat.centre == pytest.approx((1.0, 0.0, 1.0))
    assert phantom_patches(v, np.zeros((0, 3), dtype=int), floor) == ()


def test_a_phantom_patch_in_pieces_whose_seam_repeats_vertices_is_one_patch():
    # two 1 x 0.5 m halves of one floating square, meshed apart (as two map tiles are): the seam
    # y = 0.5 has each vertex twice, 0.2 mm apart; joined, it is one 1 m^2 patch, not two
    floor = lambda p: p[:, 2]  # noqa: E731
    a, b = _square(0.0, 0.0, 0.5, 0.5), _square(0.0, 0.5, 0.5, 0.5)
    va, vb = a[0] * [2.0, 1.0, 1.0], b[0] * [2.0, 1.0, 1.0] + [0.0, 2e-4, 0.0]
    v, f = np.vstack([va, vb]), np.vstack([a[1], b[1] + len(va)])
    (one,) = phantom_patches(v, f, floor)
    assert one.area_m2 == pytest.approx(1.0, rel=1e-3)
    assert [round(p.area_m2, 3) for p in phantom_patches(v, f, floor, join_m=0.0)] == [0.5, 0.5]
