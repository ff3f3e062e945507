"""Tile lattice (tiles.py): which tiles a point's reach touches."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from groundstation.mapping.tiles import TileLayout


@pytest.mark.parametrize(("edge", "reach"), [(1.0, 0.25), (0.75, 0.75), (0.5, 1.3)])
def test_keys_near_are_the_tiles_whose_core_meets_a_points_reach_box(edge, reach):
    rng = np.random.default_rng(7)
    X = rng.uniform(-2.0, 2.0, (40, 3))
    layout = TileLayout(edge, 3 * reach)
    got = {tuple(k) for k in layout.keys_near(X, reach)}
    want = set()
    for x in X:  # brute force: every key from the box's low to its high corner
        lo = np.floor((x - reach) / edge).astype(int)
        hi = np.floor((x + reach) / edge).astype(int)
        want |= set(itertools.product(*(range(a, b + 1) for a, b in zip(lo, hi, strict=True))))
    assert got == want
    assert {tuple(k) for k in layout.keys(X)} <= got


def test_keys_near_without_points_is_empty():
    assert TileLayout(1.0, 0.3).keys_near(np.zeros((0, 3)), 0.25).shape == (0, 3)


@pytest.mark.parametrize(("edge", "halo"), [(1.0, 0.69), (0.75, 0.9), (2.0, 0.0)])
def test_members_of_many_tiles_are_each_tiles_members(edge, halo):
    # points on the lattice planes and their halo bounds too (where < and >= decide)
    rng = np.random.default_rng(3)
    layout = TileLayout(edge, halo)
    grid = np.arange(-3, 4) * edge
    X = np.vstack([
        rng.uniform(-3.0, 3.0, (500, 3)),
        rng.choice(np.concatenate([grid, grid - halo, grid + halo]), (200, 3)),
    ])  # fmt: skip
    keys = [tuple(int(v) for v in k) for k in layout.keys_near(X, halo)]
    got = layout.members_of(X, keys)
    assert list(got) == keys
    for key in keys:
        np.testing.assert_array_equal(got[key], layout.members(X, key))
    n_in = sum(len(v) for v in got.values())
    assert n_in > len(X) if halo > 0 else n_in == len(X)  # halos overlap; cores partition
