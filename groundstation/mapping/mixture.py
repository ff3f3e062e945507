"""Event-mixture GPIS: every contact event is true or false, decided by its prior and the rest of
the data (ALGORITHM.md §11-§12). Pure: no clocks, files or threads.

Model
-----
A GP ``f ~ GP(mu0, k)`` (squared exponential) explains the shape potential. Rows come in
*groups*: the rows of one contact event (its contact and internal points) form a group with a
latent ``z_g`` (true or false) and a prior ``pi_g = P(z_g = false)`` (the detector's ``p_false``
from the impulse's physics, or a default); free-space rows are their own trusted group (-1).
Given ``z_g``, a row's label is ``y_i ~ N(f_i, s_i^2)`` when true (``s_i``: its placement noise)
and ``y_i ~ N(f_i, s_out^2)`` when false (``s_out`` on the label scale: nothing ties it to f).

Fit (an EM on the two-component mixture, one responsibility per group)
----------------------------------------------------------------------
1. Responsibilities ``r_g = P(z_g = false | data)`` start at the priors (or the last fit's).
2. The GP is fitted with every group decided: precision ``1 / s_i^2`` for the rows of a group
   decided true (``r_g`` at most its decision line), ``1 / s_out^2`` for the others (a
   classification EM: the mean-field expectation of the precision would let a 90 % false
   group still draw its phantom patch),
   factorised in the B form (``_linalg.factorize_blocks``: only the blocks of P step 3 needs).
3. Each *burst* (groups close in time and space: ``mapping/events.py``) is left out as a whole,
   in closed form from ``P = (K + W^-1)^-1``: ``e_B = P_BB^-1 a_B`` is the residual of the
   burst's labels from the prediction of the other data, ``P_BB^-1`` its covariance (R&W 5.4.2
   for blocks; ALGORITHM.md §12). For each group g of the burst, the log likelihood ratio of
   false against true is

       llr_g = log N(e_g; 0, v_g + s_out^2) - log N(e_g; 0, v_g + s_g^2)

   on the group's mean residual ``e_g`` (its rows share one placement: they are one piece of
   evidence), with ``v_g`` its latent predictive variance (from ``P_BB^-1`` minus the rows'
   current noise) and ``s_g^2`` its rows' mean noise. Leaving out the whole burst is what
   makes a cluster of consistent false contacts (a gust that keeps hitting one spot) unable to
   vouch for itself.
4. ``r_g = sigmoid(logit pi_g + llr_g + extra_g)`` (``extra_g``: other evidence, e.g. the
   body's swept volume, ``mapping/training.py``), then back to 2 until no ``r_g`` moves by
   ``tol`` (or until no decision changes and the posteriors move less than ``tol``).

The kernel hyperparameters maximise the weighted GP's evidence ``log N(y | mu0, K + W^-1)`` with
``W`` fixed (L-BFGS-B on the M3 gradient), inside :class:`KernelBounds` (tied to the map's
resolution), when asked for (``learn_kernel``): at the first iteration of a fit.

``posterior_false_`` is a calibrated probability per group; a group is decided (fitted and
flagged) false when it exceeds its decision line (``Groups.decide_p``, or the estimator's
``decide_p`` for all): 1/2 minimises errors for equal costs, and ``c / (1 + c)`` minimises the
expected cost when trusting a false contact costs ``1 / c`` times as much as dropping a true one.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.optimize import minimize

from groundstation.errors import InputDataError, NotFittedError
from groundstation.mapping._linalg import BlockFactor, factorize, factorize_blocks
from groundstation.mapping.kernels import se_from_sq_dists, se_mixed, sq_dists

LOG_2PI = math.log(2.0 * math.pi)
_PRIOR_CLIP = 1e-4
_EXCLUDED = 1e4  # a group decided false is fitted with this times the outlier variance


@dataclasses.dataclass(frozen=True)
class KernelBounds:
    """Bounds of the learnt kernel hyperparameters.

    Attributes
    ----------
    lengthscale : (lo, hi), metres
        The finest detail the map resolves and the smoothest it may become.
    signal_var : (lo, hi), label units^2
    """

    lengthscale: tuple[float, float]
    signal_var: tuple[float, float]

    def __post_init__(self) -> None:
        for name in ("lengthscale", "signal_var"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise InputDataError(
                    f"kernel bounds: {name} must satisfy 0 < lo <= hi, got {lo, hi}"
                )

    def clip(self, lengthscale: float, signal_var: float) -> tuple[float, float]:
        return (
            float(np.clip(lengthscale, *self.lengthscale)),
            float(np.clip(signal_var, *self.signal_var)),
        )

    def at_bound(
        self, lengthscale: float, signal_var: float, rtol: float = 1e-3
    ) -> tuple[str, ...]:
        """Which bounds the values sit on (for the fit summary)."""
        out = []
        lo, hi = self.lengthscale
        if lengthscale <= lo * (1 + rtol):
            out.append("lengthscale_lower")
        if lengthscale >= hi * (1 - rtol):
            out.append("lengthscale_upper")
        lo, hi = self.signal_var
        if signal_var <= lo * (1 + rtol):
            out.append("signal_var_lower")
        if signal_var >= hi * (1 - rtol):
            out.append("signal_var_upper")
        return tuple(out)


@dataclasses.dataclass(frozen=True)
class MixtureFit:
    """Summary of one :meth:`EventMixtureGPIS.fit` (frozen; what the mapper, ``diagnose`` and
    the benches read).

    Attributes
    ----------
    lengthscale, signal_var : float
    log_marginal : float
        ``log N(y | mu0, K + W^-1)`` at the final weights.
    n_iter : int
        EM iterations (factorisations) used.
    converged : bool
        No responsibility moved by more than ``tol`` at the last iteration.
    at_bounds : tuple of str
        Kernel bounds the hyperparameters sit on.
    n_train : int
    n_groups : int
    n_flagged : int
        Groups decided false (posterior P(false) above the group's decision line).
    reasons : tuple of str
        Why the fit may not be trusted (empty when fine).
    kernel_held : bool
        The last kernel step asked for the length-scale cap and was not taken
        (``mapping.hold_at_cap``): the kernel in force was not learnt from these data.
    """

    lengthscale: float
    signal_var: float
    log_marginal: float
    n_iter: int
    converged: bool
    at_bounds: tuple[str, ...]
    n_train: int
    n_groups: int
    n_flagged: int
    reasons: tuple[str, ...] = ()
    kernel_held: bool = False


@dataclasses.dataclass(frozen=True)
class Groups:
    """Which rows belong to which group, and the groups' bursts and priors.

    Attributes
    ----------
    row_group : (n,) int64
        Group index of each row, -1 for trusted rows (free space).
    prior_false : (G,) float64
        ``P(z_g = false)`` before the data.
    burst : (G,) int64
        Burst index of each group (groups of one burst are left out together).
    extra_llr : (G,) float64
        Further log likelihood ratios (false vs true) from outside the GP.
    companion : (n,) int64, optional
        For a trusted row (``row_group`` -1), the group it is left out with when that group's
        burst is tested, -1 for none: the vehicle's own free-space samples at a contact event
        (``mapping/training.py``). It stays in the fit with its own precision.
    decide_p : (G,) float64, optional
        Each group's decision line: decided false when its posterior P(false) exceeds it
        (default: the estimator's ``decide_p`` for every group).
    """

    row_group: np.ndarray
    prior_false: np.ndarray
    burst: np.ndarray
    extra_llr: np.ndarray
    companion: np.ndarray | None = None
    decide_p: np.ndarray | None = None

    def __post_init__(self) -> None:
        g = self.prior_false.shape[0]
        if self.burst.shape != (g,) or self.extra_llr.shape != (g,):
            raise InputDataError(
                "groups: prior_false, burst and extra_llr need one entry per group"
            )
        if self.row_group.size and self.row_group.max(initial=-1) >= g:
            raise InputDataError("groups: a row refers to a group that does not exist")
        if self.companion is not None:
            c = self.companion
            if c.shape != self.row_group.shape or (c.size and c.max(initial=-1) >= g):
                raise InputDataError("groups: companion needs one group (or -1) per row")
            if np.any((c >= 0) & (self.row_group >= 0)):
                raise InputDataError("groups: a row of a group cannot be another's companion")
        if self.decide_p is not None:
            line = self.decide_p
            if line.shape != (g,) or not np.all((line > 0.0) & (line < 1.0)):
                raise InputDataError("groups: decide_p needs one line in (0, 1) per group")

    def lines(self, default: float) -> np.ndarray:
        """(G,) each group's decision line (``default`` where none is given)."""
        if self.decide_p is None:
            return np.full(self.prior_false.shape[0], float(default))
        return self.decide_p


@dataclasses.dataclass(frozen=True)
class MixedPosterior:
    """A fitted GP over value and derivative rows, frozen for grid evaluation:
    mean = mu0 + k*^T a, var = k** - |L^-1 W^1/2 k*|^2 (k* from ``kernels.se_mixed``)."""

    X: np.ndarray
    V: np.ndarray
    center: np.ndarray
    a: np.ndarray
    L: np.ndarray
    sw: np.ndarray
    mu0: float
    lengthscale: float
    signal_var: float

    def predict(
        self, Xs: np.ndarray, return_std: bool = False, chunk_mb: float = 64.0
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Mean (m,) and, if ``return_std``, latent std (m,) of f at ``Xs`` (m, d)."""
        from scipy.linalg import solve_triangular

        m_pts = Xs.shape[0]
        n = self.X.shape[0]
        mean = np.empty(m_pts)
        std = np.empty(m_pts) if return_std else None
        step = max(1, int(chunk_mb * 1e6 // (8.0 * n * (4 if return_std else 3))))
        inv_l2 = 1.0 / (self.lengthscale * self.lengthscale)
        # k(q, x) = sf2 exp(q.x / l^2 - |q|^2 / 2l^2 - |x|^2 / 2l^2) (centred): one GEMM, a
        # clip and an exp over the (m, n) block, sf2 folded into the weights. Columns
        # in the order value rows, then derivative rows: the derivative factor is applied to a
        # contiguous slice (an indexed update of the block costs more than the exp).
        is_d = np.einsum("ij,ij->i", self.V, self.V) > 0.0
        order = np.concatenate([np.flatnonzero(~is_d), np.flatnonzero(is_d)])
        nv = n - int(is_d.sum())
        back = np.argsort(order)
        B = self.X[order] - self.center
        # the exponent as one GEMM: [q, -|q|^2 / 2l^2, 1] @ [x / l^2; 1; -|x|^2 / 2l^2]
        Bt = np.vstack([B.T * inv_l2, np.ones(n), -0.5 * inv_l2 * np.einsum("ij,ij->i", B, B)])
        a = self.signal_var * self.a[order]
        Vd = self.V[order[nv:]].T * inv_l2
        xv = np.einsum("ij,ji->i", B[nv:], Vd)  # (x_j - c) . v_j / l^2
        sw = self.signal_var * self.sw
        for start in range(0, m_pts, step):
            stop = min(start + step, m_pts)
            A = Xs[start:stop] - self.center
            a_half = -0.5 * inv_l2 * np.einsum("ij,ij->i", A, A)
            Ks = np.column_stack([A, a_half, np.ones(stop - start)]) @ Bt
            np.minimum(Ks, 0.0, out=Ks)  # rounding can put a coincident point above 0
            np.exp(Ks, out=Ks)
            if nv < n:  # cov(f(q), d_v f(x_j)) = k (q - x_j) . v_j / l^2
                dot = A @ Vd
                dot -= xv[None, :]
                Ks[:, nv:] *= dot
            mean[start:stop] = self.mu0 + Ks @ a
            if std is not None:
                Kw = np.take(Ks, back, axis=1)  # back in the factor's row order
                Kw *= sw[None, :]
                v = solve_triangular(self.L, Kw.T, lower=True, check_finite=False)
                var = self.signal_var - np.einsum("ij,ij->j", v, v)
                std[start:stop] = np.sqrt(np.maximum(var, 0.0))
        if std is None:
            return mean
        return mean, std


def _log_normal_v(e: np.ndarray, var: np.ndarray) -> np.ndarray:
    """log N(e; 0, var), elementwise."""
    return -0.5 * (e * e / var + np.log(var) + LOG_2PI)


def _inverses(P: np.ndarray) -> np.ndarray:
    """(b, s, s) inverses of a stack of blocks (the pseudo-inverse of a singular one)."""
    try:
        return np.linalg.inv(P)
    except np.linalg.LinAlgError:
        out = np.empty_like(P)
        for i, Pi in enumerate(P):
            try:
                out[i] = np.linalg.inv(Pi)
            except np.linalg.LinAlgError:
                out[i] = np.linalg.pinv(Pi)
        return out


def _checked(X, y, noise_var, groups: Groups, start, directions) -> tuple:
    """Validated fit inputs: (X, y, noise_var, directions, clipped priors, responsibilities)."""
    X = np.asarray(X, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    s2 = np.asarray(noise_var, dtype=np.float64)
    n = X.shape[0]
    if X.ndim != 2 or y.shape != (n,) or s2.shape != (n,) or groups.row_group.shape != (n,):
        raise InputDataError(f"fit: X (n, d), y, noise_var and row groups must agree, n = {n}")
    if n < 2 or not (np.isfinite(X).all() and np.isfinite(y).all()):
        raise InputDataError("fit: need at least 2 finite rows")
    if not (s2 > 0).all():
        raise InputDataError("fit: noise variances must be > 0")
    prior = np.clip(groups.prior_false, _PRIOR_CLIP, 1 - _PRIOR_CLIP)
    r = prior.copy() if start is None else np.clip(np.asarray(start, float), 0.0, 1.0)
    if r.shape != prior.shape:
        raise InputDataError("fit: start must have one entry per group")
    V = np.zeros_like(X) if directions is None else np.asarray(directions, dtype=np.float64)
    if V.shape != X.shape:
        raise InputDataError("fit: directions must have the shape of X")
    return X, y, s2, V, prior, r


def kernel_blocks(X: np.ndarray, max_rows: int) -> list[np.ndarray]:
    """Rows of ``X`` (n, d) cut into spatial blocks of at most ``max_rows`` (all of them in one
    block when ``max_rows`` is 0 or at least n): each block is halved at the median of its
    longest side until small enough, so blocks stay compact (about cubes) and even in size."""
    X = np.asarray(X, dtype=np.float64)
    todo, out = [np.arange(X.shape[0])], []
    while todo:
        b = todo.pop()
        if max_rows <= 0 or b.size <= max_rows:
            out.append(b)
            continue
        axis = int(np.argmax(np.ptp(X[b], axis=0)))
        order = b[np.argsort(X[b, axis], kind="stable")]
        todo += [order[order.size // 2 :], order[: order.size // 2]]
    return [np.sort(b) for b in out]


class EventMixtureGPIS:
    """GP implicit surface with one true/false latent per contact event (module docstring).

    Parameters
    ----------
    lengthscale, signal_var : float
        Initial kernel hyperparameters (clipped into ``bounds``).
    bounds : KernelBounds
    outlier_var : float
        ``s_out^2``: label variance of a false group's rows.
    prior_mean : float
        ``mu0``.
    learn_kernel : bool
        Maximise the evidence over the kernel hyperparameters at the first iteration.
    max_iter : int
        EM iterations (factorisations) at most.
    tol : float
        Convergence: largest change of a responsibility.
    kernel_iter : int
        L-BFGS-B iterations of a kernel step.
    kernel_block_rows : int
        A kernel step on more value rows than this maximises the sum of the evidences of
        spatial blocks of at most this many rows (:func:`kernel_blocks`) instead of the evidence
        of all of them (0: always all). Each evaluation factorises its rows in full (the
        gradient needs ``P``), so its cost grows with their cube; blocks many length scales wide
        lose only the correlations across their faces (the product-of-experts training of
        Deisenroth & Ng, "Distributed Gaussian Processes", ICML 2015).
    flag_inside : bool
        Whether a group that the rest of the data places inside the structure (mean residual
        ``e_g > 0``: its labels lie above the prediction) may gain evidence for 'false'. Off,
        its ``llr_g`` is at most 0: a false contact lies where the vehicle flew, in free space.
    chunk_mb : float
        Memory budget of one prediction chunk.
    decide_p : float
        A group whose posterior P(false) exceeds this is decided false: fitted with the
        outlier variance, and flagged (``mapper.flag_p``; 1/2 minimises errors for equal costs).
        ``Groups.decide_p`` gives a group its own line instead.
    """

    def __init__(
        self,
        *,
        lengthscale: float,
        signal_var: float,
        bounds: KernelBounds,
        outlier_var: float = 1.0,
        prior_mean: float = 0.0,
        learn_kernel: bool = True,
        max_iter: int = 20,
        tol: float = 1e-3,
        kernel_iter: int = 15,
        kernel_block_rows: int = 0,
        flag_inside: bool = False,
        chunk_mb: float = 64.0,
        decide_p: float = 0.5,
    ) -> None:
        if not outlier_var > 0 or max_iter < 1 or not tol > 0:
            raise InputDataError("outlier_var > 0, max_iter >= 1 and tol > 0 are required")
        if not 0.0 < decide_p < 1.0:
            raise InputDataError(f"decide_p must be in (0, 1), got {decide_p!r}")
        self.bounds = bounds
        self.lengthscale, self.signal_var = bounds.clip(lengthscale, signal_var)
        self.outlier_var = float(outlier_var)
        self.prior_mean = float(prior_mean)
        self.learn_kernel = bool(learn_kernel)
        self.max_iter = int(max_iter)
        self.tol = float(tol)
        self.kernel_iter = int(kernel_iter)
        self.kernel_block_rows = int(kernel_block_rows)
        self.flag_inside = bool(flag_inside)
        self.chunk_mb = float(chunk_mb)
        self.decide_p = float(decide_p)
        self.fit_: MixtureFit | None = None

    # ------------------------------------------------------------------ fitting

    def fit(
        self,
        X: np.ndarray,
        y: np.ndarray,
        noise_var: np.ndarray,
        groups: Groups,
        start: np.ndarray | None = None,
        theta: tuple[float, float] | None = None,
        directions: np.ndarray | None = None,
    ) -> EventMixtureGPIS:
        """Fit (module docstring).

        Parameters
        ----------
        X : (n, d) float64, metres
        y : (n,) float64, label units (potential values)
        noise_var : (n,) float64, > 0
            Each row's variance when its group is true.
        groups : Groups
        start : (G,) float64, optional
            Starting responsibilities (a warm start); default the priors.
        theta : (lengthscale, signal_var), optional
            Starting kernel hyperparameters (default the constructor's).
        directions : (n, d) float64, optional
            Zero for value rows; a unit vector makes the row the derivative of f along it
            (``kernels.se_mixed``): a contact's tangent plane, with ``y = 0``. The kernel is
            learnt on the value rows only.

        Returns
        -------
        self
        """
        X, y, s2, V, prior, r = _checked(X, y, noise_var, groups, start, directions)
        n = X.shape[0]
        line = groups.lines(self.decide_p)
        ell, sf2 = self.bounds.clip(*(theta or (self.lengthscale, self.signal_var)))
        is_val = np.einsum("ij,ij->i", V, V) == 0.0
        center = X.mean(axis=0)
        rg = groups.row_group
        in_group = rg >= 0
        bursts = self._burst_rows(groups)
        resid = y - self.prior_mean
        resid = np.where(is_val, resid, y)  # a derivative's prior mean is 0
        converged = False
        cycled = False
        seen: set[bytes] = set()
        burst_rows = np.concatenate(bursts) if bursts else np.zeros(0, dtype=np.int64)
        cuts = np.cumsum([0] + [b.size for b in bursts])
        spans = [slice(int(cuts[k]), int(cuts[k + 1])) for k in range(len(bursts))]
        fac: BlockFactor | None = None
        K: np.ndarray | None = None
        llr = np.zeros_like(r)
        it = 0
        for it in range(1, self.max_iter + 1):
            w = self._precisions(s2, rg, in_group, r > line)
            if it == 1:  # the kernel is fixed after the first iteration
                if self.learn_kernel:
                    ell, sf2 = self._kernel_step(
                        X[is_val], center, w[is_val], resid[is_val], ell, sf2
                    )
                K = se_mixed(X, V, X, V, ell, sf2, center=center)
            fac = factorize_blocks(K, w, resid, self.prior_mean, burst_rows)
            llr = self._leave_burst_out(fac, w, s2, rg, bursts, spans, r.size, is_val)
            logit = np.log(prior) - np.log1p(-prior) + llr + groups.extra_llr
            r_new = 1.0 / (1.0 + np.exp(-np.clip(logit, -50.0, 50.0)))
            delta = float(np.max(np.abs(r_new - r))) if r.size else 0.0
            same = bool(np.array_equal(r_new > line, r > line))
            seen.add((r > line).tobytes())
            r = r_new
            # the fit depends on the decisions only: once none flips and the posteriors
            # settle, another iteration changes nothing the map shows
            if delta < self.tol or (same and delta < 10.0 * self.tol):
                converged = True
                break
            if not same and (r > line).tobytes() in seen:
                # decisions came back to an earlier set: a cycle between groups that explain
                # each other away; stop with the posteriors of this iteration
                cycled = True
                break
        # the posterior of the final decisions (the last factor already is, unless one flipped)
        w_final = self._precisions(s2, rg, in_group, r > line)
        if fac is None or not np.array_equal(w_final, w):
            fac = factorize_blocks(K, w_final, resid, self.prior_mean, burst_rows[:0])
        w = w_final
        self.X_train_, self.y_train_ = X, y
        self.posterior_false_ = r
        self.llr_ = llr
        self.weights_ = w
        self.lengthscale_, self.signal_var_ = ell, sf2
        Xo, Vo, ao, swo = fac.in_factor_order(X, V, fac.a, fac.sw)
        self.posterior_ = MixedPosterior(Xo, Vo, center, ao, fac.L, swo, self.prior_mean, ell, sf2)
        self.mean_train_ = fac.m
        at = self.bounds.at_bound(ell, sf2)
        self.fit_ = MixtureFit(
            lengthscale=ell,
            signal_var=sf2,
            log_marginal=float(fac.log_marginal(w)),
            n_iter=it,
            converged=converged,
            at_bounds=at,
            n_train=n,
            n_groups=int(r.size),
            n_flagged=int(np.sum(r > line)),
            reasons=() if converged else (("decisions_cycle",) if cycled else ("not_converged",)),
        )
        return self

    def learn_theta(
        self,
        X: np.ndarray,
        y: np.ndarray,
        noise_var: np.ndarray,
        groups: Groups,
        start: np.ndarray | None = None,
        directions: np.ndarray | None = None,
    ) -> tuple[float, float]:
        """The kernel hyperparameters ``(lengthscale, signal_var)`` that :meth:`fit` with
        ``learn_kernel`` would learn from these inputs: its first iteration's kernel step, without
        the EM that follows (the kernel is fixed after it), for a caller that wants only them."""
        X, y, s2, V, _, r = _checked(X, y, noise_var, groups, start, directions)
        is_val = np.einsum("ij,ij->i", V, V) == 0.0
        rg = groups.row_group
        w = self._precisions(s2, rg, rg >= 0, r > groups.lines(self.decide_p))
        ell, sf2 = self.bounds.clip(self.lengthscale, self.signal_var)
        resid = y[is_val] - self.prior_mean
        return self._kernel_step(X[is_val], X.mean(axis=0), w[is_val], resid, ell, sf2)

    def _precisions(self, s2, rg, in_group, decided) -> np.ndarray:
        """Row precisions for the GP: a group decided false (``decided``, (G,) bool: its
        posterior above its line) counts with the outlier variance, one decided true with its
        own noise. (The mean-field expectation ``(1 - r) / s^2 + r / s_out^2`` lets a group
        that is 90 % false still pull the surface with a tenth of a true contact's weight, a
        phantom patch the map then draws.)"""
        w = 1.0 / s2
        if decided.size:
            false = in_group & decided[np.maximum(rg, 0)]
            w = np.where(false, 1.0 / (_EXCLUDED * self.outlier_var), w)
        return w

    @staticmethod
    def _burst_rows(groups: Groups) -> list[np.ndarray]:
        """Row indices of each burst (bursts of groups that have rows), with the companions
        of its groups."""
        rg = groups.row_group
        if groups.companion is not None:
            rg = np.where(rg >= 0, rg, groups.companion)
        rows = np.flatnonzero(rg >= 0)
        if rows.size == 0:
            return []
        b_of_row = groups.burst[rg[rows]]
        order = np.argsort(b_of_row, kind="stable")
        rows, b_sorted = rows[order], b_of_row[order]
        cuts = np.flatnonzero(np.diff(b_sorted)) + 1
        return np.split(rows, cuts)

    def _leave_burst_out(
        self, fac: BlockFactor, w, s2, rg, bursts, spans, n_groups, is_val
    ) -> np.ndarray:
        """llr (false vs true) of every group from its burst's leave-out residual.

        A group's rows are not independent evidence: its contact samples lie a few
        millimetres apart and its internal point is the contact moved by ``d_in``, true or
        false alike. So each group is judged on its mean residual ``e_g = mean_i e_i``, whose
        latent variance is ``v_g = mean_ij V_ij``: ``N(e_g; 0, v_g + s_g^2)`` if true
        (``s_g^2``: the mean row noise, the rows sharing one placement error) against
        ``N(e_g; 0, v_g + s_out^2)`` if false.
        """
        llr = np.zeros(n_groups)
        sizes = np.array([b.size for b in bursts], dtype=np.int64)
        for size in np.unique(sizes).tolist():  # bursts of one size at a time, batched
            which = np.flatnonzero(sizes == size)
            rows = np.stack([bursts[b] for b in which])  # (nb, s)
            cols = np.stack([np.arange(spans[b].start, spans[b].stop) for b in which])
            C = _inverses(fac.P_blocks(cols))  # P_BB^-1
            e = np.einsum("bij,bj->bi", C, fac.a[rows])  # y_B - E[y_B | rest]
            V = C  # latent predictive covariance of f_B | rest: C - W_B^-1
            diag = np.arange(size)
            V[:, diag, diag] -= 1.0 / w[rows]
            # (burst, group) units over the groups' value rows: companions (-1) are left out
            # with the burst but are not its evidence, and slopes are not label residuals
            g_rows = rg[rows]
            sel = (g_rows >= 0) & is_val[rows]
            if not sel.any():
                continue
            unit = np.full(rows.shape, -1, dtype=np.int64)
            groups_here, unit[sel] = np.unique(g_rows[sel], return_inverse=True)
            U = groups_here.size
            n = np.bincount(unit[sel], minlength=U).astype(np.float64)
            eg = np.bincount(unit[sel], weights=e[sel], minlength=U) / n
            sg = np.bincount(unit[sel], weights=s2[rows][sel], minlength=U) / n
            same = (unit[:, :, None] == unit[:, None, :]) & (unit[:, :, None] >= 0)
            by = np.broadcast_to(unit[:, :, None], same.shape)[same]
            vg = np.maximum(np.bincount(by, weights=V[same], minlength=U) / (n * n), 0.0)
            out = _log_normal_v(eg, vg + self.outlier_var) - _log_normal_v(eg, vg + sg)
            if not self.flag_inside:  # placed inside by the rest: not a gust's point
                out = np.where(eg > 0, np.minimum(out, 0.0), out)
            llr[groups_here] = out
        return llr

    def _kernel_step(self, Xv, center, w, resid, ell, sf2) -> tuple[float, float]:
        """Maximise log N(y | mu0, K + W^-1) over (log l, log sf2) within the bounds, on the
        value rows ``Xv``: summed over :func:`kernel_blocks` when there are more than
        ``kernel_block_rows`` of them."""
        lo = np.log([self.bounds.lengthscale[0], self.bounds.signal_var[0]])
        hi = np.log([self.bounds.lengthscale[1], self.bounds.signal_var[1]])
        blocks = kernel_blocks(Xv, self.kernel_block_rows)
        parts = [(b, sq_dists(Xv[b], Xv[b], center=center)) for b in blocks]

        def fun(th: np.ndarray):
            e, s = float(np.exp(th[0])), float(np.exp(th[1]))
            value, grad = 0.0, np.zeros(2)
            for b, D in parts:
                K = se_from_sq_dists(D.copy(), e, s)
                fac = factorize(K, D, w[b], resid[b], self.prior_mean, e)
                value -= fac.log_marginal(w[b])
                grad -= fac.grad
            return value, grad

        x0 = np.clip(np.log([ell, sf2]), lo, hi)
        try:
            res = minimize(
                fun, x0, jac=True, method="L-BFGS-B", bounds=list(zip(lo, hi, strict=True)),
                options={"maxiter": self.kernel_iter},
            )  # fmt: skip
            th = res.x if np.all(np.isfinite(res.x)) else x0
        except (ArithmeticError, ValueError, np.linalg.LinAlgError):
            th = x0
        return self.bounds.clip(float(np.exp(th[0])), float(np.exp(th[1])))

    # ------------------------------------------------------------------ prediction

    def _check(self) -> None:
        if self.fit_ is None:
            raise NotFittedError("this EventMixtureGPIS is not fitted yet", hint="call fit first")

    def predict(
        self, Xq: np.ndarray, return_std: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Posterior mean (m,) and, if ``return_std``, latent std (m,) at ``Xq`` (m, d)."""
        self._check()
        return self.posterior_.predict(np.asarray(Xq, float), return_std, self.chunk_mb)
