"""Homoscedastic GP implicit surface (GPIS) with ML-II hyperparameters.

The GP of ALGORITHM.md §1 with Gaussian noise ``noise_var``; it is the B-form machinery of
``_linalg`` with ``W = I / noise_var``. Hyperparameters ``(log l, log sigma_f^2, log sigma_n^2)``
maximise the log marginal likelihood L1 by L-BFGS-B with the analytic gradients M3 and
``dL/dlog sigma_n^2 = 1/2 sigma_n^2 (a^T a - tr P)`` (ALGORITHM.md §4.2).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
from scipy.optimize import minimize

from groundstation.errors import ConvergenceWarning
from groundstation.mapping._linalg import BFactor, FrozenPosterior, factorize
from groundstation.mapping.kernels import se_from_sq_dists, sq_dists
from groundstation.mapping.validation import (
    check_bounds,
    check_finite,
    check_fitted,
    check_inputs,
    check_int,
    check_positive,
    check_training_data,
)


@dataclasses.dataclass
class GpisFit:
    """Result of :func:`fit_gpis` (internal; shared with RobustGPIS's initialisation)."""

    theta: np.ndarray  # (3,) log lengthscale, log signal_var, log noise_var
    K: np.ndarray
    factor: BFactor
    log_marginal: float
    n_iter: int
    converged: bool
    message: str


def gpis_objective(
    theta: np.ndarray, D: np.ndarray, r: np.ndarray, mu0: float
) -> tuple[float, np.ndarray, np.ndarray, BFactor]:
    """Log marginal likelihood L1 of the homoscedastic GP and its gradient.

    Parameters
    ----------
    theta : (3,) float64
        ``(log l, log sigma_f^2, log sigma_n^2)``.
    D : (n, n) float64, squared distances, metres^2
    r : (n,) float64, ``y - mu0``
    mu0 : float

    Returns
    -------
    lml : float
    grad : (3,) float64, d lml / d theta (M3 plus the noise gradient)
    K : (n, n) float64
    factor : BFactor
    """
    ell, sf2, sn2 = np.exp(theta)
    K = se_from_sq_dists(D, ell, sf2)
    w = np.full(r.shape[0], 1.0 / sn2)
    fac = factorize(K, D, w, r, mu0, ell)
    lml = fac.log_marginal(w)
    # ALGORITHM.md §4.2: dL/dlog sigma_n^2 = 1/2 sigma_n^2 (a^T a - tr P).
    g_noise = 0.5 * sn2 * (float(fac.a @ fac.a) - fac.tr_P)
    return lml, np.array([fac.grad[0], fac.grad[1], g_noise]), K, fac


def fit_gpis(
    D: np.ndarray,
    r: np.ndarray,
    mu0: float,
    theta0: np.ndarray,
    log_bounds: np.ndarray,
    optimize: bool,
    max_iter: int,
    tol: float,
) -> GpisFit:
    """Maximise L1 over ``theta`` with L-BFGS-B (relative ``ftol = tol``) from ``theta0``.

    ``log_bounds`` is (3, 2). Returns the best evaluated point with its factorisation.
    """
    best: dict[str, object] = {}

    def fun(theta: np.ndarray) -> tuple[float, np.ndarray]:
        lml, grad, K, fac = gpis_objective(theta, D, r, mu0)
        if not best or lml > best["lml"]:  # type: ignore[operator]
            best.update(theta=theta.copy(), lml=lml, K=K, fac=fac)
        return -lml, -grad

    if not optimize:
        fun(np.asarray(theta0, dtype=np.float64))
        return GpisFit(best["theta"], best["K"], best["fac"], best["lml"], 0, True, "fixed")  # type: ignore[arg-type]
    res = minimize(
        fun,
        np.asarray(theta0, dtype=np.float64),
        jac=True,
        method="L-BFGS-B",
        bounds=[tuple(b) for b in log_bounds],
        options={"maxiter": max_iter, "ftol": tol, "gtol": 1e-8},
    )
    # status 1 = iteration/evaluation limit. status 2 (line search cannot improve) happens at an
    # optimum reached to rounding precision, so it counts as converged.
    converged = res.status != 1
    msg = str(res.message)
    return GpisFit(
        best["theta"],
        best["K"],
        best["fac"],
        best["lml"],
        int(res.nit),
        converged,
        msg,  # type: ignore[arg-type]
    )


class GPIS:
    """Homoscedastic Gaussian-process implicit surface (scikit-learn style).

    Parameters
    ----------
    lengthscale : float, metres
        Initial squared-exponential length scale.
    signal_var : float
        Initial signal variance sigma_f^2 (label units^2).
    noise_var : float
        Initial noise variance sigma_n^2 (label units^2).
    prior_mean : float
        Constant prior mean mu0 (paper: 0).
    optimize : bool
        Learn (l, sigma_f^2, sigma_n^2) by ML-II; otherwise keep the initial values.
    max_iter : int
        L-BFGS-B iteration limit.
    tol : float
        Relative change of the log marginal likelihood at which L-BFGS-B stops (``ftol``).
    lengthscale_bounds, signal_var_bounds, noise_var_bounds : (float, float)
        Bounds of the learnt hyperparameters.
    chunk_mb : float
        Memory budget of one prediction chunk, MB.
    warm_start : bool
        Start a refit from the previous fit's hyperparameters.

    Attributes
    ----------
    X_train_ : (n, d) float64, metres
    y_train_ : (n,) float64
    lengthscale_, signal_var_, noise_var_ : float
    log_marginal_likelihood_ : float
        L1 at the fitted hyperparameters.
    uncertainty_ : (n,) float64
        Posterior (latent) variance at the training points.
    n_iter_ : int
    converged_ : bool
    """

    def __init__(
        self,
        lengthscale: float = 0.25,
        signal_var: float = 1.0,
        noise_var: float = 0.01,
        prior_mean: float = 0.0,
        optimize: bool = True,
        max_iter: int = 200,
        tol: float = 1e-6,
        lengthscale_bounds: tuple[float, float] = (1e-2, 1e2),
        signal_var_bounds: tuple[float, float] = (1e-3, 1e3),
        noise_var_bounds: tuple[float, float] = (1e-6, 1e1),
        chunk_mb: float = 64.0,
        warm_start: bool = False,
    ) -> None:
        self.lengthscale = lengthscale
        self.signal_var = signal_var
        self.noise_var = noise_var
        self.prior_mean = prior_mean
        self.optimize = optimize
        self.max_iter = max_iter
        self.tol = tol
        self.lengthscale_bounds = lengthscale_bounds
        self.signal_var_bounds = signal_var_bounds
        self.noise_var_bounds = noise_var_bounds
        self.chunk_mb = chunk_mb
        self.warm_start = warm_start

    def _settings(self) -> tuple[np.ndarray, np.ndarray, float]:
        ell = check_positive("lengthscale", self.lengthscale)
        sf2 = check_positive("signal_var", self.signal_var)
        sn2 = check_positive("noise_var", self.noise_var)
        bounds = np.log(
            [
                check_bounds("lengthscale_bounds", self.lengthscale_bounds, ell, "lengthscale"),
                check_bounds("signal_var_bounds", self.signal_var_bounds, sf2, "signal_var"),
                check_bounds("noise_var_bounds", self.noise_var_bounds, sn2, "noise_var"),
            ]
        )
        mu0 = check_finite("prior_mean", self.prior_mean)
        check_int("max_iter", self.max_iter, 1)
        check_positive("tol", self.tol)
        check_positive("chunk_mb", self.chunk_mb)
        return np.log([ell, sf2, sn2]), bounds, mu0

    def fit(self, X: np.ndarray, y: np.ndarray) -> GPIS:
        """Fit to points ``X`` (n, 2|3) float64 metres with labels ``y`` (n,); returns self."""
        theta0, bounds, mu0 = self._settings()
        X, y = check_training_data(X, y)
        prev = getattr(self, "posterior_", None)
        if self.warm_start and prev is not None and prev.X.shape[1] == X.shape[1]:
            theta0 = np.clip(
                np.log([self.lengthscale_, self.signal_var_, self.noise_var_]),
                bounds[:, 0],
                bounds[:, 1],
            )
        D = sq_dists(X)
        res = fit_gpis(
            D, y - mu0, mu0, theta0, bounds, bool(self.optimize), int(self.max_iter), self.tol
        )
        del D
        ell, sf2, sn2 = (float(v) for v in np.exp(res.theta))
        self.X_train_ = X
        self.y_train_ = y
        self.lengthscale_, self.signal_var_, self.noise_var_ = ell, sf2, sn2
        self.log_marginal_likelihood_ = float(res.log_marginal)
        self.uncertainty_ = res.factor.diag_A.copy()
        self.n_iter_ = res.n_iter
        self.converged_ = res.converged
        self.posterior_ = FrozenPosterior(
            X, X.mean(axis=0), res.factor.a, res.factor.L, res.factor.sw, mu0, ell, sf2
        )
        if not res.converged:
            warnings.warn(
                f"GPIS hyperparameter search stopped after {res.n_iter} iterations without "
                f"meeting tol={self.tol} ({res.message}); increase max_iter",
                ConvergenceWarning,
                stacklevel=2,
            )
        return self

    def predict(
        self, X: np.ndarray, return_std: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Posterior mean ``mu(X)`` (m,) and, if ``return_std``, latent std (m,).

        ``X`` is (m, d) float64, metres, with the training dimension d; evaluated in chunks of
        at most ``chunk_mb`` MB.
        """
        check_fitted(self)
        X = check_inputs(X, "X", dims=(self.X_train_.shape[1],))
        return self.posterior_.predict(X, return_std, check_positive("chunk_mb", self.chunk_mb))
