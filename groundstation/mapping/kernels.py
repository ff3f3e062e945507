"""Squared-exponential kernel (ALGORITHM.md §1) and its hyperparameter derivatives (M3).

``k(x, x') = sigma_f^2 exp(-|x - x'|^2 / (2 l^2))``. Hyperparameters are learnt in log units,
``theta = (log l, log sigma_f^2)``; the derivatives below are with respect to those.
"""

from __future__ import annotations

import numpy as np


def sq_dists(
    X1: np.ndarray, X2: np.ndarray | None = None, center: np.ndarray | None = None
) -> np.ndarray:
    """Squared Euclidean distances ``D_ij = |x1_i - x2_j|^2`` (ALGORITHM.md §1).

    Parameters
    ----------
    X1 : (n, d) float64, metres
    X2 : (m, d) float64, metres, optional
        Defaults to ``X1``; the result is then symmetric with an exact zero diagonal.
    center : (d,) float64, metres, optional
        Point subtracted before the GEMM expansion (default: mean of ``X1``). Pass the same
        centre for every chunk of a prediction so chunked and unchunked results agree.

    Returns
    -------
    D : (n, m) float64, metres^2, clipped at 0 (the GEMM expansion can round below 0).
    """
    X1 = np.asarray(X1, dtype=np.float64)
    same = X2 is None
    X2 = X1 if same else np.asarray(X2, dtype=np.float64)
    # Centre on X1's mean so the expansion |a|^2 + |b|^2 - 2ab loses fewer digits far from 0.
    if center is not None:
        c = np.asarray(center, dtype=np.float64)
    else:
        c = X1.mean(axis=0) if X1.shape[0] else np.zeros(X1.shape[1])
    A = X1 - c
    Bm = A if same else X2 - c
    D = A @ Bm.T
    D *= -2.0
    D += np.einsum("ij,ij->i", A, A)[:, None]
    D += np.einsum("ij,ij->i", Bm, Bm)[None, :]
    np.maximum(D, 0.0, out=D)
    if same:
        np.fill_diagonal(D, 0.0)
        D = 0.5 * (D + D.T)
    return D


def se_from_sq_dists(
    D: np.ndarray, lengthscale: float, signal_var: float, out: np.ndarray | None = None
) -> np.ndarray:
    """Squared-exponential kernel from squared distances.

    Parameters
    ----------
    D : (n, m) float64, metres^2
    lengthscale : float, metres
    signal_var : float, label units^2
    out : (n, m) float64, optional
        Buffer to write into (may be ``D`` itself).

    Returns
    -------
    K : (n, m) float64, ``signal_var * exp(-D / (2 lengthscale^2))``
    """
    out = np.multiply(D, -0.5 / (lengthscale * lengthscale), out=out)
    np.exp(out, out=out)
    out *= signal_var
    return out


def se_kernel(
    X1: np.ndarray, X2: np.ndarray | None, lengthscale: float, signal_var: float
) -> np.ndarray:
    """Squared-exponential kernel matrix ``k(X1, X2)``.

    Parameters
    ----------
    X1 : (n, d) float64, metres
    X2 : (m, d) float64, metres, or None for ``X1``
    lengthscale : float, metres
    signal_var : float, label units^2

    Returns
    -------
    K : (n, m) float64
    """
    D = sq_dists(X1, X2)
    return se_from_sq_dists(D, lengthscale, signal_var, out=D)


def se_grad_log_params(
    K: np.ndarray, D: np.ndarray, lengthscale: float
) -> tuple[np.ndarray, np.ndarray]:
    """Derivatives of ``K`` with respect to ``(log l, log sigma_f^2)`` (ALGORITHM.md M3).

    ``dK/dlog l = K o D / l^2`` and ``dK/dlog sigma_f^2 = K``. Allocates one n x m array; the
    estimators contract these with ``a a^T - P`` without forming them (see ``_linalg``).

    Returns
    -------
    dK_dlog_l, dK_dlog_sf2 : (n, m) float64
    """
    return K * D / (lengthscale * lengthscale), K


def se_mixed(
    X1: np.ndarray,
    V1: np.ndarray,
    X2: np.ndarray,
    V2: np.ndarray,
    lengthscale: float,
    signal_var: float,
    center: np.ndarray | None = None,
) -> np.ndarray:
    """Covariances of values and directional derivatives of a GP with the SE kernel.

    Row i of ``X1`` is the value ``f(x_i)`` when ``V1[i] = 0``, else the derivative of f at
    ``x_i`` along the unit vector ``V1[i]`` (the same for ``X2``, ``V2``). With ``a = x - x'``
    and ``k = k(x, x')``::

        cov(f(x), f(x'))                 = k
        cov(f(x), d_v f(x'))             = k (a . v) / l^2
        cov(d_u f(x), f(x'))             = -k (a . u) / l^2
        cov(d_u f(x), d_v f(x'))         = k [(u . v) / l^2 - (a . u)(a . v) / l^4]

    Parameters
    ----------
    X1 : (n, d), V1 : (n, d), X2 : (m, d), V2 : (m, d) float64
    lengthscale, signal_var : float
    center : (d,) float64, optional
        Passed to :func:`sq_dists`.

    Returns
    -------
    K : (n, m) float64
    """
    X1 = np.asarray(X1, dtype=np.float64)
    X2 = np.asarray(X2, dtype=np.float64)
    V1 = np.asarray(V1, dtype=np.float64)
    V2 = np.asarray(V2, dtype=np.float64)
    K = se_from_sq_dists(sq_dists(X1, X2, center=center), lengthscale, signal_var)
    d1 = np.einsum("ij,ij->i", V1, V1) > 0.0
    d2 = np.einsum("ij,ij->i", V2, V2) > 0.0
    if not d1.any() and not d2.any():
        return K
    # The factor differs from 1 only in the rows and columns of derivatives (a few per
    # cent of them): scale those blocks in place, never a temporary of K's size per case.
    l2 = lengthscale * lengthscale
    r1, c2 = np.flatnonzero(d1), np.flatnonzero(d2)
    if c2.size:
        Xc, Vc = X2[c2], V2[c2]
        dot_v2 = X1 @ Vc.T - np.einsum("ij,ij->i", Xc, Vc)[None, :]  # (x_i - x'_j) . v_j
        block = dot_v2 / l2
        if r1.size:
            U = V1[r1]
            dot_u1 = np.einsum("ij,ij->i", X1[r1], U)[:, None] - U @ Xc.T  # (x_i - x'_j) . u_i
            block[r1] = (U @ Vc.T) / l2 - dot_u1 * dot_v2[r1] / (l2 * l2)
        K[:, c2] *= block
    if r1.size:
        v2 = np.flatnonzero(~d2)
        U = V1[r1]
        dot_u1 = np.einsum("ij,ij->i", X1[r1], U)[:, None] - U @ X2[v2].T
        K[np.ix_(r1, v2)] *= -dot_u1 / l2
    return K
