"""Narrow-band field evaluation (field.py) against the dense grid: same zero set."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.mapping.field import narrow_band_field
from groundstation.mapping.grid import Grid, GridError, evaluate_field
from groundstation.mapping.metrics import chamfer_distance
from groundstation.mapping.surface import extract_contours, extract_surface


def scene(X: np.ndarray) -> np.ndarray:
    """A smooth GPIS-like field: -1 inside, 0 on a sphere and a box, +1 far outside."""
    d1 = np.linalg.norm(X - [1.0, 1.0, 0.8], axis=1) - 0.5
    q = np.abs(X - [2.6, 1.0, 0.8]) - [0.5, 0.4, 0.3]
    d2 = np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)
    return np.tanh(np.minimum(d1, d2) / 0.25)


def count_calls(fn):
    calls = {"points": 0}

    def wrapped(X: np.ndarray) -> np.ndarray:
        calls["points"] += X.shape[0]
        return fn(X)

    return wrapped, calls


@pytest.mark.parametrize("coarse_factor", [2, 4, 8])
def test_narrow_band_and_dense_fields_have_the_same_zero_set(coarse_factor: int) -> None:
    grid = Grid.from_bounds((0.0, 0.0, 0.0), (3.6, 2.0, 1.6), 0.04)
    dense = evaluate_field(lambda X, return_std=False: scene(X), grid).mean
    fn, calls = count_calls(scene)
    band = narrow_band_field(fn, grid, coarse_factor=coarse_factor, band_voxels=2)
    assert calls["points"] == band.n_evaluated
    assert band.fraction_evaluated < 0.6  # the point of the exercise
    # Exact where evaluated; the same sign everywhere (sign-preserving fill).
    np.testing.assert_array_equal(band.values[band.evaluated], dense[band.evaluated])
    np.testing.assert_array_equal(np.sign(band.values), np.sign(dense))
    # Both ends of every grid edge that the zero set crosses were evaluated exactly.
    crossing = np.zeros(grid.shape, dtype=bool)
    for ax in range(3):
        s = np.diff(np.sign(dense), axis=ax) != 0
        lo = [slice(None)] * 3
        lo[ax] = slice(0, -1)
        crossing[tuple(lo)] |= s
    assert crossing.any() and np.all(band.evaluated[crossing])
    a = extract_surface(dense, grid)
    b = extract_surface(band.values, grid)
    assert not a.is_empty
    assert chamfer_distance(a.vertices, b.vertices) < 0.5 * grid.spacing


def test_two_dimensional_band_matches_dense_contours() -> None:
    grid = Grid.from_bounds((0.0, 0.0), (3.0, 2.0), 0.02)

    def f(X: np.ndarray) -> np.ndarray:
        return np.tanh((np.linalg.norm(X - [1.5, 1.0], axis=1) - 0.6) / 0.2)

    dense = f(grid.points()).reshape(grid.shape)
    band = narrow_band_field(f, grid, coarse_factor=4)
    np.testing.assert_array_equal(np.sign(band.values), np.sign(dense))
    ca = np.concatenate(extract_contours(dense, grid))
    cb = np.concatenate(extract_contours(band.values, grid))
    assert chamfer_distance(ca, cb) < 0.5 * grid.spacing
    assert band.fraction_evaluated < 0.35


def test_coarse_factor_one_is_the_dense_grid_and_bad_arguments_raise() -> None:
    grid = Grid.from_bounds((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 0.1)
    band = narrow_band_field(scene, grid, coarse_factor=1)
    assert band.evaluated.all() and band.n_evaluated == grid.size
    with pytest.raises(GridError, match="power of two"):
        narrow_band_field(scene, grid, coarse_factor=3)
    with pytest.raises(GridError, match="NaN"):
        narrow_band_field(lambda X: np.full(X.shape[0], np.nan), grid)
    with pytest.raises(GridError, match="wrong number"):
        narrow_band_field(lambda X: np.zeros(1), grid)
