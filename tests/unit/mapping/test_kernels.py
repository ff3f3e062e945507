"""Squared-exponential kernel: vectorised forms against a slow loop oracle (STYLE.md 9)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from groundstation.mapping.kernels import (
    se_from_sq_dists,
    se_grad_log_params,
    se_kernel,
    sq_dists,
)


def slow_se(X1: np.ndarray, X2: np.ndarray, ell: float, sf2: float) -> np.ndarray:
    K = np.empty((len(X1), len(X2)))
    for i, a in enumerate(X1):
        for j, b in enumerate(X2):
            d2 = sum((float(p) - float(q)) ** 2 for p, q in zip(a, b, strict=True))
            K[i, j] = sf2 * math.exp(-d2 / (2.0 * ell * ell))
    return K


@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("offset", [0.0, 50.0])
def test_vectorised_kernel_equals_loop(d: int, offset: float) -> None:
    rng = np.random.default_rng(d)
    X1 = rng.uniform(-2, 2, (17, d)) + offset
    X2 = rng.uniform(-2, 2, (9, d)) + offset
    for ell, sf2 in [(0.25, 1.0), (1.3, 0.4)]:
        np.testing.assert_allclose(
            se_kernel(X1, X2, ell, sf2), slow_se(X1, X2, ell, sf2), rtol=1e-12, atol=1e-14
        )
        np.testing.assert_allclose(
            se_kernel(X1, None, ell, sf2), slow_se(X1, X1, ell, sf2), rtol=1e-12, atol=1e-14
        )


def test_sq_dists_symmetric_zero_diagonal_nonnegative() -> None:
    rng = np.random.default_rng(1)
    X = rng.uniform(-3, 3, (30, 3))
    X = np.vstack([X, X[:3], X[:3] + 1e-9])  # exact and near duplicates
    D = sq_dists(X)
    assert np.array_equal(D, D.T)
    assert np.all(np.diag(D) == 0.0)
    assert np.all(D >= 0.0)
    np.testing.assert_allclose(D, ((X[:, None, :] - X[None, :, :]) ** 2).sum(-1), atol=1e-12)


def test_sq_dists_centre_does_not_change_result() -> None:
    rng = np.random.default_rng(2)
    X1, X2 = rng.uniform(-1, 1, (5, 2)), rng.uniform(-1, 1, (7, 2))
    np.testing.assert_allclose(
        sq_dists(X1, X2), sq_dists(X1, X2, center=np.array([0.3, -0.2])), atol=1e-14
    )


def test_kernel_log_parameter_derivatives_match_finite_differences() -> None:
    rng = np.random.default_rng(3)
    X = rng.uniform(-1, 1, (12, 2))
    D = sq_dists(X)
    ell, sf2, h = 0.7, 1.4, 1e-6
    dl, ds = se_grad_log_params(se_from_sq_dists(D, ell, sf2), D, ell)
    fd_l = (
        se_from_sq_dists(D, ell * math.exp(h), sf2) - se_from_sq_dists(D, ell * math.exp(-h), sf2)
    ) / (2 * h)
    fd_s = (
        se_from_sq_dists(D, ell, sf2 * math.exp(h)) - se_from_sq_dists(D, ell, sf2 * math.exp(-h))
    ) / (2 * h)
    np.testing.assert_allclose(dl, fd_l, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(ds, fd_s, rtol=1e-6, atol=1e-10)
