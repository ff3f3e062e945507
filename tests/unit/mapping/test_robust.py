"""Robust GPIS (ALGORITHM.md §10 "Recommended tests"): bound terms against quadrature and a
dense textbook implementation, ELBO monotonicity, gradients, limits, outlier detection, warm
start, chunking and input checks."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import scipy.linalg
from scipy import integrate, stats
from scipy.special import digamma, gammaln
from threadpoolctl import threadpool_limits

from groundstation.errors import ConfigError, ConvergenceWarning, InputDataError, NotFittedError
from groundstation.mapping import GPIS, RobustGPIS
from groundstation.mapping._linalg import FrozenPosterior, factorize, factorize_blocks
from groundstation.mapping.kernels import se_from_sq_dists, se_kernel, sq_dists
from groundstation.mapping.robust import (
    collapsed_elbo,
    direct_update,
    elbo,
    em_update,
    kl_tau,
    log_gamma_ratio_half,
    optimal_beta,
    site_bound_sum,
)

assert scipy.linalg  # loaded before the thread limit below so it applies to its BLAS too


@pytest.fixture(autouse=True, scope="module")
def _single_thread_blas():
    # Tiny matrices: threaded OpenBLAS only adds contention on shared 2-core machines.
    with threadpool_limits(1):
        yield


def circle(n_c=60, n_free=60, n_out=6, seed=1):
    """ALGORITHM.md §7 data: contacts on the unit circle with 2 % radial noise, free space in
    1.25 < r < 2, one interior anchor, and ``n_out`` false contacts (y = 0) in free space.

    Returns X (n, 2), y (n,), indices of the planted outliers.
    """
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
            [[0.0, 0.0]],
            np.c_[ro * np.cos(to), ro * np.sin(to)],
        ]
    )
    y = np.r_[np.zeros(n_c), np.ones(n_free), -1.0, np.zeros(n_out)]
    return X, y, np.arange(len(y) - n_out, len(y))


def clarity(X, u, out):
    """Paper's Q_o = mean u of normal data within 0.5 m of outlier o / u_o (small = clear), and
    whether every outlier's u exceeds every such neighbour's u."""
    inl = np.setdiff1d(np.arange(len(u)), out)
    q, exceeds = [], True
    for o in out:
        near = inl[np.linalg.norm(X[inl] - X[o], axis=1) < 0.5]
        assert near.size > 0
        q.append(u[near].mean() / u[o])
        exceeds &= bool(u[o] > u[near].max())
    return max(q), exceeds


# ----------------------------------------------------------------------- bound terms


def test_inverse_gamma_kl_matches_quadrature() -> None:
    for at, bt, a, b in [(2.5, 4.3, 2.0, 4.0), (0.7, 0.01, 0.2, 0.002), (60.5, 3.0, 60.0, 2.5)]:
        q, p = stats.invgamma(at, scale=bt), stats.invgamma(a, scale=b)

        def integrand(t, q=q, p=p):
            tau = math.exp(t)
            return q.pdf(tau) * (q.logpdf(tau) - p.logpdf(tau)) * tau

        mode = math.log(bt / (at + 1))
        val, _ = integrate.quad(integrand, mode - 30, mode + 30, points=[mode], limit=400)
        assert kl_tau(np.array([at]), np.array([bt]), a, b)[0] == pytest.approx(
            val, rel=1e-7, abs=1e-10
        )


def test_site_bound_is_student_t_density_and_optimum_over_q_tau() -> None:
    alpha, beta = 1.3, 0.07
    s = np.array([0.0004, 0.3, 2.0])
    for si in s:
        # With A_ii = 0, L4 is log int N(r | 0, tau) IG(tau | alpha, beta) dtau (Student-t).
        r = math.sqrt(si)

        def integrand(t, r=r):
            tau = math.exp(t)
            return (
                stats.norm.pdf(r, scale=math.sqrt(tau))
                * stats.invgamma.pdf(tau, alpha, scale=beta)
                * tau
            )

        val, _ = integrate.quad(integrand, -40, 15, limit=400)
        assert float(site_bound_sum(alpha, beta, np.array([si]))) == pytest.approx(
            math.log(val), rel=1e-8
        )
    # L4 = max over q(tau_i) of l_i - KL_tau_i, attained at E3/E4.
    at, bt = np.full(3, alpha + 0.5), beta + 0.5 * s

    def sites(at, bt):
        ell = -0.5 * math.log(2 * math.pi) - 0.5 * (np.log(bt) - digamma(at)) - 0.5 * at / bt * s
        return ell - kl_tau(at, bt, alpha, beta)

    np.testing.assert_allclose(
        sites(at, bt), [site_bound_sum(alpha, beta, s[i : i + 1]) for i in range(3)], rtol=1e-12
    )
    for fa, fb in [(1.1, 1.0), (0.9, 1.0), (1.0, 1.1), (1.0, 0.9)]:
        assert np.all(sites(at * fa, bt * fb) < sites(at, bt))


def test_log_gamma_ratio_is_continuous_across_the_series_switch() -> None:
    a = np.array([99.999999, 100.0, 100.000001, 20.0])
    v = log_gamma_ratio_half(a)
    assert abs(v[0] - v[1]) < 1e-8 and abs(v[2] - v[1]) < 1e-8
    assert v[3] == pytest.approx(gammaln(20.5) - gammaln(20.0), rel=1e-14)


def test_em_m_step_is_stationary_and_direct_update_is_not_beaten() -> None:
    rng = np.random.default_rng(0)
    s = np.r_[rng.exponential(0.01, 50), rng.exponential(1.0, 5)]
    at, bt = np.full(55, 2.5), 4.0 + 0.5 * s
    a, b = em_update(at, bt, (1e-3, 1e6), 1e-6)

    def J(a, b):  # sum_i E_q log IG(tau_i | a, b)   (M1/M2 maximise this)
        return np.sum(
            a * np.log(b) - gammaln(a) - (a + 1) * (np.log(bt) - digamma(at)) - b * at / bt
        )

    h = 1e-6
    grad_a = (J(a * (1 + h), b) - J(a * (1 - h), b)) / (2 * h * a)
    grad_b = (J(a, b * (1 + h)) - J(a, b * (1 - h))) / (2 * h * b)
    assert abs(grad_a) < 1e-4 and abs(grad_b) < 1e-4
    a, b = direct_update(s, 2.0, (1e-3, 1e6), 1e-6)
    best = float(site_bound_sum(a, b, s))
    for fa in (0.9, 1.0, 1.1):
        for fb in (0.9, 1.0, 1.1):
            assert float(site_bound_sum(a * fa, b * fb, s)) <= best + 1e-9
    # the beta root of M1' for that alpha
    assert np.mean(b / (b + s / 2)) == pytest.approx(a / (a + 0.5), rel=1e-12)
    # all-alike residuals: the profile's optimum is the Gaussian limit (ALGORITHM.md §7.3)
    a_g, _ = direct_update(np.full(40, 0.01), 2.0, (1e-3, 1e6), 1e-6)
    assert a_g > 1e5
    # exactly interpolated data: beta sits on its floor (§7.4)
    assert optimal_beta(2.0, np.r_[np.zeros(50), 1.0], 1e-6)[0] == 1e-6


# ----------------------------------------------------------------------- dense oracle


def dense_state(X, y, ell, sf2, w, mu0):
    """Textbook q(f) and KL_f with K^-1 (only valid at a moderate length scale, ALGORITHM.md §6)."""
    K = se_kernel(X, None, ell, sf2)
    assert np.linalg.cond(K) < 1e8
    Kinv = np.linalg.inv(K)
    A = np.linalg.inv(Kinv + np.diag(w))
    m = mu0 + A @ (w * (y - mu0))
    n = len(y)
    kl_f = 0.5 * (
        np.trace(Kinv @ A)
        + (m - mu0) @ Kinv @ (m - mu0)
        - n
        + np.linalg.slogdet(K)[1]
        - np.linalg.slogdet(A)[1]
    )
    return m, A, kl_f


def test_b_form_matches_dense_and_collapsed_bound_equals_full_bound() -> None:
    X, y, _ = circle(20, 20, 2)
    D = sq_dists(X)
    ell, sf2, mu0 = 0.35, 0.8, 0.1
    rng = np.random.default_rng(2)
    at = np.full(len(y), 1.7)
    bt = rng.uniform(0.01, 2.0, len(y))
    w = at / bt
    fac = factorize(se_from_sq_dists(D, ell, sf2), D, w, y - mu0, mu0, ell)
    m, A, kl_f = dense_state(X, y, ell, sf2, w, mu0)
    np.testing.assert_allclose(fac.m, m, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(fac.diag_A, np.diag(A), rtol=1e-8, atol=1e-12)
    assert fac.kl_f == pytest.approx(kl_f, rel=1e-9)
    s = (y - fac.m) ** 2 + fac.diag_A
    l2 = elbo(fac.kl_f, s, at, bt, 1.2, 0.3)
    l2_dense = elbo(kl_f, (y - m) ** 2 + np.diag(A), at, bt, 1.2, 0.3)
    assert l2 == pytest.approx(l2_dense, abs=1e-8)
    # L3 == L2 at the optimal q(f)
    assert collapsed_elbo(fac, at, bt, 1.2, 0.3) == pytest.approx(l2, abs=1e-9)


def test_block_factor_matches_the_dense_inverse() -> None:
    """The mixture's lean factorisation: P's blocks, the mean and the evidence against the
    dense ``(K + W^-1)^-1`` and the full factorisation."""
    X, y, _ = circle(20, 20, 2)
    D = sq_dists(X)
    ell, sf2, mu0 = 0.35, 0.8, 0.1
    w = np.random.default_rng(3).uniform(0.5, 400.0, len(y))
    K = se_from_sq_dists(D, ell, sf2)
    P = np.linalg.inv(K + np.diag(1.0 / w))
    rows = np.array([7, 3, 30, 31, 12])
    blk = factorize_blocks(K, w, y - mu0, mu0, rows)
    full = factorize(K, None, w, y - mu0, mu0, ell)
    np.testing.assert_allclose(blk.P_block(slice(0, 2)), P[np.ix_([7, 3], [7, 3])], rtol=1e-9)
    np.testing.assert_allclose(blk.P_block(slice(2, 5)), P[np.ix_(rows[2:], rows[2:])], rtol=1e-9)
    np.testing.assert_allclose(blk.a, P @ (y - mu0), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(blk.m, full.m, rtol=1e-12, atol=1e-14)  # rows reordered
    assert blk.log_marginal(w) == pytest.approx(full.log_marginal(w), rel=1e-12)
    # its Cholesky factor has the rows asked for last: B in that order
    o = blk.order
    np.testing.assert_array_equal(o[-rows.size :], rows)
    sw = np.sqrt(w)[o]
    B = np.eye(len(y)) + sw[:, None] * K[np.ix_(o, o)] * sw[None, :]
    np.testing.assert_allclose(blk.L @ blk.L.T, B, rtol=1e-12, atol=1e-12)


def test_each_coordinate_step_raises_the_dense_bound() -> None:
    X, y, _ = circle(20, 20, 2)
    D = sq_dists(X)
    ell, sf2 = 0.35, 0.8
    K = se_from_sq_dists(D, ell, sf2)
    alpha, beta = 2.0, 4.0
    at, bt = np.full(len(y), alpha), np.full(len(y), beta)
    m, A, kl_f = dense_state(X, y, ell, sf2, at / bt, 0.0)
    values = [elbo(kl_f, (y - m) ** 2 + np.diag(A), at, bt, alpha, beta)]
    for _ in range(3):
        s = (y - m) ** 2 + np.diag(A)
        at, bt = np.full(len(y), alpha + 0.5), beta + 0.5 * s  # q(tau): E3/E4
        values.append(elbo(kl_f, s, at, bt, alpha, beta))
        alpha, beta = em_update(at, bt, (1e-3, 1e6), 1e-6)  # (alpha, beta): M1/M2
        values.append(elbo(kl_f, s, at, bt, alpha, beta))
        m, A, kl_f = dense_state(X, y, ell, sf2, at / bt, 0.0)  # q(f): E1/E2
        values.append(elbo(kl_f, (y - m) ** 2 + np.diag(A), at, bt, alpha, beta))
        fac = factorize(K, D, at / bt, y, 0.0, ell)
        assert collapsed_elbo(fac, at, bt, alpha, beta) == pytest.approx(values[-1], abs=1e-8)
    assert np.all(np.diff(values) > 0)


def test_kernel_gradient_m3_matches_central_differences() -> None:
    X, y, _ = circle(25, 25, 3)
    D = sq_dists(X)
    w = np.random.default_rng(4).uniform(0.5, 500.0, len(y))
    r = y - 0.2

    def lml(theta):
        ell, sf2 = np.exp(theta)
        fac = factorize(se_from_sq_dists(D, ell, sf2), D, w, r, 0.2, ell)
        return fac.log_marginal(w), fac.grad

    theta = np.log([0.45, 1.3])
    _, grad = lml(theta)
    for j, h in enumerate([1e-5, 1e-5]):
        e = np.zeros(2)
        e[j] = h
        fd = (lml(theta + e)[0] - lml(theta - e)[0]) / (2 * h)
        assert abs(grad[j] - fd) <= 1e-5 * abs(fd), (j, grad[j], fd)


def test_gaussian_limit_equals_gpis() -> None:
    """alpha -> inf with beta = alpha sigma^2: q(tau) collapses on sigma^2 (ALGORITHM.md §1)."""
    X, y, _ = circle(30, 30, 3)
    ell, sf2, sn2 = 0.5, 0.9, 0.03
    gp = GPIS(lengthscale=ell, signal_var=sf2, noise_var=sn2, optimize=False).fit(X, y)
    D = sq_dists(X)
    K = se_from_sq_dists(D, ell, sf2)
    alpha = 1e9
    beta = alpha * sn2
    s = (y - gp.predict(X)) ** 2 + gp.uncertainty_  # any q(f) will do in the limit
    at, bt = np.full(len(y), alpha + 0.5), beta + 0.5 * s  # E3/E4
    fac = factorize(K, D, at / bt, y, 0.0, ell)
    post = FrozenPosterior(X, X.mean(axis=0), fac.a, fac.L, fac.sw, 0.0, ell, sf2)
    Xs = np.random.default_rng(0).uniform(-2, 2, (80, 2))
    m_r, s_r = post.predict(Xs, return_std=True)
    m_g, s_g = gp.predict(Xs, return_std=True)
    np.testing.assert_allclose(m_r, m_g, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(s_r, s_g, rtol=1e-5, atol=1e-5)
    l3 = collapsed_elbo(fac, at, bt, alpha, beta)
    assert l3 == pytest.approx(gp.log_marginal_likelihood_, rel=1e-5)


def test_prediction_is_the_papers_heteroscedastic_gp() -> None:
    X, y, _ = circle(40, 40, 4)
    model = RobustGPIS(lengthscale=0.5, optimize=False, beta_floor=1e-3).fit(X, y)
    Sigma = np.diag(model.uncertainty_)  # Sigma = diag(beta~/alpha~)
    K = se_kernel(X, None, model.lengthscale_, model.signal_var_)
    Xs = np.random.default_rng(1).uniform(-2, 2, (60, 2))
    Ks = se_kernel(X, Xs, model.lengthscale_, model.signal_var_)
    mean = Ks.T @ np.linalg.solve(K + Sigma, y)
    var = model.signal_var_ - np.einsum("ij,ij->j", Ks, np.linalg.solve(K + Sigma, Ks))
    m, s = model.predict(Xs, return_std=True)
    np.testing.assert_allclose(m, mean, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(s, np.sqrt(var), rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(model.weights_, 1.0 / model.uncertainty_)
    np.testing.assert_allclose(model.uncertainty_, model.beta_tilde_ / model.alpha_tilde_)


# ----------------------------------------------------------------------- the EM


@pytest.mark.parametrize("noise_update", ["direct", "em"])
@pytest.mark.parametrize("kernel_step", ["rprop", "lbfgs"])
@pytest.mark.parametrize(("init", "optimize"), [("gpis", True), ("prior", True), ("prior", False)])
def test_elbo_never_decreases(noise_update, kernel_step, init, optimize) -> None:
    if kernel_step == "lbfgs" and not optimize:
        pytest.skip("kernel_step is unused with optimize=False")
    X, y, _ = circle(40, 40, 4)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        model = RobustGPIS(
            noise_update=noise_update,
            kernel_step=kernel_step,
            init=init,
            optimize=optimize,
            max_iter=50,
        ).fit(X, y)
    trace = np.asarray(model.elbo_trace_)
    assert len(trace) == model.n_iter_ + 1 and np.all(np.isfinite(trace))
    assert np.all(np.diff(trace) >= -1e-9 * np.maximum(1.0, np.abs(trace[1:])))
    assert trace[-1] > trace[0]
    assert model.beta_ >= model.beta_floor and 1e-3 <= model.alpha_ <= 1e6


def test_false_contacts_are_flagged_by_the_default_model() -> None:
    X, y, out = circle()
    model = RobustGPIS().fit(X, y)
    assert model.converged_
    q, exceeds = clarity(X, model.uncertainty_, out)
    assert exceeds and q < 0.25
    # the mean surface is robust: the false contacts sit well inside "outside"
    assert np.all(model.predict(X[out]) > 0.3)
    # the homoscedastic GPIS variance does not single them out (ALGORITHM.md §7.7)
    gp = GPIS().fit(X, y)
    assert clarity(X, gp.uncertainty_, out)[0] > 0.1


def test_literal_em_stalls_from_paper_beta_but_not_from_small_beta() -> None:
    """ALGORITHM.md §7.1: from beta = 4 nobody is down-weighted; beta0 = 0.02 or the direct
    update separate the false contacts."""
    X, y, out = circle()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        stalled = RobustGPIS(noise_update="em", beta=4.0, init="prior").fit(X, y)
    assert clarity(X, stalled.uncertainty_, out)[0] > 0.5
    assert stalled.beta_ > 1.0
    small = RobustGPIS(noise_update="em", beta=0.02, init="prior").fit(X, y)
    q, exceeds = clarity(X, small.uncertainty_, out)
    assert exceeds and q < 0.25
    direct = RobustGPIS(noise_update="direct", beta=4.0, init="prior").fit(X, y)
    q, exceeds = clarity(X, direct.uncertainty_, out)
    assert exceeds and q < 0.25


@pytest.mark.parametrize("eps", [0.0, 1e-9])
def test_duplicate_inputs_fit(eps: float) -> None:
    X, y, out = circle(40, 40, 4)
    X = np.vstack([X, X[:12] + eps, X[out[:1]] + eps])
    y = np.r_[y, y[:12], 0.0]
    model = RobustGPIS().fit(X, y)
    mean, std = model.predict(X, return_std=True)
    assert np.all(np.isfinite(mean)) and np.all(np.isfinite(std))
    assert np.all(np.isfinite(model.uncertainty_)) and np.all(np.isfinite(model.elbo_trace_))


def test_chunked_prediction_equals_unchunked() -> None:
    X, y, _ = circle(40, 40, 4)
    model = RobustGPIS().fit(X, y)
    Xs = np.random.default_rng(3).uniform(-2, 2, (257, 2))
    m_full, s_full = model.predict(Xs, return_std=True)
    model.chunk_mb = 1e-3
    m_chunk, s_chunk = model.predict(Xs, return_std=True)
    np.testing.assert_allclose(m_chunk, m_full, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(s_chunk, s_full, rtol=1e-11, atol=1e-11)
    assert model.posterior_.chunk_rows(64.0, True) * 8 * 3 * len(X) <= 64e6


def test_warm_start_on_appended_data_is_faster_and_gives_the_same_flags() -> None:
    X, y, out = circle(70, 70, 6, seed=2)
    perm = np.random.default_rng(2).permutation(len(y))
    X, y, is_out = X[perm], y[perm], np.isin(perm, out)
    k = int(0.95 * len(y))
    warm = RobustGPIS(warm_start=True).fit(X[:k], y[:k])
    warm.fit(X, y)  # old rows first, 5 % new rows appended
    cold = RobustGPIS().fit(X, y)
    assert warm.converged_ and warm.n_iter_ < cold.n_iter_
    flags_warm = warm.uncertainty_ > 100 * np.median(warm.uncertainty_)
    flags_cold = cold.uncertainty_ > 100 * np.median(cold.uncertainty_)
    assert np.array_equal(flags_warm, flags_cold) and flags_cold[is_out].all()
    assert warm.elbo_trace_[-1] == pytest.approx(cold.elbo_trace_[-1], rel=1e-3)
    # data that is not an extension of the previous set still fits
    warm.fit(X[::-1], y[::-1])
    assert np.all(np.isfinite(warm.uncertainty_))


def test_three_dimensional_sphere_with_false_contacts() -> None:
    rng = np.random.default_rng(0)
    v = rng.standard_normal((90, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    X = np.vstack([v[:70], 1.6 * v[70:85], [[0, 0, 0]], 1.5 * v[85:]])
    y = np.r_[np.zeros(70), np.ones(15), -1.0, np.zeros(5)]
    model = RobustGPIS().fit(X, y)
    u = model.uncertainty_
    assert np.all(u[-5:] > 100 * np.median(u[:70]))


def test_iteration_limit_warns() -> None:
    X, y, _ = circle(40, 40, 4)
    with pytest.warns(ConvergenceWarning, match="max_iter"):
        model = RobustGPIS(max_iter=2).fit(X, y)
    assert not model.converged_ and model.n_iter_ == 2


def test_predict_before_fit_raises() -> None:
    with pytest.raises(NotFittedError):
        RobustGPIS().predict(np.zeros((1, 2)))


def test_bad_input_is_named() -> None:
    X, y, _ = circle(10, 10, 1)
    X[[4, 7], 1] = np.nan
    with pytest.raises(InputDataError, match=r"rows \[4, 7\]"):
        RobustGPIS().fit(X, y)
    with pytest.raises(InputDataError, match="no contact"):
        RobustGPIS().fit(np.zeros((3, 2)), np.ones(3))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"noise_update": "kuss"}, "noise_update"),
        ({"kernel_step": "adam"}, "kernel_step"),
        ({"init": "zero"}, "init"),
        ({"lengthscale": -0.25}, "lengthscale"),
        ({"beta": 1e-9}, "beta_floor"),
        ({"alpha_bounds": (0.0, 1.0)}, "alpha_bounds"),
        ({"tol": 0.0}, "tol"),
    ],
)
def test_bad_settings_raise_config_error_at_fit(kwargs, match) -> None:
    X, y, _ = circle(10, 10, 1)
    model = RobustGPIS(**kwargs)
    with pytest.raises(ConfigError, match=match):
        model.fit(X, y)


def test_blas_threads_limits_every_pool_and_restores_it():
    from threadpoolctl import threadpool_info

    from groundstation.mapping._linalg import blas_threads

    before = [i["num_threads"] for i in threadpool_info()]
    for _ in range(2):  # the cached pools serve a second use too
        with blas_threads(1):
            assert all(i["num_threads"] == 1 for i in threadpool_info())
        assert [i["num_threads"] for i in threadpool_info()] == before
    with blas_threads(0):  # 0: the process setting is left alone
        assert [i["num_threads"] for i in threadpool_info()] == before
