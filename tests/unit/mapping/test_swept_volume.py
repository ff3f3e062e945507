"""The swept-volume test (``training._inside_body``) against its definition, pair by pair.

The fast version finds candidate pairs with a box query on scaled coordinates and tests a
coarse subsample of the free-space samples before the rest; the oracle below loops over every
(probe, sample) pair with the rule as the docstring states it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from groundstation.mapping.training import (
    SWEEP_COARSE,
    TrainingPolicy,
    _inside_body,
    _Sweep,
)


def oracle(free_X, free_t, pts, normals, owner, t_span, p: TrainingPolicy, G: int) -> np.ndarray:
    """``out[g]``: some probe of group g is inside the body at a sample away from g's span."""
    R, H, tol = p.body_radius_m, p.body_half_height_m, p.sweep_tolerance_m
    excl = int(p.sweep_exclude_s * 1e9)
    out = np.zeros(G, dtype=bool)
    for k in range(len(pts)):
        g = owner[k]
        lo, hi = t_span[g][0] - excl, t_span[g][1] + excl
        n = normals[k]
        along = bool(np.any(n != 0.0)) and p.tolerance_along_normal
        for m in range(len(free_X)):
            if lo <= free_t[m] <= hi:
                continue
            dx = free_X[m] - pts[k]
            if along:
                ends = [dx + s * tol * n for s in (-1.0, 1.0)]
                inside = all(np.hypot(e[0], e[1]) < R and abs(e[2]) < H for e in ends)
            else:
                inside = np.hypot(dx[0], dx[1]) < R - tol and abs(dx[2]) < H - tol
            if inside:
                out[g] = True
                break
    return out


@pytest.mark.parametrize("along", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_fast_swept_volume_test_is_the_rule_pair_by_pair(seed, along):
    rng = np.random.default_rng(seed)
    p = dataclasses.replace(TrainingPolicy(), tolerance_along_normal=along)
    G = 40
    # a vehicle lingering in a few spots (hundreds of samples each) and flying between them
    spots = rng.uniform(-0.6, 0.6, size=(4, 3))
    hover = spots[rng.integers(0, 4, 600)] + rng.normal(0.0, 0.03, size=(600, 3))
    path = rng.uniform(-0.8, 0.8, size=(200, 3))
    free_X = np.concatenate([hover, path])
    free_t = rng.integers(0, 100 * 10**9, len(free_X))
    owner = np.sort(rng.integers(0, G, 300))
    pts = rng.uniform(-0.7, 0.7, size=(300, 3))
    n = rng.normal(size=(300, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[rng.random(300) < 0.2] = 0.0  # probes without a normal
    start = rng.integers(0, 100 * 10**9, G)
    t_span = [(int(s), int(s) + int(rng.integers(0, 3 * 10**9))) for s in start]

    assert len(free_X) > SWEEP_COARSE  # the coarse pass runs
    out = np.zeros(G, dtype=bool)
    _inside_body(_Sweep.of(free_X, free_t, p), pts, n, owner, t_span, p, out)
    want = oracle(free_X, free_t, pts, n, owner, t_span, p, G)
    assert 0 < want.sum() < G  # both answers occur
    np.testing.assert_array_equal(out, want)


def test_a_probe_on_the_boundary_of_the_body_is_not_inside():
    """The box query keeps the pairs whose rounding lands a hair past its half-widths; the
    strict test still rejects the probe exactly at the body's top."""
    p = dataclasses.replace(TrainingPolicy(), sweep_tolerance_m=0.0)
    free_X = np.array([[0.0, 0.0, 0.0]])
    free_t = np.array([10 * 10**9])
    pts = np.array([[0.0, 0.0, p.body_half_height_m], [0.1, 0.0, 0.999 * p.body_half_height_m]])
    out = np.zeros(2, dtype=bool)
    _inside_body(_Sweep.of(free_X, free_t, p), pts, np.zeros((2, 3)), np.array([0, 1]),
                 [(0, 0), (0, 0)], p, out)  # fmt: skip
    np.testing.assert_array_equal(out, [False, True])
