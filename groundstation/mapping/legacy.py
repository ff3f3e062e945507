"""The legacy mapping engine (``mapping.engine = legacy``): merge -> fit (exact or sparse,
warm-started) -> field -> mesh, flags by a margin on u.

DESIGN.md §3 "Model no more than the scene needs": :class:`LegacySurfaceModel` merges redundant
observations (``merge.py``: incremental radius merge by default, radii frozen until the learnt
length scale moves them by ``merge_hysteresis``), fits the exact :class:`RobustGPIS` while the
merged set fits ``exact_budget`` and the sparse :class:`SparseRobustGPIS` beyond it (same
weights, ALGORITHM.md §8), and warm-starts every refit from the previous one. Warm refits keep
the kernel hyperparameters unless the merged set grew by ``theta_refit_growth`` and stop when
no ``log u_i`` moves by ``refit_u_tol``, so a covered structure refits in a few cheap
iterations; a fit stuck at the Gaussian limit is redone cold at such a growth step. Only a
narrow band around the zero set is meshed (``field.py``), on a grid whose spacing follows the
learnt length scale.
Pure: no clock reads except the ``timings_`` it reports, no files, no threads.
"""

from __future__ import annotations

import math
import time
import warnings
from typing import NamedTuple

import numpy as np

from groundstation.errors import ConvergenceWarning, InputDataError, NotFittedError
from groundstation.mapping._linalg import blas_threads
from groundstation.mapping.field import BandField, narrow_band_field
from groundstation.mapping.gpis import GPIS
from groundstation.mapping.grid import Grid
from groundstation.mapping.merge import StreamingMerger, TrainingSet, merge_observations
from groundstation.mapping.robust import RobustGPIS
from groundstation.mapping.settings import MappingSettings, SurfaceSettings
from groundstation.mapping.sparse import SparseRobustGPIS, choose_inducing
from groundstation.mapping.surface import SurfaceMesh, confident_part, extract_surface
from groundstation.mapping.validation import check_inputs

# Fitted state handed to the other estimator when the mode switches (exact <-> sparse): both
# warm-start from (theta, alpha, beta), q(tau) of a common prefix and the predictive moments.
_HANDOVER = (
    "X_train_",
    "y_train_",
    "alpha_tilde_",
    "beta_tilde_",
    "lengthscale_",
    "signal_var_",
    "alpha_",
    "beta_",
    "posterior_",
    "_rprop_step",
)


_DEFAULT_MAPPING = MappingSettings()  # frozen: safe to share as argument defaults
_DEFAULT_SURFACE = SurfaceSettings()


class IdUncertainty(NamedTuple):
    """Per raw observation: ``ids`` (N,) int64 and the ``u`` (N,) float64 of its merged cell."""

    ids: np.ndarray
    u: np.ndarray


def _quantised(lengthscale: float) -> float:
    """Length scale rounded to a power of sqrt(2) (stable voxel sizes between refits)."""
    return 2.0 ** (round(2.0 * math.log2(lengthscale)) / 2.0)


class LegacySurfaceModel:
    """Default mapping pipeline (see the module docstring).

    Parameters
    ----------
    mapping : MappingSettings
    surface : SurfaceSettings

    Attributes (after ``fit``)
    --------------------------
    fit_ : RobustGPIS | SparseRobustGPIS | GPIS
        The underlying estimator of the last fit.
    mode_ : "exact" | "sparse"
    training_set_ : TrainingSet
        The merged training set of the last fit.
    n_train_, n_raw_ : int
        Merged and raw observation counts.
    suspect_ids_ : (k,) int64
        Ids flagged as suspected false contacts by the last fit (kept apart at the next merge).
    converged_ : bool
    timings_ : dict
        ``merge_s``, ``fit_s`` (last ``fit``), ``field_s``, ``mesh_s`` (last ``mesh``), seconds.
    last_field_ : BandField
        The narrow-band field of the last ``mesh`` call.
    cold_checks_, cold_wins_ : int
        Cold fits run beside warm refits (``mapping.cold_check``) and how many had the higher
        ELBO.
    """

    def __init__(
        self,
        mapping: MappingSettings = _DEFAULT_MAPPING,
        surface: SurfaceSettings = _DEFAULT_SURFACE,
    ) -> None:
        self.mapping = mapping
        self.surface = surface
        self.fit_ = None
        self.mode_: str | None = None
        self.suspect_ids_ = np.zeros(0, dtype=np.int64)
        self.timings_: dict[str, float] = {}
        self._estimators: dict[str, object] = {}
        self._merger: StreamingMerger | None = None
        self._n_theta = 0  # merged size at the last fit that learnt the kernel hyperparameters
        self.cold_checks_ = 0  # cold fits run beside warm refits (mapping.cold_check)
        self.cold_wins_ = 0  # ... and how many of them won on the ELBO

    # ------------------------------------------------------------------ fit

    def _voxel(self) -> float:
        """Length scale that sets the merge radii: the learnt one, rounded (see settings), but
        never above twice the resolution floor ``lengthscale_min``. Merging at a learnt scale
        feeds back: a degenerate fit (l -> 1-2 m on the Gaussian plateau) merged a gusty
        89-observation session into 21 cells, which only a degenerate fit could explain."""
        ms = self.mapping
        ell = self.fit_.lengthscale_ if self.fit_ is not None else ms.lengthscale
        return _quantised(min(ell, 2.0 * max(ms.lengthscale_min, ms.lengthscale)))

    def _voxels(self) -> tuple[float, float]:
        ms = self.mapping
        ell = self._voxel()
        inner = max(ms.merge_voxel_factor * ell, ms.merge_voxel_min)
        return inner, max(ms.external_voxel_factor * ell, inner)

    def _merge(self, X, y, ids, t_ns) -> TrainingSet:
        """Merged view of all raw observations (``merge_rule``; radii frozen with hysteresis)."""
        ms = self.mapping
        inner, outer = self._voxels()
        if ms.merge_rule == "voxel":
            return merge_observations(X, y, ids, t_ns, inner, self.suspect_ids_, outer)
        m = self._merger
        h = ms.merge_hysteresis
        if (
            m is None
            or not (1.0 / h < m.radius_m / inner < h)
            or not (1.0 / h < m.external_radius_m / outer < h)
        ):
            m = self._merger = StreamingMerger(inner, outer)
        return m.update(X, y, ids, t_ns, self.suspect_ids_)

    def _weights(self, ts: TrainingSet, rows=slice(None)) -> dict:
        """``sample_weight`` of the robust fit: capped cell counts (``merge_weight_cap``)."""
        cap = self.mapping.merge_weight_cap
        if self.mapping.model == "gpis" or cap <= 1.0:
            return {}
        return {"sample_weight": np.minimum(ts.counts[rows], cap).astype(np.float64)}

    def _potential(self, y: np.ndarray) -> np.ndarray:
        """Labels (-1/0/+1) -> the values the estimator fits (internal: ``inside_value``)."""
        y = np.asarray(y, dtype=np.float64)
        return np.where(y < 0.0, self.mapping.inside_value, y)

    def _bounds(self) -> dict:
        """Initial kernel hyperparameters clipped into the configured bounds, and the bounds."""
        ms = self.mapping
        ell_hi, sf2_lo = 1e2, 1e-3
        return dict(
            lengthscale=min(max(ms.lengthscale, ms.lengthscale_min), ell_hi),
            signal_var=min(max(ms.signal_var, sf2_lo), ms.signal_var_max),
            lengthscale_bounds=(ms.lengthscale_min, ell_hi),
            signal_var_bounds=(sf2_lo, ms.signal_var_max),
        )

    def _make(self, mode: str):
        ms = self.mapping
        if ms.model == "gpis":
            return GPIS(
                **self._bounds(),
                noise_var=ms.noise_var,
                prior_mean=ms.prior_mean,
                optimize=ms.optimize,
                max_iter=ms.max_iter,
                tol=ms.tol,
                chunk_mb=self.surface.chunk_mb,
                warm_start=True,
            )
        common = dict(
            **self._bounds(),
            alpha=ms.alpha,
            beta=ms.beta,
            prior_mean=ms.prior_mean,
            optimize=ms.optimize,
            noise_update=ms.noise_update,
            max_iter=ms.max_iter,
            tol=ms.tol,
            beta_floor=ms.beta_floor,
            chunk_mb=self.surface.chunk_mb,
            warm_start=True,
        )
        if mode == "sparse":
            return SparseRobustGPIS(n_inducing=ms.n_inducing, **common)
        return RobustGPIS(**common)

    def fit(
        self,
        X: np.ndarray,
        y: np.ndarray,
        ids: np.ndarray | None = None,
        t_ns: np.ndarray | None = None,
    ) -> LegacySurfaceModel:
        """Fit to all raw observations so far.

        Parameters
        ----------
        X : (N, 2|3) float64, metres
        y : (N,) float64 labels (-1 internal, 0 contact, +1 external)
        ids : (N,) int64, optional
            Observation ids (default ``0..N-1``); suspects are remembered by id between fits.
        t_ns : (N,) int64, optional
            Observation times, ns (default: row order).

        Returns
        -------
        self
        """
        ms = self.mapping
        X = check_inputs(X, "X")
        n = X.shape[0]
        ids = np.arange(n, dtype=np.int64) if ids is None else np.asarray(ids)
        t_ns = np.arange(n, dtype=np.int64) if t_ns is None else np.asarray(t_ns)
        pilot_s = 0.0
        with blas_threads(ms.blas_threads):
            t0 = time.perf_counter()
            if ms.merge and n > ms.merge_min_raw:
                ts = self._merge(X, y, ids, t_ns)
            else:
                ts = _identity_set(X, np.asarray(y, dtype=np.float64).reshape(-1), ids)
            prev = self.fit_
            if (
                prev is not None
                and ms.model != "gpis"
                and getattr(prev, "alpha_", 0.0) >= ms.gaussian_restart_alpha
                and len(ts) > ms.theta_refit_growth * self._n_theta
            ):
                # The Gaussian limit is absorbing for warm starts (ALGORITHM.md §7.3): with
                # markedly more data, start over (pilot, cold fit) instead of continuing it.
                self.fit_, self._estimators, self._n_theta = None, {}, 0
            if (
                self.fit_ is None
                and ms.merge
                and n > ms.merge_min_raw
                and ms.model != "gpis"
                and len(ts) > ms.pilot_size
            ):
                # Cold start on a large set: learn l on a voxel subsample (exact, cheap), then
                # merge at the learnt scale; the fit below warm-starts from this pilot.
                tp = time.perf_counter()
                sub = choose_inducing(ts.X, ts.y, ms.lengthscale, ms.pilot_size)
                pilot = self._make("exact")
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", ConvergenceWarning)
                    pilot.fit(ts.X[sub], self._potential(ts.y[sub]), **self._weights(ts, sub))
                self.fit_ = pilot
                pilot_s = time.perf_counter() - tp
                ts = self._merge(X, y, ids, t_ns)
            t1 = time.perf_counter()
            mode = "exact" if (ms.model == "gpis" or len(ts) <= ms.exact_budget) else "sparse"
            est = self._estimators.get(mode)
            if est is None:
                est = self._make(mode)
                prev = self.fit_
                if prev is not None and prev is not est and ms.model != "gpis":
                    for name in _HANDOVER:  # warm start across the exact -> sparse switch
                        if hasattr(prev, name):
                            setattr(est, name, getattr(prev, name))
                self._estimators[mode] = est
            warm = getattr(est, "posterior_", None) is not None
            if ms.model != "gpis":
                est.tol = ms.refit_tol if warm else ms.tol
                est.max_iter = ms.refit_max_iter if warm else ms.max_iter
                est.u_tol = ms.refit_u_tol if warm else None
                # Warm refits keep theta unless the merged set grew markedly (a covered
                # structure stops growing, so its refits only update q(tau) and q(f)).
                learn = ms.optimize and (
                    not warm or len(ts) > ms.theta_refit_growth * self._n_theta
                )
                est.optimize = learn
                if learn:
                    self._n_theta = len(ts)
            with warnings.catch_warnings():
                # A refit cut at refit_max_iter is expected; converged_ reports it.
                if warm:
                    warnings.simplefilter("ignore", ConvergenceWarning)
                est.fit(ts.X, self._potential(ts.y), **self._weights(ts))
            if warm and mode == "exact" and ms.model != "gpis" and ms.cold_check and est.optimize:
                est = self._cold_check(est, mode, ts)
            t2 = time.perf_counter()
        self.fit_, self.mode_, self.training_set_ = est, mode, ts
        self.n_train_, self.n_raw_ = len(ts), n
        self.converged_ = bool(est.converged_)
        if ms.model != "gpis":
            # Only contacts can be false positives (ALGORITHM.md §7.5).
            u, contact = np.asarray(est.uncertainty_), ts.y == 0.0
            u_ref = ms.suspect_ratio * float(np.median(u[contact])) if contact.any() else 0.0
            flagged = np.flatnonzero((u > max(ms.suspect_u, u_ref)) & contact)
            self.suspect_ids_ = (
                np.unique(np.concatenate([ts.ids[ts.members[j]] for j in flagged]))
                if flagged.size
                else np.zeros(0, dtype=np.int64)
            )
        self.timings_ = {"merge_s": t1 - t0 - pilot_s, "fit_s": t2 - t1 + pilot_s}
        return self

    def _cold_check(self, est, mode: str, ts: TrainingSet):
        """A cold fit on the same set; the higher final ELBO wins (both bound the same model's
        evidence). Warm refits keep q(tau) of earlier rows, so a contact once down-weighted
        stays so: on a wall survey the warm stream ended at ELBO 90 where a cold fit on the
        same 341 merged rows reached 161 (and separated gusts from touches)."""
        ms = self.mapping
        cold = self._make(mode)
        cold.tol, cold.max_iter = ms.tol, ms.max_iter
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            cold.fit(ts.X, self._potential(ts.y), **self._weights(ts))
        self.cold_checks_ += 1
        if cold.elbo_trace_[-1] > est.elbo_trace_[-1]:
            self.cold_wins_ += 1
            self._estimators[mode] = cold
            return cold
        return est

    def _check_fitted(self) -> None:
        if self.fit_ is None:
            raise NotFittedError("this LegacySurfaceModel is not fitted yet", hint="call fit first")

    def predict(
        self, Xq: np.ndarray, return_std: bool = False
    ) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
        """Posterior mean (m,) and, if ``return_std``, latent std (m,) at ``Xq`` (m, d) metres."""
        self._check_fitted()
        with blas_threads(self.mapping.blas_threads):
            return self.fit_.predict(Xq, return_std=return_std)

    def uncertainty_by_id(self) -> IdUncertainty:
        """``u`` of every raw observation id (members of a merged cell share the cell's u).

        For ``model = "gpis"`` this is the posterior variance at the training points.
        """
        self._check_fitted()
        ts = self.training_set_
        return IdUncertainty(ids=ts.ids.copy(), u=np.asarray(self.fit_.uncertainty_)[ts.cell_of])

    # ------------------------------------------------------------------ field and mesh

    def mesh_grid(self, region_min=None, region_max=None) -> Grid:
        """The fine grid of :meth:`mesh`: spacing ``max(spacing, l / voxels_per_lengthscale)``
        over the contacts' bounding box (+ ``region_margin``) within the configured region."""
        self._check_fitted()
        ss = self.surface
        X, y = self.fit_.X_train_, self.fit_.y_train_
        if X.shape[1] != 3:
            raise InputDataError("mesh() needs 3D data; use predict on a 2D grid instead")
        lo = np.asarray(ss.region_min if region_min is None else region_min, dtype=np.float64)
        hi = np.asarray(ss.region_max if region_max is None else region_max, dtype=np.float64)
        if lo.size == 0 and hi.size == 0:  # no clip configured
            lo, hi = np.full(3, -np.inf), np.full(3, np.inf)
        if lo.shape != (3,) or hi.shape != (3,):
            raise InputDataError(f"region corners must have 3 coordinates, got {lo}, {hi}")
        contacts = X[y == 0.0]
        lo = np.maximum(lo, contacts.min(axis=0) - ss.region_margin)
        hi = np.minimum(hi, contacts.max(axis=0) + ss.region_margin)
        spacing = max(ss.spacing, self.fit_.lengthscale_ / ss.voxels_per_lengthscale)
        hi = np.maximum(hi, lo + 2.0 * spacing)
        return Grid.from_bounds(lo, hi, spacing)

    def field(self, region_min=None, region_max=None) -> BandField:
        """Narrow-band mean field on :meth:`mesh_grid` (``field.narrow_band_field``)."""
        grid = self.mesh_grid(region_min, region_max)
        with blas_threads(self.mapping.blas_threads):
            return narrow_band_field(
                self.fit_.predict,
                grid,
                coarse_factor=self.surface.coarse_factor,
                band_voxels=self.surface.band_voxels,
            )

    def mesh(self, region_min=None, region_max=None, with_std: bool = True) -> SurfaceMesh:
        """Zero-level mesh: narrow-band field, marching cubes, predictive std at the vertices.

        Parameters
        ----------
        region_min, region_max : (3,) metres, optional
            Override the configured region (still cut to the contacts' box + margin).
        with_std : bool
            Evaluate the predictive std at the mesh vertices (only there).

        Returns
        -------
        SurfaceMesh
        """
        t0 = time.perf_counter()
        band = self.field(region_min, region_max)
        t1 = time.perf_counter()
        mesh = extract_surface(band.values, band.grid)
        frac = self.surface.max_std_fraction
        if (with_std or frac < 1.0) and not mesh.is_empty:
            with blas_threads(self.mapping.blas_threads):
                _, std = self.fit_.predict(mesh.vertices, return_std=True)
            mesh = SurfaceMesh(mesh.vertices, mesh.faces, mesh.normals, std)
            if frac < 1.0:
                mesh = confident_part(mesh, frac * math.sqrt(self.fit_.signal_var_))
        t2 = time.perf_counter()
        self.last_field_ = band
        self.timings_.update(field_s=t1 - t0, mesh_s=t2 - t1)
        return mesh


def _identity_set(X: np.ndarray, y: np.ndarray, ids: np.ndarray) -> TrainingSet:
    n = X.shape[0]
    idx = np.arange(n, dtype=np.int64)
    return TrainingSet(
        X=X,
        y=np.asarray(y, dtype=np.float64),
        counts=np.ones(n, dtype=np.int64),
        rep_ids=ids.astype(np.int64),
        members=[idx[i : i + 1] for i in range(n)],
        cell_of=idx,
        suspect=np.zeros(n, dtype=bool),
        ids=ids.astype(np.int64),
    )
