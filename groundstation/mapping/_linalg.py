"""B-form factorisation of a GP with per-datum noise, and the frozen posterior for prediction.

Everything goes through ``B = I + W^1/2 K W^1/2`` (ALGORITHM.md §2-§3): its eigenvalues are >= 1,
so its Cholesky needs no jitter even with duplicate inputs, and ``K^-1`` is never formed. One
factorisation costs one ``potrf`` + one ``potri`` and a handful of O(n^2) passes; it returns the
posterior ``q(f)`` (E1/E2), the collapsed bound's parts (L1, KL_f of L2b) and the kernel gradient
(M3), so an EM iteration needs exactly one of them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
from collections.abc import Iterator

import numpy as np
from scipy.linalg import lapack, solve_triangular

from groundstation.errors import GroundstationError
from groundstation.mapping.kernels import se_from_sq_dists, sq_dists

LOG_2PI = math.log(2.0 * math.pi)


@functools.cache
def _threadpools():
    """The process's BLAS/OpenMP thread pools, found once: a fresh ``threadpool_limits`` scans
    every loaded library again (3-4 ms, 6 % of a typical live refit)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()  # after scipy's BLAS is loaded (imported above)


@contextlib.contextmanager
def blas_threads(n: int) -> Iterator[None]:
    """Limit BLAS threads while fitting (0: leave the process setting alone)."""
    if n <= 0:
        yield
        return
    with _threadpools().limit(limits=n):
        yield


class FactorizationError(GroundstationError, ArithmeticError):
    """The Cholesky factorisation of B failed (only possible with non-finite values)."""


@dataclasses.dataclass(frozen=True)
class BFactor:
    """Posterior ``q(f) = N(m, A)`` for kernel ``K`` and noise precisions ``w``.

    Attributes
    ----------
    L : (n, n) float64, Fortran order
        Lower Cholesky factor of ``B = I + W^1/2 K W^1/2`` (upper triangle zero).
    sw : (n,) float64
        ``W^1/2 = sqrt(w)``.
    a : (n,) float64
        ``(K + W^-1)^-1 r = W^1/2 B^-1 W^1/2 r`` (ALGORITHM.md §2).
    m : (n,) float64
        Posterior mean ``mu0 + K a`` (E2).
    diag_A : (n,) float64
        Posterior variances ``A_ii`` (E1, row-sum form of §3), clipped at 0.
    diag_P : (n,) float64
        Diagonal of ``P = (K + W^-1)^-1`` (leave-one-out moments, R&W eq. 5.12).
    logdet_B, tr_Binv, tr_P, aKa, r_a : float
        ``log|B|``, ``tr(B^-1)``, ``tr(P)`` with ``P = W^1/2 B^-1 W^1/2``, ``a^T K a``, ``r^T a``.
    grad : (2,) float64
        M3 gradient of L1 with respect to ``(log l, log sigma_f^2)``.
    P : (n, n) float64 or None
        ``P = (K + W^-1)^-1`` (full, symmetric) when asked for (``keep_P``): its blocks give
        leave-group-out residuals (ALGORITHM.md §12).
    """

    L: np.ndarray
    sw: np.ndarray
    a: np.ndarray
    m: np.ndarray
    diag_A: np.ndarray
    logdet_B: float
    tr_Binv: float
    tr_P: float
    diag_P: np.ndarray
    aKa: float
    r_a: float
    grad: np.ndarray
    P: np.ndarray | None = None

    @property
    def kl_f(self) -> float:
        """``KL(q(f) || p(f))`` in the stable form of ALGORITHM.md L2b."""
        n = self.a.shape[0]
        return 0.5 * (self.tr_Binv + self.aKa - n + self.logdet_B)

    def log_marginal(self, w: np.ndarray) -> float:
        """``log N(y | mu0, K + W^-1)`` (ALGORITHM.md L1)."""
        n = self.a.shape[0]
        return -0.5 * self.r_a - 0.5 * (self.logdet_B - np.sum(np.log(w))) - 0.5 * n * LOG_2PI


def _cholesky_B(K: np.ndarray, sw: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor (Fortran order, upper triangle zero) of ``B = I + W^1/2 K W^1/2``."""
    n = K.shape[0]
    B = K * sw[:, None]
    B *= sw[None, :]
    B.flat[:: n + 1] += 1.0
    # B is symmetric: hand LAPACK its transpose (Fortran order) so potrf works in place.
    L, info = lapack.dpotrf(B.T, lower=1, clean=1, overwrite_a=1)
    if info != 0:
        raise FactorizationError(
            f"Cholesky of B = I + W^1/2 K W^1/2 failed (info={info})",
            hint="check the inputs and hyperparameters for NaN/inf",
        )
    return L


def factorize(
    K: np.ndarray,
    D: np.ndarray | None,
    w: np.ndarray,
    r: np.ndarray,
    mu0: float,
    lengthscale: float,
    keep_P: bool = False,
) -> BFactor:
    """Factorise ``B`` and derive ``q(f)``, the bound's parts and the M3 gradient.

    Parameters
    ----------
    K : (n, n) float64
        Kernel matrix at the training inputs (not modified).
    D : (n, n) float64, metres^2, or None
        Squared distances between the training inputs (for ``dK/dlog l = K o D / l^2``);
        None skips the kernel gradient (``grad`` is then zero), e.g. for a kernel matrix with
        derivative rows, whose gradient this formula does not give.
    w : (n,) float64, > 0
        Noise precisions ``E[1/tau_i]`` (GPIS: ``1/noise_var``).
    r : (n,) float64
        Centred labels ``y - mu0``.
    mu0 : float
        Prior mean.
    lengthscale : float, metres
    keep_P : bool
        Also return ``P = (K + W^-1)^-1`` in full (one more n^2 copy).

    Returns
    -------
    BFactor
    """
    n = K.shape[0]
    sw = np.sqrt(w)
    L = _cholesky_B(K, sw)
    z, info = lapack.dpotrs(L, sw * r, lower=1)
    a = sw * z
    Ka = K @ a
    m = mu0 + Ka
    logdet_B = 2.0 * float(np.sum(np.log(np.diag(L))))
    # B^-1 from potri (ALGORITHM.md §3); only its lower triangle is filled, the upper is 0.
    T, info = lapack.dpotri(L, lower=1, overwrite_c=0)
    if info != 0:
        raise FactorizationError(f"potri of B failed (info={info})")
    tr_Binv = float(np.trace(T))
    T *= sw[:, None]
    T *= sw[None, :]  # lower triangle of P = W^1/2 B^-1 W^1/2
    diag_P = np.diag(T).copy()
    tr_P = float(diag_P.sum())
    P_full = None
    if keep_P:
        P_full = T + T.T
        P_full.flat[:: n + 1] -= diag_P
    T *= K  # lower triangle of P o K
    dT = np.diag(T).copy()
    rs = T.sum(axis=1) + T.sum(axis=0) - dT  # row sums of the full symmetric P o K
    # ALGORITHM.md §3: A_ii = sum_j [B^-1]_ij w_j^1/2 K_ji / w_i^1/2 = (P o K 1)_i / w_i.
    diag_A = np.maximum(rs / w, 0.0)
    sum_PK = float(rs.sum())
    aKa = float(a @ Ka)
    if D is None:
        grad = np.zeros(2)
    else:
        T *= D  # lower triangle of P o K o D; D has a zero diagonal: the full sum is twice this
        sum_PKD = 2.0 * float(T.sum())
        np.multiply(K, D, out=T)
        aKDa = float(a @ (T @ a))
        l2 = lengthscale * lengthscale
        # ALGORITHM.md M3: dL/dtheta_j = 1/2 tr[(a a^T - P) dK/dtheta_j].
        grad = np.array([0.5 * (aKDa - sum_PKD) / l2, 0.5 * (aKa - sum_PK)])
    del T
    return BFactor(
        L=L,
        sw=sw,
        a=a,
        m=m,
        diag_A=diag_A,
        logdet_B=logdet_B,
        tr_Binv=tr_Binv,
        tr_P=tr_P,
        diag_P=diag_P,
        aKa=aKa,
        r_a=float(r @ a),
        grad=grad,
        P=P_full,
    )


@dataclasses.dataclass(frozen=True)
class FrozenPosterior:
    """A fitted GP with per-datum noise ``Sigma = W^-1``, frozen for grid evaluation.

    mean = mu0 + k*^T a; var = k** - v^T v with v = L^-1 W^1/2 k* (ALGORITHM.md §6).
    """

    X: np.ndarray
    center: np.ndarray
    a: np.ndarray
    L: np.ndarray
    sw: np.ndarray
    mu0: float
    lengthscale: float
    signal_var: float

    def chunk_rows(self, chunk_mb: float, return_std: bool) -> int:
        """Test points per chunk so that one chunk's (rows, n) temporaries fit in ``chunk_mb``."""
        n = self.X.shape[0]
        per_row = 8.0 * n * (3 if return_std else 2)
        return max(1, int(chunk_mb * 1e6 // per_row))

    def predict(
        self, Xs: np.ndarray, return_std: bool = False, chunk_mb: float = 64.0
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Posterior mean (and latent standard deviation) at ``Xs``.

        Parameters
        ----------
        Xs : (m, d) float64, metres
        return_std : bool
        chunk_mb : float
            Memory budget of one chunk, MB.

        Returns
        -------
        mean : (m,) float64
        std : (m,) float64, only if ``return_std``
        """
        m_pts = Xs.shape[0]
        mean = np.empty(m_pts)
        std = np.empty(m_pts) if return_std else None
        step = self.chunk_rows(chunk_mb, return_std)
        for start in range(0, m_pts, step):
            stop = min(start + step, m_pts)
            Ks = sq_dists(Xs[start:stop], self.X, center=self.center)  # (c, n)
            se_from_sq_dists(Ks, self.lengthscale, self.signal_var, out=Ks)
            mean[start:stop] = self.mu0 + Ks @ self.a
            if std is not None:
                Ks *= self.sw[None, :]
                # (c, n) C-order -> (n, c) Fortran view: trsm without a copy.
                v = solve_triangular(self.L, Ks.T, lower=True, check_finite=False, overwrite_b=True)
                var = self.signal_var - np.einsum("ij,ij->j", v, v)
                std[start:stop] = np.sqrt(np.maximum(var, 0.0))
        if std is None:
            return mean
        return mean, std


@dataclasses.dataclass(frozen=True)
class BlockFactor:
    """What an EM iteration of the event mixture needs of ``B = I + W^1/2 K W^1/2``, and no
    more: the posterior mean's weights and the blocks of ``P = (K + W^-1)^-1`` of the rows it
    leaves out (``P_bb = Z_b^T Z_b`` with ``Z = L^-1 W^1/2 E_b``).

    ``B`` is factorised with the rows asked for last (``order``). Forward substitution then
    leaves ``Z`` zero above the trailing block, where it is that block's triangular inverse
    scaled by ``W^1/2``: O(k^3 / 3) for k rows asked, instead of a solve over their columns,
    O(n^2 k) (on a hover spot's tile, 540 of 770 rows belong to gusts: 6x fewer flops).

    Attributes
    ----------
    L : (n, n) float64
        Lower Cholesky factor of ``B`` with its rows and columns in ``order``.
    sw : (n,) float64
        ``W^1/2``.
    a : (n,) float64
        ``(K + W^-1)^-1 r``.
    m : (n,) float64
        Posterior mean ``mu0 + K a``.
    logdet_B, r_a : float
    Z : (k, k) float64
        ``L^-1 W^1/2`` at the columns of the rows asked for, in the order asked, without its
        leading ``n - k`` rows (zero).
    order : (n,) int64 or None
        The row order of ``L`` (None: the rows' own).
    """

    L: np.ndarray
    sw: np.ndarray
    a: np.ndarray
    m: np.ndarray
    logdet_B: float
    r_a: float
    Z: np.ndarray
    order: np.ndarray | None = None

    def in_factor_order(self, *arrays: np.ndarray) -> tuple[np.ndarray, ...]:
        """Per-row ``arrays`` in the row order of ``L`` (a posterior built on ``L`` needs its
        rows, weights and ``W^1/2`` in that order)."""
        return tuple(a if self.order is None else a[self.order] for a in arrays)

    def P_blocks(self, cols: np.ndarray) -> np.ndarray:
        """(b, s, s): ``P`` restricted to each row of ``cols`` ((b, s) positions in the order
        the rows were asked for), all blocks in one product."""
        Zc = self.Z[:, cols]  # (k, b, s)
        return np.einsum("kbi,kbj->bij", Zc, Zc)

    def P_block(self, cols: slice) -> np.ndarray:
        """``P`` restricted to the asked-for rows ``cols`` (a slice of their order)."""
        return self.P_blocks(np.arange(cols.start, cols.stop)[None, :])[0]

    def log_marginal(self, w: np.ndarray) -> float:
        """``log N(y | mu0, K + W^-1)`` (ALGORITHM.md L1)."""
        n = self.a.shape[0]
        return -0.5 * self.r_a - 0.5 * (self.logdet_B - np.sum(np.log(w))) - 0.5 * n * LOG_2PI


def factorize_blocks(
    K: np.ndarray, w: np.ndarray, r: np.ndarray, mu0: float, rows: np.ndarray
) -> BlockFactor:
    """Cholesky of ``B``, the posterior mean and ``P``'s columns at ``rows`` (see
    :class:`BlockFactor`; ``factorize`` gives the full set of moments and the gradient).

    Raises
    ------
    FactorizationError
        Non-finite values in ``K`` or ``w``.
    """
    n = K.shape[0]
    sw = np.sqrt(w)
    rows = np.asarray(rows, dtype=np.int64)
    k = rows.size
    order = None
    if k:  # the rows asked for last (in the order asked), the others before them
        last = np.zeros(n, dtype=bool)
        last[rows] = True
        order = np.concatenate([np.flatnonzero(~last), rows])
        if np.array_equal(order, np.arange(n)):
            order = None
    if order is None:
        L = _cholesky_B(K, sw)
        z, _ = lapack.dpotrs(L, sw * r, lower=1)
        a = sw * z
    else:
        swo = sw[order]
        L = _cholesky_B(K[np.ix_(order, order)], swo)
        z, _ = lapack.dpotrs(L, swo * r[order], lower=1)
        a = np.empty(n)
        a[order] = swo * z
    Z = np.zeros((0, 0))
    if k:
        Linv, info = lapack.dtrtri(L[n - k :, n - k :], lower=1)
        if info != 0:
            raise FactorizationError(f"inverse of B's trailing Cholesky block failed (info={info})")
        Z = Linv * sw[rows][None, :]
    return BlockFactor(
        L=L,
        sw=sw,
        a=a,
        m=mu0 + K @ a,
        logdet_B=2.0 * float(np.sum(np.log(np.diag(L)))),
        r_a=float(r @ a),
        Z=Z,
        order=order,
    )
