"""Sparse robust GPIS: the Student-t variational EM with an SGPR posterior (ALGORITHM.md §8).

For a fixed ``q(tau)`` the model is a GP with known per-datum noise ``1/w_i``, so the Titsias
collapsed bound with heteroscedastic noise (S1) and its marginals (S2) replace the exact
``q(f)``; the q(tau) E-step (E3/E4), the direct (alpha, beta) update and the guarded rprop
kernel step are the exact model's (``robust.py``). The algebra is the unit-noise SGPR after
scaling the columns of ``Phi = Lu^-1 Kuf`` and the residuals by ``sqrt(w_i)`` (GPflow's SGPR
with ``variance_at``). Per EM iteration: O(n M^2 + M^3) time, O(n M) memory.

Inducing inputs ``Z`` ("auto") are training points: a voxel subsample of the contacts at a
spacing of about ``l/2`` plus a coarser subsample of the free-space and interior points,
thinned until ``M <= n_inducing``; ``Z`` stays fixed during the EM.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
from scipy.linalg import lapack, solve_triangular

from groundstation.errors import ConfigError, ConvergenceWarning, InputDataError
from groundstation.mapping._linalg import LOG_2PI, FactorizationError
from groundstation.mapping.kernels import se_from_sq_dists, sq_dists
from groundstation.mapping.robust import (
    PATIENCE,
    RPROP_START,
    RobustGPIS,
    _EMLoop,
    _prec,
    check_sample_weight,
    direct_update,
)
from groundstation.mapping.validation import (
    check_fitted,
    check_inputs,
    check_int,
    check_positive,
    check_training_data,
)

JITTER = 1e-6  # relative jitter on Kuu (times sigma_f^2); Q = Kfu Kuu^-1 Kuf stays <= K
# Contact subsample spacing, in length scales (ALGORITHM.md §8: <= l/2). At l/2 the Nystrom
# residual between inducing points was large enough on the 3D box/cylinder scene to push the
# EM to a high-noise optimum (Chamfer 0.12 m vs 0.06 m at l/4).
CONTACT_SPACING = 0.25
FREE_SPACING = 1.0  # free-space / interior subsample spacing, in length scales
THIN_FACTOR = 1.15  # growth of both spacings per thinning round when M > n_inducing


def _chol(A: np.ndarray, what: str) -> np.ndarray:
    L, info = lapack.dpotrf(A, lower=1, clean=1, overwrite_a=0)
    if info != 0:
        raise FactorizationError(
            f"Cholesky of {what} failed (info={info})",
            hint="check the inputs and hyperparameters for NaN/inf",
        )
    return L


def voxel_representatives(X: np.ndarray, spacing: float) -> np.ndarray:
    """Row indices of one point per occupied voxel: the point nearest the voxel's centroid.

    Parameters
    ----------
    X : (n, d) float64, metres
    spacing : float, metres

    Returns
    -------
    idx : (k,) int64, sorted ascending (deterministic)
    """
    if X.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    keys = np.floor(X / spacing).astype(np.int64)
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    k = int(inv.max()) + 1
    cnt = np.bincount(inv, minlength=k).astype(np.float64)
    cen = np.stack([np.bincount(inv, X[:, j], minlength=k) for j in range(X.shape[1])], 1)
    cen /= cnt[:, None]
    dist = np.sum((X - cen[inv]) ** 2, axis=1)
    order = np.lexsort((np.arange(X.shape[0]), dist, inv))  # per cell: nearest, then first
    first = np.ones(order.size, dtype=bool)
    first[1:] = inv[order[1:]] != inv[order[:-1]]
    return np.sort(order[first])


def choose_inducing(X: np.ndarray, y: np.ndarray, lengthscale: float, n_max: int) -> np.ndarray:
    """Inducing inputs for GPIS (ALGORITHM.md §8 "Choosing Z"): rows of ``X``.

    Also used to pick the subsample of the cold-start exact fit.

    Contacts (``y == 0``) are subsampled per voxel of ``CONTACT_SPACING * l``, the other points
    per voxel of ``FREE_SPACING * l``; both spacings grow by ``THIN_FACTOR`` until at most
    ``n_max`` points remain.

    Returns
    -------
    idx : (M,) int64 row indices into ``X``
    """
    contact = np.flatnonzero(y == 0.0)
    other = np.flatnonzero(y != 0.0)
    scale = 1.0
    for _ in range(200):
        ic = contact[voxel_representatives(X[contact], CONTACT_SPACING * lengthscale * scale)]
        io = other[voxel_representatives(X[other], FREE_SPACING * lengthscale * scale)]
        if ic.size + io.size <= n_max:
            return np.sort(np.concatenate([ic, io]))
        scale *= THIN_FACTOR
    raise InputDataError(f"could not thin the inducing set to {n_max} points")  # pragma: no cover


@dataclasses.dataclass(frozen=True)
class SparseFactor:
    """SGPR posterior ``q(u)`` for noise precisions ``w`` and its bound (ALGORITHM.md S1/S2).

    Attributes
    ----------
    Lu : (M, M) lower Cholesky of ``Kuu + jitter``
    LB : (M, M) lower Cholesky of ``B_M = I + Phi W Phi^T``
    Binv : (M, M) ``B_M^-1`` (full, symmetric)
    mu_v : (M,) whitened posterior mean ``L_B^-T c`` of ``v = Lu^-1 u``
    m, diag_A : (n,) S2 marginals (``diag_A`` keeps the Nystrom residual ``k_ii - q_ii``)
    F : float, collapsed bound S1 (``log N(r | 0, Q + W^-1) - 1/2 sum w (k - q)``)
    kl_f : float, ``KL(q(u) || p(u))``, so that L2 = sum l_i(s_i) - kl_f - sum KL_tau
    grad : (2,) dS1/d(log l, log sigma_f^2)
    """

    Lu: np.ndarray
    LB: np.ndarray
    Binv: np.ndarray
    mu_v: np.ndarray
    m: np.ndarray
    diag_A: np.ndarray
    F: float
    kl_f: float
    grad: np.ndarray

    def log_marginal(self, w: np.ndarray) -> float:
        """S1 (the theta-dependent part of L3 with S1), for the L-BFGS kernel step."""
        return self.F


def kernel_blocks(
    Duu: np.ndarray, Duf: np.ndarray, lengthscale: float, signal_var: float, jitter: float = JITTER
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The theta-only part of S1: ``Kuu + jitter`` (M, M), its Cholesky ``Lu``, ``Kuf`` (M, n)
    and ``Phi = Lu^-1 Kuf`` (M, n) (ALGORITHM.md §8)."""
    M = Duu.shape[0]
    Kuu = se_from_sq_dists(Duu, lengthscale, signal_var)
    Kuu.flat[:: M + 1] += jitter * signal_var  # jitter scales with sigma_f^2: dKuu/dlog sf2 = Kuu
    Lu = _chol(Kuu, "Kuu")
    Kuf = se_from_sq_dists(Duf, lengthscale, signal_var)
    Phi = solve_triangular(Lu, Kuf, lower=True, check_finite=False)  # Lu^-1 Kuf (S1)
    return Kuu, Lu, Kuf, Phi


def sparse_factorize(
    Duu: np.ndarray,
    Duf: np.ndarray,
    w: np.ndarray,
    r: np.ndarray,
    mu0: float,
    lengthscale: float,
    signal_var: float,
    jitter: float = JITTER,
    with_grad: bool = True,
    blocks: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> SparseFactor:
    """S1/S2 and the kernel gradient of S1 at ``theta`` for precisions ``w``.

    Parameters
    ----------
    Duu : (M, M) squared distances between inducing inputs, metres^2
    Duf : (M, n) squared distances inducing -> training inputs, metres^2
    w : (n,) noise precisions ``E[1/tau_i]``
    r : (n,) centred labels ``y - mu0``
    mu0, lengthscale, signal_var : floats
    jitter : float, relative to ``signal_var``
    with_grad : bool
    blocks : tuple, optional
        ``kernel_blocks(Duu, Duf, lengthscale, signal_var, jitter)`` for this theta (reused
        between EM iterations that keep theta: only the weights change).

    Returns
    -------
    SparseFactor
    """
    M, n = Duf.shape
    l2 = lengthscale * lengthscale
    if blocks is None:
        blocks = kernel_blocks(Duu, Duf, lengthscale, signal_var, jitter)
    Kuu, Lu, Kuf, Phi = blocks
    sw = np.sqrt(w)
    At = Phi * sw[None, :]  # sqrt(w)-scaled columns: unit-noise SGPR algebra
    B = At @ At.T
    B.flat[:: M + 1] += 1.0
    LB = _chol(B, "B_M = I + Phi W Phi^T")
    yt = sw * r
    c = solve_triangular(LB, At @ yt, lower=True, check_finite=False)
    mu_v = solve_triangular(LB, c, lower=True, trans=1, check_finite=False)
    Gam = solve_triangular(LB, Phi, lower=True, check_finite=False)  # L_B^-1 Phi
    q_diag = np.einsum("ij,ij->j", Phi, Phi)
    resid = np.maximum(signal_var - q_diag, 0.0)  # Nystrom residual k_ii - q_ii
    m = mu0 + Phi.T @ mu_v  # S2 mean
    diag_A = resid + np.einsum("ij,ij->j", Gam, Gam)  # S2 variance
    logdet_B = 2.0 * float(np.sum(np.log(np.diag(LB))))
    # S1 (ALGORITHM.md §8).
    F = (
        -0.5 * (float(w @ (r * r)) - float(c @ c))
        - 0.5 * (logdet_B - float(np.sum(np.log(w))))
        - 0.5 * n * LOG_2PI
        - 0.5 * float(w @ resid)
    )
    Binv, info = lapack.dpotri(LB, lower=1)
    Binv = Binv + np.tril(Binv, -1).T
    # KL(q(v) || N(0, I)) with q(v) = N(mu_v, B^-1) (whitened q(u)).
    kl_f = 0.5 * (float(np.trace(Binv)) + float(mu_v @ mu_v) - M + logdet_B)
    grad = np.zeros(2)
    if with_grad:
        # dS1/dtheta = tr[H dKfu] - 1/2 tr[E dKuu] - 1/2 sum w dk_ii with (derivation in the
        # module notes) a = (Q + W^-1)^-1 r = w (y - m), H = Lu^-T [mu_v a^T + (I - B^-1) Phi W]
        # and E = Lu^-T [mu_v mu_v^T + B - 2I + B^-1] Lu^-1.
        a = w * (r + mu0 - m)
        IB = -Binv
        IB.flat[:: M + 1] += 1.0
        Ht = np.outer(mu_v, a) + IB @ (Phi * w[None, :])
        H = solve_triangular(Lu, Ht, lower=True, trans=1, check_finite=False)
        Et = np.outer(mu_v, mu_v) + B + Binv
        Et.flat[:: M + 1] -= 2.0
        E = solve_triangular(Lu, Et, lower=True, trans=1, check_finite=False)
        E = solve_triangular(Lu, E.T, lower=True, trans=1, check_finite=False).T
        HK = H * Kuf
        EK = E * Kuu
        g_sf2 = (
            float(np.sum(Ht * Phi)) - 0.5 * float(np.sum(EK)) - 0.5 * signal_var * float(np.sum(w))
        )
        g_ell = (float(np.sum(HK * Duf)) - 0.5 * float(np.sum(EK * Duu))) / l2
        grad = np.array([g_ell, g_sf2])
    return SparseFactor(
        Lu=Lu, LB=LB, Binv=Binv, mu_v=mu_v, m=m, diag_A=diag_A, F=F, kl_f=kl_f, grad=grad
    )


@dataclasses.dataclass(frozen=True)
class SparsePosterior:
    """A fitted SGPR frozen for grid evaluation (ALGORITHM.md §8 "Cost and prediction").

    mean = mu0 + k*^T v with ``v = Lu^-T mu_v``; var = k** - k*^T R k* with
    ``R = Kuu^-1 - Sigma_u = Lu^-T (I - B^-1) Lu^-1``.
    """

    X: np.ndarray  # (M, d) inducing inputs; ``X`` so that generic checks see the dimension
    center: np.ndarray
    v: np.ndarray
    R: np.ndarray
    mu0: float
    lengthscale: float
    signal_var: float

    @classmethod
    def from_factor(cls, Z, fac: SparseFactor, mu0, lengthscale, signal_var) -> SparsePosterior:
        M = Z.shape[0]
        v = solve_triangular(fac.Lu, fac.mu_v, lower=True, trans=1, check_finite=False)
        IB = -fac.Binv
        IB.flat[:: M + 1] += 1.0
        T = solve_triangular(fac.Lu, IB, lower=True, trans=1, check_finite=False)
        R = solve_triangular(fac.Lu, T.T, lower=True, trans=1, check_finite=False)
        R = 0.5 * (R + R.T)
        return cls(Z, Z.mean(axis=0), v, R, float(mu0), float(lengthscale), float(signal_var))

    def predict(
        self, Xs: np.ndarray, return_std: bool = False, chunk_mb: float = 64.0
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Mean (m,) and, if ``return_std``, latent std (m,) at ``Xs`` (m, d) metres."""
        m_pts = Xs.shape[0]
        M = self.X.shape[0]
        mean = np.empty(m_pts)
        std = np.empty(m_pts) if return_std else None
        step = max(1, int(chunk_mb * 1e6 // (8.0 * M * (2 if return_std else 1))))
        for start in range(0, m_pts, step):
            stop = min(start + step, m_pts)
            Ks = sq_dists(Xs[start:stop], self.X, center=self.center)
            se_from_sq_dists(Ks, self.lengthscale, self.signal_var, out=Ks)
            mean[start:stop] = self.mu0 + Ks @ self.v
            if std is not None:
                var = self.signal_var - np.einsum("ij,ij->i", Ks @ self.R, Ks)
                std[start:stop] = np.sqrt(np.maximum(var, 0.0))
        return mean if std is None else (mean, std)


class _SparseEMLoop(_EMLoop):
    """The EM of ``robust._EMLoop`` with the SGPR factor in place of the exact one."""

    def __init__(self, Duu, Duf, y, r, mu0, cfg, jitter, c=None):
        super().__init__(None, y, r, mu0, cfg, c)
        self.Duu, self.Duf, self.jitter = Duu, Duf, jitter
        self._blocks: dict = {}  # theta -> kernel_blocks, the last two thetas (current, trial)

    def _factor(self, theta: np.ndarray, w: np.ndarray):
        ell, sf2 = np.exp(theta)
        key = tuple(np.asarray(theta, dtype=np.float64).tolist())
        blocks = self._blocks.get(key)
        if blocks is None:  # only theta steps need new kernel blocks
            while len(self._blocks) >= 2:
                self._blocks.pop(next(iter(self._blocks)))
            blocks = kernel_blocks(self.Duu, self.Duf, ell, sf2, self.jitter)
        self._blocks.pop(key, None)
        self._blocks[key] = blocks  # most recently used last
        return None, sparse_factorize(
            self.Duu,
            self.Duf,
            _prec(w, self.c),
            self.r,
            self.mu0,
            ell,
            sf2,
            self.jitter,
            self.cfg["optimize"],
            blocks=blocks,
        )

    def _factor_K(self, K, theta: np.ndarray, w: np.ndarray):
        return self._factor(theta, w)[1]


class SparseRobustGPIS(RobustGPIS):
    """Robust GPIS with an inducing-point (SGPR) posterior and the same per-datum weights.

    Parameters
    ----------
    n_inducing : int
        Maximum number of inducing inputs M (used when ``inducing="auto"``).
    inducing : "auto" | (M, d) array, metres
        Inducing inputs, or ``"auto"`` for :func:`choose_inducing` at the current length scale.
    jitter : float
        Relative jitter added to ``Kuu`` (times sigma_f^2).
    init_subset : int
        Cold start: an exact :class:`RobustGPIS` is fitted to at most this many rows (the
        inducing rows) and its predictive moments start q(tau) of every row (§8 "Streaming").
    **kwargs
        Every :class:`RobustGPIS` setting (``lengthscale``, ``alpha``, ``beta``, ``tol``,
        ``warm_start`` ...). ``init`` is ignored (see ``init_subset``).

    Attributes
    ----------
    The fitted attributes of :class:`RobustGPIS`, plus ``inducing_`` (M, d) and
    ``inducing_index_`` (M,) (row indices into ``X_train_``, or None for user-given Z).
    """

    def __init__(
        self,
        n_inducing: int = 500,
        inducing: str | np.ndarray = "auto",
        jitter: float = JITTER,
        init_subset: int = 600,
        **kwargs,
    ) -> None:
        super().__init__(**kwargs)
        self.n_inducing = n_inducing
        self.inducing = inducing
        self.jitter = jitter
        self.init_subset = init_subset

    def _inducing(self, X: np.ndarray, y: np.ndarray, ell: float):
        if isinstance(self.inducing, str):
            if self.inducing != "auto":
                raise ConfigError(
                    f"inducing must be 'auto' or an (M, d) array, got {self.inducing!r}"
                )
            idx = choose_inducing(X, y, ell, check_int("n_inducing", self.n_inducing, 1))
            return X[idx], idx
        Z = check_inputs(self.inducing, "inducing", dims=(X.shape[1],))
        return Z, None

    def fit(
        self, X: np.ndarray, y: np.ndarray, sample_weight: np.ndarray | None = None
    ) -> SparseRobustGPIS:
        """Fit to ``X`` (n, 2|3) float64 metres with labels ``y`` (n,); returns self.

        ``sample_weight`` (n,): row multiplicities, as in :meth:`RobustGPIS.fit`.
        """
        cfg = self._settings()
        jitter = check_positive("jitter", self.jitter)
        X, y = check_training_data(X, y)
        n = X.shape[0]
        c = check_sample_weight(sample_weight, n)
        mu0 = cfg["mu0"]
        r = y - mu0
        prev = getattr(self, "posterior_", None)
        warm = self.warm_start and prev is not None and prev.X.shape[1] == X.shape[1]
        step = np.full(2, RPROP_START)
        if warm:
            # ALGORITHM.md §8 "Streaming": (theta, alpha, beta) from the previous fit; every row
            # starts at q(tau_i) = IG(alpha + 1/2, beta + s_i/2) from the previous predictive
            # moments (for rows seen before these are the previous E4 inputs).
            theta = np.clip(np.log([self.lengthscale_, self.signal_var_]), *cfg["bounds"].T)
            alpha = float(np.clip(self.alpha_, *cfg["alpha_bounds"]))
            beta = max(float(self.beta_), cfg["floor"])
            mean, sd = prev.predict(X, return_std=True, chunk_mb=cfg["chunk_mb"])
            s = (y - mean) ** 2 + sd**2
            step = np.clip(getattr(self, "_rprop_step", step), 1e-3, RPROP_START)
        if not warm:
            # Cold start: exact robust GPIS on a voxel subsample (theta, alpha, beta and a robust
            # q(f)), then s_i of every row from its predictive moments (§8 "Streaming").
            n_sub = check_int("init_subset", self.init_subset, 2)
            # All rows when they fit the budget: a voxel subsample can drop the free-space
            # points that contradict a false contact, and the init then lands in the Gaussian
            # limit (ALGORITHM.md §7.3; seen on a radius-merged sphere session).
            sub = (
                np.arange(n)
                if n <= n_sub
                else choose_inducing(X, y, math.exp(cfg["theta"][0]), n_sub)
            )
            if not np.any(y[sub] == 0.0):
                sub = np.union1d(sub, np.flatnonzero(y == 0.0)[:1])
            params = {k: getattr(self, k) for k in _ROBUST_PARAMS}
            params.update(warm_start=False)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", ConvergenceWarning)
                init = RobustGPIS(**params).fit(X[sub], y[sub], None if c is None else c[sub])
            theta = np.log([init.lengthscale_, init.signal_var_])
            alpha, beta = init.alpha_, max(init.beta_, cfg["floor"])
            mean, sd = init.predict(X, return_std=True)
            s = (y - mean) ** 2 + sd**2
            if cfg["noise_update"] == "direct":
                alpha, beta = direct_update(s, alpha, cfg["alpha_bounds"], cfg["floor"], c)
        # Z at the current (warm) or subsample-learnt (cold) length scale, fixed during the EM.
        Z, zidx = self._inducing(X, y, math.exp(theta[0]))
        at, bt = np.full(n, alpha + 0.5), beta + 0.5 * s  # E3/E4 from predictive moments
        Duu = sq_dists(Z)
        Duf = sq_dists(Z, X)
        em = _SparseEMLoop(Duu, Duf, y, r, mu0, cfg, jitter, c)
        fac = em._factor_K(None, theta, at / bt)
        state = em.run(theta, None, fac, at, bt, alpha, beta, step)
        theta, fac = state["theta"], state["fac"]
        ell, sf2 = (float(v) for v in np.exp(theta))
        self.X_train_, self.y_train_ = X, y
        self.inducing_, self.inducing_index_ = Z, zidx
        self.lengthscale_, self.signal_var_ = ell, sf2
        self.alpha_, self.beta_ = float(state["alpha"]), float(state["beta"])
        self.alpha_tilde_, self.beta_tilde_ = state["at"], state["bt"]
        self.uncertainty_ = state["bt"] / state["at"]
        self.weights_ = state["at"] / state["bt"]
        self.elbo_trace_ = state["trace"]
        self.n_iter_ = state["n_iter"]
        self.converged_ = state["converged"]
        self._rprop_step = state["step"]
        self.posterior_ = SparsePosterior.from_factor(Z, fac, mu0, ell, sf2)
        if not self.converged_:
            warnings.warn(
                f"SparseRobustGPIS EM stopped at max_iter={self.max_iter} before the relative "
                f"ELBO change fell below tol={self.tol} for {PATIENCE} iterations",
                ConvergenceWarning,
                stacklevel=2,
            )
        return self

    def predict(
        self, X: np.ndarray, return_std: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Posterior mean (m,) and, if ``return_std``, latent std (m,) at ``X`` (m, d) metres.

        Mean O(M) and variance O(M^2) per point (ALGORITHM.md §8).
        """
        check_fitted(self)
        X = check_inputs(X, "X", dims=(self.X_train_.shape[1],))
        return self.posterior_.predict(X, return_std, check_positive("chunk_mb", self.chunk_mb))


_ROBUST_PARAMS = (
    "lengthscale",
    "signal_var",
    "alpha",
    "beta",
    "prior_mean",
    "optimize",
    "noise_update",
    "kernel_step",
    "init",
    "max_iter",
    "tol",
    "beta_floor",
    "alpha_bounds",
    "lengthscale_bounds",
    "signal_var_bounds",
    "chunk_mb",
)
