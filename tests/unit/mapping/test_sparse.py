"""Sparse robust GPIS (ALGORITHM.md §8): the Z = X limit, nested bounds, gradients, fits."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import scipy.linalg
from threadpoolctl import threadpool_limits

from groundstation.errors import ConfigError, ConvergenceWarning, InputDataError
from groundstation.mapping import RobustGPIS
from groundstation.mapping._linalg import FrozenPosterior, factorize
from groundstation.mapping.kernels import se_from_sq_dists, sq_dists
from groundstation.mapping.sparse import (
    SparsePosterior,
    SparseRobustGPIS,
    choose_inducing,
    sparse_factorize,
    voxel_representatives,
)

assert scipy.linalg  # loaded before the thread limit so it applies to its BLAS too


@pytest.fixture(autouse=True, scope="module")
def _single_thread_blas():
    with threadpool_limits(1):
        yield


def circle(n_c=80, n_free=60, n_out=6, seed=1):
    """Contacts on the unit circle, free space in 1.25 < r < 2, 4 interior anchors and
    ``n_out`` false contacts in free space; returns X, y, outlier indices."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 2 * np.pi, n_c, endpoint=False) + rng.uniform(0, 0.05, n_c)
    r = 1 + 0.02 * rng.standard_normal(n_c)
    tf, rf = rng.uniform(0, 2 * np.pi, n_free), np.sqrt(rng.uniform(1.25**2, 4, n_free))
    to = np.linspace(0, 2 * np.pi, n_out, endpoint=False) + 0.3
    ro = rng.uniform(1.5, 1.8, n_out)
    X = np.vstack(
        [
            np.c_[r * np.cos(t), r * np.sin(t)],
            np.c_[rf * np.cos(tf), rf * np.sin(tf)],
            [[0.0, 0.0], [0.4, 0.0], [-0.4, 0.0], [0.0, 0.4]],
            np.c_[ro * np.cos(to), ro * np.sin(to)],
        ]
    )
    y = np.r_[np.zeros(n_c), np.ones(n_free), -np.ones(4), np.zeros(n_out)]
    return X, y, np.arange(n_c + n_free + 4, X.shape[0])


def _problem(n=70, seed=0):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1, 1, (n, 2))
    y = rng.choice([-1.0, 0.0, 1.0], n)
    w = rng.uniform(0.5, 50.0, n)
    return X, y, w


def test_inducing_equal_to_training_points_gives_the_exact_model() -> None:
    X, y, w = _problem()
    ell, sf2, mu0 = 0.6, 1.3, 0.0
    D = sq_dists(X)
    exact = factorize(se_from_sq_dists(D, ell, sf2), D, w, y - mu0, mu0, ell)
    sparse = sparse_factorize(D, D, w, y - mu0, mu0, ell, sf2, jitter=1e-10)
    # S1 = L1, S2 = the exact marginals, KL(q(u)||p(u)) = KL_f, and the same M3 gradient.
    assert sparse.F == pytest.approx(exact.log_marginal(w), rel=1e-7)
    np.testing.assert_allclose(sparse.m, exact.m, atol=1e-6)
    np.testing.assert_allclose(sparse.diag_A, exact.diag_A, atol=1e-7)
    assert sparse.kl_f == pytest.approx(exact.kl_f, rel=1e-6)
    np.testing.assert_allclose(sparse.grad, exact.grad, rtol=1e-5)
    # And the frozen predictors agree away from the data.
    post = SparsePosterior.from_factor(X, sparse, mu0, ell, sf2)
    frozen = FrozenPosterior(X, X.mean(0), exact.a, exact.L, exact.sw, mu0, ell, sf2)
    Xs = np.random.default_rng(5).uniform(-1.5, 1.5, (200, 2))
    m_s, s_s = post.predict(Xs, return_std=True)
    m_e, s_e = frozen.predict(Xs, return_std=True)
    # (the predictors go through Lu^-T, which amplifies the 1e-10 jitter's rounding)
    np.testing.assert_allclose(m_s, m_e, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(s_s, s_e, atol=1e-3)


def test_nested_inducing_sets_give_increasing_bounds_below_the_exact_value() -> None:
    X, y, w = _problem(n=150, seed=2)
    ell, sf2 = 0.5, 1.0
    D = sq_dists(X)
    exact = factorize(se_from_sq_dists(D, ell, sf2), D, w, y, 0.0, ell).log_marginal(w)
    bounds = [
        sparse_factorize(sq_dists(X[:k]), sq_dists(X[:k], X), w, y, 0.0, ell, sf2).F
        for k in (20, 60, 150)
    ]
    assert bounds[0] < bounds[1] < bounds[2] <= exact + 1e-6 * abs(exact)
    assert bounds[2] == pytest.approx(exact, rel=1e-4)  # default jitter 1e-6 on Kuu


def test_kernel_gradient_matches_central_differences() -> None:
    X, y, w = _problem(n=90, seed=3)
    Z = X[::3]
    Duu, Duf = sq_dists(Z), sq_dists(Z, X)
    theta = np.log([0.45, 0.8])

    def bound(t: np.ndarray) -> float:
        ell, sf2 = np.exp(t)
        return sparse_factorize(Duu, Duf, w, y, 0.0, ell, sf2, with_grad=False).F

    grad = sparse_factorize(Duu, Duf, w, y, 0.0, *np.exp(theta)).grad
    h = 1e-5
    fd = [(bound(theta + h * e) - bound(theta - h * e)) / (2 * h) for e in np.eye(2)]
    np.testing.assert_allclose(grad, fd, rtol=1e-5)


def test_voxel_subsample_and_inducing_choice() -> None:
    X, y, _ = circle()
    idx = voxel_representatives(X, 0.5)
    keys = np.floor(X[idx] / 0.5)
    assert len({tuple(k) for k in keys}) == idx.size  # one per voxel
    assert idx.size == len({tuple(k) for k in np.floor(X / 0.5)})
    Z = choose_inducing(X, y, lengthscale=0.5, n_max=30)
    assert 0 < Z.size <= 30
    assert np.any(y[Z] == 0) and np.any(y[Z] != 0)


def test_sparse_model_flags_false_contacts_and_its_elbo_never_decreases() -> None:
    X, y, out = circle()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        model = SparseRobustGPIS(n_inducing=60).fit(X, y)
    assert model.inducing_.shape[0] <= 60
    trace = np.asarray(model.elbo_trace_)
    assert np.all(np.diff(trace) >= -1e-9 * np.abs(trace[1:]))
    u = model.uncertainty_
    contacts = np.setdiff1d(np.flatnonzero(y == 0), out)
    assert u[out].min() > 10 * np.median(u[contacts])
    # The mean surface is the unit circle.
    th = np.linspace(0, 2 * np.pi, 50)
    on = model.predict(np.c_[np.cos(th), np.sin(th)])
    assert np.median(np.abs(on)) < 0.1
    mean, std = model.predict(np.c_[np.cos(th), np.sin(th)] * 3, return_std=True)
    assert np.all(std >= 0) and mean.shape == (50,)


def test_warm_start_on_appended_data_keeps_the_flags_in_fewer_iterations() -> None:
    X, y, out = circle(n_c=100, n_free=70)
    keep = np.ones(X.shape[0], dtype=bool)
    keep[[5, 17, 60, 110]] = False  # a few rows arrive later
    order = np.r_[np.flatnonzero(keep), np.flatnonzero(~keep)]
    X, y = X[order], y[order]
    out = np.flatnonzero(np.isin(order, out))
    n0 = int(keep.sum())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        model = SparseRobustGPIS(n_inducing=60, warm_start=True).fit(X[:n0], y[:n0])
        cold_iter = model.n_iter_
        model.fit(X, y)
    assert model.n_iter_ < cold_iter
    contacts = np.setdiff1d(np.flatnonzero(y == 0), out)
    assert model.uncertainty_[out].min() > 10 * np.median(model.uncertainty_[contacts])


def test_fixed_inducing_array_and_bad_settings() -> None:
    X, y, _ = circle(n_c=40, n_free=30, n_out=2)
    Z = X[::4]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        model = SparseRobustGPIS(inducing=Z, max_iter=20).fit(X, y)
    np.testing.assert_array_equal(model.inducing_, Z)
    with pytest.raises(InputDataError, match="inducing"):
        SparseRobustGPIS(inducing=np.zeros((4, 3))).fit(X, y)
    with pytest.raises(ConfigError, match="inducing"):
        SparseRobustGPIS(inducing="kmeans").fit(X, y)
    with pytest.raises(ConfigError, match="jitter"):
        SparseRobustGPIS(jitter=0.0).fit(X, y)


def test_sparse_and_exact_agree_when_every_point_is_inducing() -> None:
    X, y, out = circle(n_c=50, n_free=40, n_out=3)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        exact = RobustGPIS().fit(X, y)
        sparse = SparseRobustGPIS(inducing=X, jitter=1e-9).fit(X, y)
    # Both detect the same outliers and trace the same zero set (the EM basins may differ in
    # raw hyperparameters, ALGORITHM.md §7.6).
    top_e = set(np.argsort(exact.uncertainty_)[-3:])
    top_s = set(np.argsort(sparse.uncertainty_)[-3:])
    assert top_e == top_s == set(out.tolist())
    th = np.linspace(0, 2 * np.pi, 40)
    ring = np.c_[np.cos(th), np.sin(th)]
    assert math.isclose(np.median(np.abs(sparse.predict(ring))), 0.0, abs_tol=0.1)


def test_sample_weight_equals_repeated_rows() -> None:
    """A row of weight c is c coincident observations (the merged-cell multiplicity)."""

    rng = np.random.default_rng(0)
    X = rng.uniform(0.0, 1.0, (30, 2))
    y = np.where(X[:, 0] > 0.6, 1.0, np.where(X[:, 0] < 0.4, -1.0, 0.0))
    y[3] = 1.0  # an outlier
    c = rng.integers(1, 4, 30)
    Xd, yd = np.repeat(X, c, axis=0), np.repeat(y, c)
    for cls, kw in ((RobustGPIS, {}), (SparseRobustGPIS, {"inducing": X[::2].copy()})):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            a = cls(max_iter=20, init="prior", **kw).fit(Xd, yd)
            b = cls(max_iter=20, init="prior", **kw).fit(X, y, sample_weight=c)
            plain = cls(max_iter=20, init="prior", **kw).fit(X, y)
        np.testing.assert_allclose(b.predict(X), a.predict(X), atol=1e-6)
        np.testing.assert_allclose(b.elbo_trace_, a.elbo_trace_, rtol=1e-6, atol=1e-4)
        assert np.abs(plain.predict(X) - a.predict(X)).max() > 1e-3
    with pytest.raises(ConfigError, match="sample_weight"):
        RobustGPIS().fit(X, y, sample_weight=np.zeros(30))
