"""Robust GPIS: Student-t GP implicit surface fitted by variational EM (ALGORITHM.md).

Model ``y_i ~ N(f_i, tau_i)``, ``tau_i ~ InvGamma(alpha, beta)``, ``f ~ GP(mu0, k)``; the
posterior ``q(f) q(tau)`` is fitted by coordinate ascent on the ELBO L2 (§5). The score
``u_i = beta~_i / alpha~_i`` flags false-positive contacts; prediction is the GP with noise
``Sigma = diag(u)``.
"""

from __future__ import annotations

import math
import warnings

import numpy as np
from scipy.optimize import brentq, minimize, minimize_scalar
from scipy.special import digamma, gammaln

from groundstation.errors import ConfigError, ConvergenceWarning
from groundstation.mapping._linalg import LOG_2PI, BFactor, FrozenPosterior, factorize
from groundstation.mapping.gpis import fit_gpis
from groundstation.mapping.kernels import se_from_sq_dists, sq_dists
from groundstation.mapping.validation import (
    check_bounds,
    check_choice,
    check_finite,
    check_fitted,
    check_inputs,
    check_int,
    check_positive,
    check_training_data,
)

ALPHA_GRID_POINTS = 57  # ALGORITHM.md §4.1: global 1-D profile search in log alpha
LBFGS_STEPS = 5  # L-BFGS-B iterations per EM iteration (kernel_step="lbfgs")
RPROP_START, RPROP_UP, RPROP_DOWN = 0.5, 1.2, 0.5  # ALGORITHM.md §4.2
RPROP_MIN, RPROP_MAX = 1e-8, 4.0
PATIENCE = 3  # ALGORITHM.md §5: tol met on 3 consecutive iterations
# The GPIS initialisation only has to land in the right basin; the EM refines theta. A loose
# tolerance halves its cost at n = 2700 (each L-BFGS-B evaluation is one factorisation).
GPIS_INIT_MAX_ITER, GPIS_INIT_TOL = 50, 1e-4
# init="auto": a cold fit that ends with alpha at or above this sits on the Gaussian plateau
# (every u_i ~ beta/alpha, nothing can be flagged; ALGORITHM.md §7.3). It is then also started
# from the heavy-tailed side, q(tau) = prior with a small beta (§7.1, beta0 = 0.02), and the
# start with the higher final ELBO L2 wins (§7.6: compare optima on the ELBO).
PLATEAU_ALPHA = 1e4
HEAVY_START_BETA = 0.02


# --------------------------------------------------------------------------- bound terms


def log_gamma_ratio_half(alpha: np.ndarray | float) -> np.ndarray:
    """``ln Gamma(alpha + 1/2) - ln Gamma(alpha)`` without cancellation at large alpha.

    The gammaln difference loses ~1e-16 ln Gamma(alpha) (1e-9 at alpha = 1e6, the Gaussian
    limit), enough to break the 1e-9 monotonicity check; above alpha = 100 use the asymptotic
    series ``1/2 ln a - 1/(8a) + 1/(192 a^3) - 1/(640 a^5)`` (error < 1e-14 there).
    """
    a = np.asarray(alpha, dtype=np.float64)
    big = np.maximum(a, 100.0)
    series = 0.5 * np.log(big) - 1.0 / (8.0 * big) + 1.0 / (192.0 * big**3) - 1.0 / (640.0 * big**5)
    small = np.minimum(a, 100.0)
    return np.where(a >= 100.0, series, gammaln(small + 0.5) - gammaln(small))


def kl_tau(at: np.ndarray, bt: np.ndarray, alpha: float, beta: float) -> np.ndarray:
    """``KL(IG(at, bt) || IG(alpha, beta))`` per datum (ALGORITHM.md L2c).

    Written with ``ln(bt/beta)`` and, where ``at = alpha + 1/2`` (E3), the stable
    ``ln Gamma(alpha + 1/2) - ln Gamma(alpha)``, so the terms stay accurate near alpha = 1e6.
    """
    half = at == alpha + 0.5
    lg = np.where(half, -log_gamma_ratio_half(alpha), gammaln(alpha) - gammaln(at))
    return (at - alpha) * digamma(at) + lg + alpha * np.log(bt / beta) - at * (bt - beta) / bt


def elbo(
    kl_f: float,
    s: np.ndarray,
    at: np.ndarray,
    bt: np.ndarray,
    alpha: float,
    beta: float,
    c: np.ndarray | None = None,
) -> float:
    """Full ELBO L2 = sum l_i - KL_f - sum KL_tau_i (ALGORITHM.md L2, L2a).

    ``c`` (n,): multiplicities (a merged cell of ``c_i`` coincident observations; their
    per-datum terms are equal, so they enter ``c_i`` times). None: all ones.
    """
    ell = -0.5 * LOG_2PI - 0.5 * (np.log(bt) - digamma(at)) - 0.5 * (at / bt) * s
    site = ell - kl_tau(at, bt, alpha, beta)
    return float((np.sum(site) if c is None else float(c @ site)) - kl_f)


def collapsed_elbo(
    fac: BFactor, at: np.ndarray, bt: np.ndarray, alpha: float, beta: float
) -> float:
    """Collapsed bound L3 at the optimal ``q(f)`` for ``w = at/bt`` (ALGORITHM.md L3, L1)."""
    w = at / bt
    e_log_tau = np.log(bt) - digamma(at)
    return float(
        fac.log_marginal(w)
        - 0.5 * np.sum(e_log_tau + np.log(w))
        - np.sum(kl_tau(at, bt, alpha, beta))
    )


def site_bound_sum(
    alpha: np.ndarray | float, beta: np.ndarray | float, s: np.ndarray, c: np.ndarray | None = None
) -> np.ndarray:
    """``sum_i L4_i(alpha, beta; s_i)`` broadcast over (alpha, beta) arrays (ALGORITHM.md L4).

    Rearranged as ``sum_i [lnG(a+1/2) - lnG(a) - ln(2 pi)/2 - a ln(1 + h_i/b) - ln(b + h_i)/2]``
    with ``h = s/2``: no O(alpha) terms cancel, so the profile stays smooth up to alpha = 1e6.
    ``c`` (n,): multiplicities of the sites (None: ones).
    """
    alpha = np.asarray(alpha, dtype=np.float64)
    beta = np.asarray(beta, dtype=np.float64)
    h = 0.5 * s
    b = beta[..., None]
    if c is None:
        n = s.shape[0]
        log1p_sum = np.log1p(h / b).sum(axis=-1)
        log_sum = np.log(b + h).sum(axis=-1)
    else:
        n = float(np.sum(c))
        log1p_sum = np.log1p(h / b) @ c
        log_sum = np.log(b + h) @ c
    return n * (log_gamma_ratio_half(alpha) - 0.5 * LOG_2PI) - alpha * log1p_sum - 0.5 * log_sum


def optimal_beta(
    alpha: np.ndarray | float, s: np.ndarray, floor: float, c: np.ndarray | None = None
) -> np.ndarray:
    """Maximiser over ``beta >= floor`` of sum L4 for fixed alpha (ALGORITHM.md §4.1).

    Root of ``(alpha + 1/2) sum_i beta / (beta + s_i/2) = n alpha``, written as
    ``G(beta) = mean_i h_i / (beta + h_i) - 1 / (2 alpha + 1) = 0`` with ``h = s/2`` (no
    ``1 - x`` cancellation near the Gaussian limit). G decreases in beta; bracketed Newton in
    log beta (bisection whenever Newton leaves the bracket), vectorised over ``alpha``.
    Returns an array shaped like ``atleast_1d(alpha)``. ``c``: site multiplicities (means
    become ``c``-weighted means).
    """
    alpha = np.atleast_1d(np.asarray(alpha, dtype=np.float64))
    h = 0.5 * s
    target = 1.0 / (2.0 * alpha + 1.0)
    cw = None if c is None else c / float(np.sum(c))

    def G_and_slope(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        b = np.exp(t)[:, None]
        frac = h / (b + h)
        if cw is None:
            return frac.mean(axis=1) - target, -(frac * (1.0 - frac)).mean(axis=1)
        return frac @ cw - target, -((frac * (1.0 - frac)) @ cw)

    lo = np.full(alpha.shape, math.log(floor))
    at_floor = G_and_slope(lo)[0] <= 0.0
    # G <= 0 once beta >= (2 alpha + 1) mean(h): bracket [floor, 2 (2 alpha + 1) mean(h)].
    mean_h = float(np.mean(h)) if cw is None else float(h @ cw)
    hi = np.log(np.maximum((2.0 * alpha + 1.0) * mean_h, floor) * 2.0)
    t = 0.5 * (lo + hi)
    for _ in range(100):
        G, slope = G_and_slope(t)
        pos = G > 0.0  # root lies above t
        lo = np.where(pos, t, lo)
        hi = np.where(pos, hi, t)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_new = t - G / slope
        outside = ~((t_new > lo) & (t_new < hi))
        root = np.abs(G) <= 1e-15 * target  # exact to rounding: keep t
        t_new = np.where(root, t, np.where(outside, 0.5 * (lo + hi), t_new))
        done = root | (np.abs(t_new - t) <= 1e-12) | (hi - lo <= 1e-12)
        t = t_new
        if np.all(done | at_floor):
            break
    return np.where(at_floor, floor, np.exp(t))


def direct_update(
    s: np.ndarray,
    alpha_old: float,
    alpha_bounds: tuple[float, float],
    floor: float,
    c: np.ndarray | None = None,
) -> tuple[float, float]:
    """Exact joint maximiser of sum L4 over (alpha, beta): grid + bounded Brent (§4.1).

    ``c`` (n,): site multiplicities (None: ones).
    """
    log_lo, log_hi = math.log(alpha_bounds[0]), math.log(alpha_bounds[1])
    grid = np.exp(np.linspace(log_lo, log_hi, ALPHA_GRID_POINTS))
    betas = optimal_beta(grid, s, floor, c)
    vals = site_bound_sum(grid, betas, s, c)
    k = int(np.argmax(vals))
    cands = [(float(vals[k]), float(grid[k]), float(betas[k]))]

    def neg_profile(log_alpha: float) -> float:
        a = math.exp(log_alpha)
        return -float(site_bound_sum(a, optimal_beta(a, s, floor, c)[0], s, c))

    left = math.log(grid[max(k - 1, 0)])
    right = math.log(grid[min(k + 1, grid.size - 1)])
    if right > left:
        res = minimize_scalar(
            neg_profile, bounds=(left, right), method="bounded", options={"xatol": 1e-7}
        )
        a = math.exp(float(res.x))
        cands.append((-float(res.fun), a, float(optimal_beta(a, s, floor, c)[0])))
    if alpha_bounds[0] <= alpha_old <= alpha_bounds[1]:  # never worse than the current alpha
        b = float(optimal_beta(alpha_old, s, floor, c)[0])
        cands.append((float(site_bound_sum(alpha_old, b, s, c)), alpha_old, b))
    _, alpha, beta = max(cands, key=lambda c: c[0])
    return alpha, beta


def em_update(
    at: np.ndarray,
    bt: np.ndarray,
    alpha_bounds: tuple[float, float],
    floor: float,
    c: np.ndarray | None = None,
) -> tuple[float, float]:
    """Literal M-step M1/M2 (Kuss): Gamma ML fit to the precisions under q(tau), beta >= floor.

    ``c`` (n,): site multiplicities (None: ones).
    """
    w = at / bt
    mean_w = float(np.average(w, weights=c))
    mean_elog = float(np.average(np.log(bt) - digamma(at), weights=c))
    lo, hi = alpha_bounds
    c = mean_elog + math.log(mean_w)  # ALGORITHM.md M1

    def h(log_a: float) -> float:
        a = math.exp(log_a)
        return math.log(a) - float(digamma(a)) - c

    alpha = _root_decreasing(h, math.log(lo), math.log(hi))
    beta = alpha / mean_w  # ALGORITHM.md M2
    if beta < floor:
        # Joint concavity: the constrained optimum lies on beta = floor, where
        # d/dalpha = ln beta - psi(alpha) - mean E ln tau = 0.
        beta = floor
        target = math.log(floor) - mean_elog
        alpha = _root_decreasing(
            lambda la: target - float(digamma(math.exp(la))), math.log(lo), math.log(hi)
        )
    return alpha, beta


def _root_decreasing(fn, lo: float, hi: float) -> float:
    """exp(root) of a decreasing ``fn`` on [lo, hi], clamped to the ends."""
    if fn(lo) <= 0.0:
        return math.exp(lo)
    if fn(hi) >= 0.0:
        return math.exp(hi)
    return math.exp(brentq(fn, lo, hi, xtol=1e-12, rtol=1e-14))


# --------------------------------------------------------------------------- estimator


class RobustGPIS:
    """Student-t robust GPIS by variational EM (scikit-learn style; ALGORITHM.md §5).

    Parameters
    ----------
    lengthscale : float, metres
        Initial squared-exponential length scale.
    signal_var : float
        Initial signal variance sigma_f^2 (label units^2).
    alpha, beta : float
        Initial InvGamma(alpha, beta) prior of the per-datum noise variances (paper: 2, 4).
    prior_mean : float
        Constant prior mean mu0 (paper: 0).
    optimize : bool
        Learn (log l, log sigma_f^2) in the M-step; (alpha, beta) are always learnt.
    noise_update : "direct" | "em"
        Exact joint (alpha, beta) maximiser of sum L4 (default) or the literal M1/M2 (§4.1).
    kernel_step : "rprop" | "lbfgs"
        One guarded rprop step or a few L-BFGS-B iterations per EM iteration (§4.2).
    init : "auto" | "gpis" | "prior"
        Start from a homoscedastic GPIS fit (theta and q(f)), from q(tau) = prior, or
        ("auto", default) from the GPIS fit and, when that run ends on the Gaussian plateau
        (alpha >= 1e4), also from q(tau) = IG(alpha, 0.02), keeping the higher final ELBO
        (``init_used_`` tells which won). On a gusty 89-point SITL set the GPIS start
        ended at alpha = 1e6 (ELBO -73.9, no contact distinguishable) and the heavy-tailed
        start at alpha = 0.17 (ELBO -38.5, the gusts flagged).
    max_iter : int
        EM iteration limit.
    tol : float
        Relative ELBO change counted as converged (3 consecutive iterations).
    beta_floor : float
        Lower bound on beta (§7.4).
    alpha_bounds, lengthscale_bounds, signal_var_bounds : (float, float)
    chunk_mb : float
        Memory budget of one prediction chunk, MB.
    warm_start : bool
        Start a refit from the previous fit's (theta, alpha, beta) and q(tau) (§8 "Streaming").

    Attributes
    ----------
    X_train_ : (n, d) float64, metres
    y_train_ : (n,) float64
    lengthscale_, signal_var_, alpha_, beta_ : float
    alpha_tilde_, beta_tilde_ : (n,) float64
        Parameters of q(tau_i) = InvGamma(alpha~_i, beta~_i).
    uncertainty_ : (n,) float64
        ``u_i = beta~_i / alpha~_i``: large values flag false-positive contacts.
    weights_ : (n,) float64
        ``1 / u_i = E[1/tau_i]``.
    elbo_trace_ : list of float
        L2 after each EM iteration, the initial state first.
    n_iter_ : int
    converged_ : bool
    """

    def __init__(
        self,
        lengthscale: float = 0.25,
        signal_var: float = 1.0,
        alpha: float = 2.0,
        beta: float = 4.0,
        prior_mean: float = 0.0,
        optimize: bool = True,
        noise_update: str = "direct",
        kernel_step: str = "rprop",
        init: str = "auto",
        max_iter: int = 200,
        tol: float = 1e-6,
        beta_floor: float = 1e-6,
        alpha_bounds: tuple[float, float] = (1e-3, 1e6),
        lengthscale_bounds: tuple[float, float] = (1e-2, 1e2),
        signal_var_bounds: tuple[float, float] = (1e-3, 1e3),
        chunk_mb: float = 64.0,
        warm_start: bool = False,
    ) -> None:
        self.lengthscale = lengthscale
        self.signal_var = signal_var
        self.alpha = alpha
        self.beta = beta
        self.prior_mean = prior_mean
        self.optimize = optimize
        self.noise_update = noise_update
        self.kernel_step = kernel_step
        self.init = init
        self.max_iter = max_iter
        self.tol = tol
        self.beta_floor = beta_floor
        self.alpha_bounds = alpha_bounds
        self.lengthscale_bounds = lengthscale_bounds
        self.signal_var_bounds = signal_var_bounds
        self.chunk_mb = chunk_mb
        self.warm_start = warm_start

    # ------------------------------------------------------------------ settings

    def _settings(self) -> dict:
        ell = check_positive("lengthscale", self.lengthscale)
        sf2 = check_positive("signal_var", self.signal_var)
        alpha = check_positive("alpha", self.alpha)
        beta = check_positive("beta", self.beta)
        floor = check_positive("beta_floor", self.beta_floor)
        if beta < floor:
            raise ConfigError(f"beta={beta!r} is below beta_floor={floor!r}")
        return {
            "theta": np.log([ell, sf2]),
            "bounds": np.log(
                [
                    check_bounds("lengthscale_bounds", self.lengthscale_bounds, ell, "lengthscale"),
                    check_bounds("signal_var_bounds", self.signal_var_bounds, sf2, "signal_var"),
                ]
            ),
            "alpha": alpha,
            "beta": beta,
            "alpha_bounds": check_bounds("alpha_bounds", self.alpha_bounds, alpha, "alpha"),
            "floor": floor,
            "mu0": check_finite("prior_mean", self.prior_mean),
            "noise_update": check_choice("noise_update", self.noise_update, ("direct", "em")),
            "kernel_step": check_choice("kernel_step", self.kernel_step, ("rprop", "lbfgs")),
            "init": check_choice("init", self.init, ("auto", "gpis", "prior")),
            "optimize": bool(self.optimize),
            "max_iter": check_int("max_iter", self.max_iter, 1),
            "tol": check_positive("tol", self.tol),
            "chunk_mb": check_positive("chunk_mb", self.chunk_mb),
            # Optional early stop (warm refits): max |delta log u_i| below this (set by callers
            # such as ``model.SurfaceModel`` as an attribute; None: ELBO rule only).
            "u_tol": getattr(self, "u_tol", None),
        }

    # ------------------------------------------------------------------ fit

    def fit(
        self, X: np.ndarray, y: np.ndarray, sample_weight: np.ndarray | None = None
    ) -> RobustGPIS:
        """Fit to points ``X`` (n, 2|3) float64 metres with labels ``y`` (n,); returns self.

        ``sample_weight`` (n,) > 0, optional: multiplicity of each row (a merged cell standing
        for ``c_i`` coincident observations: its noise precision is ``c_i w_i`` and its bound
        terms count ``c_i`` times, which is exact for coincident duplicates; ``model.py``).
        The GPIS initialisation ignores it (it only picks the basin).
        """
        cfg = self._settings()
        X, y = check_training_data(X, y)
        n = X.shape[0]
        c = check_sample_weight(sample_weight, n)
        mu0 = cfg["mu0"]
        r = y - mu0
        D = sq_dists(X)
        prev = getattr(self, "posterior_", None)
        warm = self.warm_start and prev is not None and prev.X.shape[1] == X.shape[1]
        em = _EMLoop(D, y, r, mu0, cfg, c)
        if warm:
            state, init_used = em.run(*self._warm_start(cfg, X, y, D, r, c, prev)), "warm"
        elif cfg["init"] == "auto":
            state, init_used = em.run(*self._gpis_start(cfg, D, r, mu0, c)), "gpis"
            if state["alpha"] >= PLATEAU_ALPHA:
                heavy = em.run(*self._prior_start(cfg, D, r, mu0, c, HEAVY_START_BETA))
                if heavy["trace"][-1] > state["trace"][-1]:
                    state, init_used = heavy, "prior"
                del heavy
        elif cfg["init"] == "gpis":
            state, init_used = em.run(*self._gpis_start(cfg, D, r, mu0, c)), "gpis"
        else:
            state, init_used = em.run(*self._prior_start(cfg, D, r, mu0, c, cfg["beta"])), "prior"
        theta, fac, at, bt, alpha, beta = (
            state["theta"],
            state["fac"],
            state["at"],
            state["bt"],
            state["alpha"],
            state["beta"],
        )
        self.init_used_ = init_used
        ell, sf2 = (float(v) for v in np.exp(theta))
        self.X_train_, self.y_train_ = X, y
        self.lengthscale_, self.signal_var_ = ell, sf2
        self.alpha_, self.beta_ = float(alpha), float(beta)
        self.alpha_tilde_, self.beta_tilde_ = at, bt
        self.uncertainty_ = bt / at
        self.weights_ = at / bt
        self.elbo_trace_ = state["trace"]
        self.n_iter_ = state["n_iter"]
        self.converged_ = state["converged"]
        self._rprop_step = state["step"]
        self.posterior_ = FrozenPosterior(X, X.mean(axis=0), fac.a, fac.L, fac.sw, mu0, ell, sf2)
        if not self.converged_:
            warnings.warn(
                f"RobustGPIS EM stopped at max_iter={self.max_iter} before the relative ELBO "
                f"change fell below tol={self.tol} for {PATIENCE} iterations",
                ConvergenceWarning,
                stacklevel=2,
            )
        return self

    # ------------------------------------------------------------------ starts
    # Each returns the arguments of _EMLoop.run: (theta, K, fac, at, bt, alpha, beta, step).

    def _warm_start(self, cfg, X, y, D, r, c, prev) -> tuple:
        """ALGORITHM.md §8 "Streaming": previous (theta, alpha, beta) and q(tau) of kept rows;
        new rows start at q(tau_i) = IG(alpha + 1/2, beta + s_i/2) from predictive moments."""
        n = X.shape[0]
        theta = np.clip(np.log([self.lengthscale_, self.signal_var_]), *cfg["bounds"].T)
        alpha = float(np.clip(self.alpha_, *cfg["alpha_bounds"]))
        beta = max(float(self.beta_), cfg["floor"])
        k = _common_prefix(X, y, self.X_train_, self.y_train_)
        at = np.full(n, alpha + 0.5)
        bt = np.empty(n)
        bt[:k] = self.beta_tilde_[:k]
        at[:k] = self.alpha_tilde_[:k]
        if k < n:
            mean, std = prev.predict(X[k:], return_std=True, chunk_mb=cfg["chunk_mb"])
            bt[k:] = beta + 0.5 * ((y[k:] - mean) ** 2 + std**2)
        step = np.clip(getattr(self, "_rprop_step", np.full(2, RPROP_START)), 1e-3, RPROP_START)
        K = se_from_sq_dists(D, *np.exp(theta))
        fac = factorize(K, D, _prec(at / bt, c), r, cfg["mu0"], math.exp(theta[0]))
        return theta, K, fac, at, bt, alpha, beta, step

    @staticmethod
    def _gpis_start(cfg, D, r, mu0, c) -> tuple:
        """ALGORITHM.md §7.2: theta from a homoscedastic GPIS fit. q(tau) starts as for new
        data in §8 "Streaming", IG(alpha + 1/2, beta + s_i/2), with s_i from the GPIS
        leave-one-out predictive moments (R&W eq. 5.12): an in-sample GPIS posterior often
        interpolates the false contacts (noise at its lower bound), which leaves all s_i alike
        and the EM at the Gaussian limit alpha -> inf (§7.3)."""
        n = D.shape[0]
        g = fit_gpis(
            D,
            r,
            mu0,
            np.append(cfg["theta"], math.log(0.01)),
            np.vstack([cfg["bounds"], np.log([1e-6, 1e1])]),
            cfg["optimize"],
            min(cfg["max_iter"], GPIS_INIT_MAX_ITER),
            max(cfg["tol"], GPIS_INIT_TOL),
        )
        theta, K = g.theta[:2].copy(), g.K
        p_ii = g.factor.diag_P
        s_loo = (g.factor.a / p_ii) ** 2 + np.maximum(1.0 / p_ii - math.exp(g.theta[2]), 0.0)
        alpha, beta = cfg["alpha"], cfg["beta"]
        if cfg["noise_update"] == "direct":
            alpha, beta = direct_update(s_loo, alpha, cfg["alpha_bounds"], cfg["floor"], c)
        at, bt = np.full(n, alpha + 0.5), beta + 0.5 * s_loo
        del g  # release the GPIS factorisation (n x n) before the EM
        fac = factorize(K, D, _prec(at / bt, c), r, mu0, math.exp(theta[0]))
        return theta, K, fac, at, bt, alpha, beta, np.full(2, RPROP_START)

    @staticmethod
    def _prior_start(cfg, D, r, mu0, c, beta0: float) -> tuple:
        """Paper: q(tau_i) = prior IG(alpha0, beta0), w = alpha0 / beta0, theta = initial."""
        n = D.shape[0]
        alpha, beta = cfg["alpha"], max(float(beta0), cfg["floor"])
        theta = cfg["theta"].copy()
        at, bt = np.full(n, alpha), np.full(n, beta)
        K = se_from_sq_dists(D, *np.exp(theta))
        fac = factorize(K, D, _prec(at / bt, c), r, mu0, math.exp(theta[0]))
        return theta, K, fac, at, bt, alpha, beta, np.full(2, RPROP_START)

    def predict(
        self, X: np.ndarray, return_std: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Posterior mean ``mu(X)`` (m,) and, if ``return_std``, latent std (m,).

        The GP with noise ``Sigma = diag(u)`` (paper's predictive equations); ``X`` is (m, d)
        float64, metres; evaluated in chunks of at most ``chunk_mb`` MB.
        """
        check_fitted(self)
        X = check_inputs(X, "X", dims=(self.X_train_.shape[1],))
        return self.posterior_.predict(X, return_std, check_positive("chunk_mb", self.chunk_mb))


def _common_prefix(X: np.ndarray, y: np.ndarray, X_old: np.ndarray, y_old: np.ndarray) -> int:
    """Number of leading rows of (X, y) identical to the previous training rows."""
    k = min(X.shape[0], X_old.shape[0])
    same = np.all(X[:k] == X_old[:k], axis=1) & (y[:k] == y_old[:k])
    return k if same.all() else int(np.argmin(same))


def check_sample_weight(sample_weight, n: int) -> np.ndarray | None:
    """``sample_weight`` as (n,) float64 > 0, or None (all ones)."""
    if sample_weight is None:
        return None
    c = np.asarray(sample_weight, dtype=np.float64).reshape(-1)
    if c.shape != (n,) or not np.all(np.isfinite(c) & (c > 0)):
        raise ConfigError(f"sample_weight must be {n} finite values > 0, got shape {c.shape}")
    return None if np.all(c == 1.0) else c


def _prec(w: np.ndarray, c: np.ndarray | None) -> np.ndarray:
    """Noise precision of each row: ``c_i w_i`` (``c_i`` coincident observations)."""
    return w if c is None else c * w


class _EMLoop:
    """The iteration of ALGORITHM.md §5 for fixed data (``c``: row multiplicities or None)."""

    def __init__(
        self,
        D: np.ndarray,
        y: np.ndarray,
        r: np.ndarray,
        mu0: float,
        cfg: dict,
        c: np.ndarray | None = None,
    ):
        self.D, self.y, self.r, self.mu0, self.cfg, self.c = D, y, r, mu0, cfg, c

    def _factor(self, theta: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, BFactor]:
        ell, sf2 = np.exp(theta)
        K = se_from_sq_dists(self.D, ell, sf2)
        return K, factorize(K, self.D, _prec(w, self.c), self.r, self.mu0, ell)

    def _s(self, fac: BFactor) -> np.ndarray:
        return (self.y - fac.m) ** 2 + fac.diag_A  # s_i = (y_i - m_i)^2 + A_ii

    def run(self, theta, K, fac, at, bt, alpha, beta, step) -> dict:
        cfg, c = self.cfg, self.c
        lo, hi = cfg["bounds"][:, 0], cfg["bounds"][:, 1]
        trace = [elbo(fac.kl_f, self._s(fac), at, bt, alpha, beta, c)]
        g_prev = np.zeros(2)
        calm, converged, n_iter = 0, False, 0
        u_tol = cfg.get("u_tol")
        log_u = np.log(bt / at)
        for n_iter in range(1, cfg["max_iter"] + 1):  # noqa: B007 (reported after the loop)
            s = self._s(fac)
            if cfg["noise_update"] == "direct":
                alpha, beta = direct_update(s, alpha, cfg["alpha_bounds"], cfg["floor"], c)
                at, bt = np.full_like(s, alpha + 0.5), beta + 0.5 * s  # E3/E4
            else:
                at, bt = np.full_like(s, alpha + 0.5), beta + 0.5 * s  # E3/E4
                alpha, beta = em_update(at, bt, cfg["alpha_bounds"], cfg["floor"], c)  # M1/M2
            w = at / bt
            # L2 of the old q(f) under the new q(tau), (alpha, beta): the guard's reference.
            base = elbo(fac.kl_f, s, at, bt, alpha, beta, c)
            if not cfg["optimize"]:
                fac = self._factor_K(K, theta, w)
            elif cfg["kernel_step"] == "rprop":
                # Guarded rprop on M3 from the previous factorisation (ALGORITHM.md §4.2).
                g = fac.grad
                prod = g * g_prev
                step = np.clip(
                    np.where(
                        prod > 0, step * RPROP_UP, np.where(prod < 0, step * RPROP_DOWN, step)
                    ),
                    RPROP_MIN,
                    RPROP_MAX,
                )
                trial = np.clip(theta + np.sign(g) * step, lo, hi)
                accepted = False
                if np.any(trial != theta):
                    K_t, fac_t = self._factor(trial, w)
                    if elbo(fac_t.kl_f, self._s(fac_t), at, bt, alpha, beta, c) >= base:
                        theta, K, fac, accepted = trial, K_t, fac_t, True
                        g_prev = g
                    del K_t, fac_t
                if not accepted:
                    step = step * RPROP_DOWN
                    g_prev = np.zeros(2)
                    fac = self._factor_K(K, theta, w)
            else:
                theta, K, fac = self._lbfgs(theta, K, w, lo, hi)
            trace.append(elbo(fac.kl_f, self._s(fac), at, bt, alpha, beta, c))
            if abs(trace[-1] - trace[-2]) <= cfg["tol"] * max(1.0, abs(trace[-1])):
                calm += 1
            else:
                calm = 0
            if calm >= PATIENCE:
                converged = True
                break
            if u_tol is not None:
                log_u_new = np.log(bt / at)
                if float(np.max(np.abs(log_u_new - log_u), initial=0.0)) < u_tol:
                    converged = True
                    break
                log_u = log_u_new
        return {
            "theta": theta,
            "fac": fac,
            "at": at,
            "bt": bt,
            "alpha": alpha,
            "beta": beta,
            "trace": trace,
            "n_iter": n_iter,
            "converged": converged,
            "step": step,
        }

    def _factor_K(self, K: np.ndarray, theta: np.ndarray, w: np.ndarray) -> BFactor:
        return factorize(K, self.D, _prec(w, self.c), self.r, self.mu0, math.exp(theta[0]))

    def _lbfgs(self, theta, K, w, lo, hi):
        """A few L-BFGS-B iterations on the theta-part of L3, i.e. L1 at fixed w (§4.2).

        Returns the best evaluated point, so L3 never decreases (the start is evaluated).
        """
        best: dict = {}

        def fun(t: np.ndarray):
            K_t, fac_t = self._factor(t, w)
            lml = fac_t.log_marginal(_prec(w, self.c))
            if not best or lml > best["lml"]:
                best.update(theta=t.copy(), K=K_t, fac=fac_t, lml=lml)
            return -lml, -fac_t.grad

        minimize(
            fun,
            theta,
            jac=True,
            method="L-BFGS-B",
            bounds=list(zip(lo, hi, strict=True)),
            options={"maxiter": LBFGS_STEPS},
        )
        return best["theta"], best["K"], best["fac"]
