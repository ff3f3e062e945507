"""Homoscedastic GPIS: gradients, a dense textbook oracle, chunking, input checks."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.linalg
from threadpoolctl import threadpool_limits

from groundstation.errors import (
    ConfigError,
    ConvergenceWarning,
    InputDataError,
    NotFittedError,
)
from groundstation.mapping import GPIS
from groundstation.mapping.gpis import gpis_objective
from groundstation.mapping.kernels import se_kernel, sq_dists

assert scipy.linalg  # loaded before the thread limit below so it applies to its BLAS too


@pytest.fixture(autouse=True, scope="module")
def _single_thread_blas():
    # Tiny matrices: threaded OpenBLAS only adds contention on shared 2-core machines.
    with threadpool_limits(1):
        yield


def circle(n_c: int = 40, n_free: int = 40, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Contacts on the unit circle (2 % radial noise), free space 1.25 < r < 2, one anchor."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, n_c, endpoint=False)
    r = 1 + 0.02 * rng.standard_normal(n_c)
    tf, rf = rng.uniform(0, 2 * np.pi, n_free), np.sqrt(rng.uniform(1.25**2, 4, n_free))
    X = np.vstack(
        [np.c_[r * np.cos(t), r * np.sin(t)], np.c_[rf * np.cos(tf), rf * np.sin(tf)], [[0.0, 0.0]]]
    )
    y = np.r_[np.zeros(n_c), np.ones(n_free), -1.0]
    return X, y


def test_log_marginal_gradient_matches_central_differences() -> None:
    X, y = circle(25, 25)
    D = sq_dists(X)
    theta = np.log([0.6, 0.8, 0.05])
    _, grad, _, _ = gpis_objective(theta, D, y - 0.2, 0.2)
    h = 1e-5
    for j in range(3):
        e = np.zeros(3)
        e[j] = h
        fd = (
            gpis_objective(theta + e, D, y - 0.2, 0.2)[0]
            - gpis_objective(theta - e, D, y - 0.2, 0.2)[0]
        ) / (2 * h)
        assert abs(grad[j] - fd) <= 1e-5 * max(abs(fd), 1e-3), (j, grad[j], fd)


def dense_gp(X, y, Xs, ell, sf2, sn2, mu0):
    """Textbook GP: (K + sn2 I)^-1 by a dense solve (fine at a moderate length scale)."""
    K = se_kernel(X, None, ell, sf2) + sn2 * np.eye(len(y))
    Ks = se_kernel(X, Xs, ell, sf2)
    Kinv_r = np.linalg.solve(K, y - mu0)
    mean = mu0 + Ks.T @ Kinv_r
    var = sf2 - np.einsum("ij,ij->j", Ks, np.linalg.solve(K, Ks))
    sign, logdet = np.linalg.slogdet(K)
    lml = -0.5 * (y - mu0) @ Kinv_r - 0.5 * logdet - 0.5 * len(y) * np.log(2 * np.pi)
    return mean, np.sqrt(var), lml


def test_fixed_hyperparameters_match_dense_textbook_gp() -> None:
    X, y = circle()
    Xs = np.random.default_rng(5).uniform(-2, 2, (50, 2))
    model = GPIS(
        lengthscale=0.5, signal_var=0.9, noise_var=0.02, prior_mean=0.1, optimize=False
    ).fit(X, y)
    mean, std = model.predict(Xs, return_std=True)
    mean_d, std_d, lml_d = dense_gp(X, y, Xs, 0.5, 0.9, 0.02, 0.1)
    np.testing.assert_allclose(mean, mean_d, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(std, std_d, rtol=1e-8, atol=1e-9)
    assert model.log_marginal_likelihood_ == pytest.approx(lml_d, rel=1e-10)
    # uncertainty_ is the predictive (latent) variance at the training points.
    _, std_tr = model.predict(X, return_std=True)
    np.testing.assert_allclose(model.uncertainty_, std_tr**2, rtol=1e-7, atol=1e-10)
    assert model.n_iter_ == 0 and model.converged_


def test_fit_learns_hyperparameters_within_bounds_and_improves_likelihood() -> None:
    X, y = circle()
    fixed = GPIS(optimize=False).fit(X, y)
    model = GPIS(noise_var_bounds=(1e-4, 1.0)).fit(X, y)
    assert model.converged_ and model.n_iter_ > 0
    assert model.log_marginal_likelihood_ > fixed.log_marginal_likelihood_
    assert 1e-2 <= model.lengthscale_ <= 1e2 and 1e-4 <= model.noise_var_ <= 1.0
    # the learnt surface separates inside from outside
    mean = model.predict(np.array([[0.0, 0.0], [0.5, 0.0], [1.6, 0.0]]))
    assert mean[0] < 0 and mean[2] > 0


def test_chunked_prediction_equals_unchunked() -> None:
    X, y = circle()
    model = GPIS(optimize=False).fit(X, y)
    Xs = np.random.default_rng(7).uniform(-2, 2, (301, 2))
    m_full, s_full = model.predict(Xs, return_std=True)
    model.chunk_mb = 1e-3  # about one row per chunk
    m_chunk, s_chunk = model.predict(Xs, return_std=True)
    assert np.array_equal(model.predict(Xs), m_chunk)
    np.testing.assert_allclose(m_chunk, m_full, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(s_chunk, s_full, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("eps", [0.0, 1e-9])
def test_duplicate_inputs_fit(eps: float) -> None:
    X, y = circle()
    X = np.vstack([X, X[:10] + eps])
    y = np.r_[y, y[:10]]
    model = GPIS(noise_var_bounds=(1e-6, 10.0)).fit(X, y)
    mean, std = model.predict(X, return_std=True)
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(std))
    assert np.all(np.isfinite(model.uncertainty_)) and np.isfinite(model.log_marginal_likelihood_)


def test_warm_start_starts_from_previous_hyperparameters() -> None:
    X, y = circle(seed=3)
    cold = GPIS().fit(X, y)
    warm = GPIS(warm_start=True).fit(X, y)
    warm.fit(X, y)  # already at the optimum: L-BFGS-B stops at once
    assert cold.n_iter_ > 2 and warm.n_iter_ <= 2
    assert warm.log_marginal_likelihood_ >= cold.log_marginal_likelihood_ - 1e-9
    not_warm = GPIS(warm_start=False).fit(X, y)
    not_warm.fit(X, y)
    assert not_warm.n_iter_ == cold.n_iter_


def test_iteration_limit_warns_and_reports_not_converged() -> None:
    X, y = circle()
    with pytest.warns(ConvergenceWarning):
        model = GPIS(max_iter=1).fit(X, y)
    assert not model.converged_


def test_predict_before_fit_raises() -> None:
    with pytest.raises(NotFittedError):
        GPIS().predict(np.zeros((3, 2)))


def _bad_inputs():
    X, y = circle(5, 5)
    Xn = X.copy()
    Xn[[2, 4], 0] = np.nan
    yi = y.copy()
    yi[3] = np.inf
    return [
        (Xn, y, r"X contains NaN or inf in rows \[2, 4\]"),
        (X, yi, r"y contains NaN or inf in rows \[3\]"),
        (X[:, 0], y, r"X must be a 2-D array"),
        (np.c_[X, X], y, r"X must have 2 or 3 columns"),
        (np.zeros((0, 2)), np.zeros(0), r"X is empty"),
        (X[:1], y[:1], r"at least 2 training points"),
        (X, y[:-1], r"X and y lengths differ"),
        (X, y[:, None], r"y must be a 1-D array"),
        (X, np.ones(len(y)), r"no contact"),
        ([["a", "b"]], [0.0], r"X must be numeric"),
    ]


@pytest.mark.parametrize(("X", "y", "match"), _bad_inputs())
def test_bad_input_raises_named_error(X, y, match) -> None:
    with pytest.raises(InputDataError, match=match):
        GPIS().fit(X, y)


def test_bad_predict_input_raises() -> None:
    X, y = circle()
    model = GPIS(optimize=False).fit(X, y)
    with pytest.raises(InputDataError, match="columns"):
        model.predict(np.zeros((2, 3)))
    with pytest.raises(InputDataError, match=r"rows \[1\]"):
        model.predict(np.array([[0.0, 0.0], [np.inf, 0.0]]))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"lengthscale": -1.0}, "lengthscale"),
        ({"noise_var": 0.0}, "noise_var"),
        ({"lengthscale_bounds": (1.0, 0.5)}, "lengthscale_bounds"),
        ({"lengthscale": 1e3}, "outside lengthscale_bounds"),
        ({"max_iter": 0}, "max_iter"),
        ({"prior_mean": float("nan")}, "prior_mean"),
    ],
)
def test_bad_settings_raise_config_error_at_fit(kwargs, match) -> None:
    X, y = circle(5, 5)
    model = GPIS(**kwargs)  # __init__ only stores
    with pytest.raises(ConfigError, match=match):
        model.fit(X, y)


def test_three_dimensional_inputs() -> None:
    rng = np.random.default_rng(0)
    v = rng.standard_normal((60, 3))
    X = np.vstack(
        [
            v / np.linalg.norm(v, axis=1, keepdims=True),
            1.8 * v[:30] / np.linalg.norm(v[:30], axis=1, keepdims=True),
        ]
    )
    y = np.r_[np.zeros(60), np.ones(30)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        model = GPIS().fit(X, y)
    assert model.predict(np.zeros((1, 3))).shape == (1,)
