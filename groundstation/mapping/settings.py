"""Settings of the mapping engine (frozen; defaults are the paper's unless a measurement says
otherwise, in which case the paper's value is named beside the default)."""

from __future__ import annotations

import dataclasses
from typing import Literal


@dataclasses.dataclass(frozen=True)
class MappingSettings:
    """How the implicit surface is estimated.

    Attributes
    ----------
    model : "robust" | "gpis"
        Student-t robust GPIS (the paper's method) or homoscedastic GPIS.
    lengthscale : float
        Initial squared-exponential length scale, metres. The paper's "initial kernel
        variance 0.25^2" read as a length scale (ALGORITHM.md §1).
    signal_var : float
        Initial kernel signal variance sigma_f^2 (label units^2).
    alpha, beta : float
        Initial InvGamma(alpha, beta) prior on the per-datum noise variances (paper: 2, 4).
    noise_var : float
        Initial noise variance of the homoscedastic GPIS.
    prior_mean : float
        Constant GP prior mean mu0 (paper: 0).
    optimize : bool
        Learn the kernel hyperparameters (M-step) or keep them at their initial values.
    noise_update : "direct" | "em"
        (alpha, beta) update: the direct maximiser (ALGORITHM.md §4.1, default) or the
        literal EM fixed point (Kuss M1/M2), which stalls from beta = 4 (§7.1).
    max_iter : int
        EM iteration limit.
    tol : float
        Relative ELBO change below which the EM counts as converged (3 iterations in a row).
    beta_floor : float
        Lower bound on beta (ALGORITHM.md §7.4).
    merge : bool
        Merge redundant observations per voxel before fitting (``mapping.merge``).
    merge_voxel_factor : float
        Voxel edge for contacts and internal points, in length scales (the learnt one, rounded
        to a power of sqrt(2) so the merged set is stable between refits).
    external_voxel_factor : float
        Voxel edge for external (free-space) points, in length scales (coarser: they are
        redundant).
    suspect_u : float
        A merged cell whose ``u_i`` exceeds this (label units^2) is a suspected false contact:
        its observations are never merged with trusted ones at the next refit.
    exact_budget : int
        Largest merged training set fitted by the exact model; above it the sparse model runs.
    n_inducing : int
        Maximum number of inducing points of the sparse model.
    pilot_size : int
        Cold start on a merged set larger than this: the length scale is first learnt by an
        exact fit on a voxel subsample of at most this many points, the data are merged at that
        scale, and the fit warm-starts from the pilot (a cold exact fit on 1,292 merged points
        took 111 EM iterations and landed in a worse basin, ALGORITHM.md §7.6).
    refit_max_iter : int
        EM iteration limit of warm-started refits. The ELBO never decreases, so a refit cut
        short is a valid partial update that the next refit continues; it keeps the refit time
        bounded as the session grows (``converged_`` then reads False).
    merge_voxel_min : float
        Floor of the merge voxel edge, metres.
    refit_tol : float
        Relative ELBO tolerance of warm-started refits (cold fits use ``tol``).
    blas_threads : int
        BLAS threads while fitting/evaluating (0: leave the process setting alone). One thread
        was steadier and faster than two on the loaded 2-core machines (STACK.md).
    """

    model: Literal["robust", "gpis"] = "robust"
    lengthscale: float = 0.25
    signal_var: float = 1.0
    alpha: float = 2.0
    beta: float = 4.0
    noise_var: float = 0.01
    prior_mean: float = 0.0
    optimize: bool = True
    noise_update: Literal["direct", "em"] = "direct"
    max_iter: int = 200
    tol: float = 1e-6
    beta_floor: float = 1e-6
    merge: bool = True
    merge_voxel_factor: float = 0.125
    external_voxel_factor: float = 1.0
    suspect_u: float = 0.05
    exact_budget: int = 1500
    n_inducing: int = 600
    pilot_size: int = 600
    refit_tol: float = 1e-5
    refit_max_iter: int = 15
    merge_voxel_min: float = 0.1
    blas_threads: int = 1

    def __post_init__(self) -> None:
        for name in (
            "lengthscale",
            "signal_var",
            "alpha",
            "beta",
            "noise_var",
            "tol",
            "merge_voxel_factor",
            "external_voxel_factor",
            "suspect_u",
            "refit_tol",
            "merge_voxel_min",
        ):
            value = getattr(self, name)
            if not value > 0:
                raise ValueError(f"mapping.{name} must be > 0, got {value!r}")
        if self.max_iter < 1:
            raise ValueError(f"mapping.max_iter must be >= 1, got {self.max_iter!r}")
        for name, low in (
            ("exact_budget", 2),
            ("n_inducing", 2),
            ("pilot_size", 2),
            ("refit_max_iter", 1),
            ("blas_threads", 0),
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"mapping.{name} must be an integer >= {low}, got {value!r}")


@dataclasses.dataclass(frozen=True)
class SurfaceSettings:
    """Where and how finely the field is evaluated and meshed.

    Attributes
    ----------
    region_min, region_max : tuple of float
        Corners of the exploration region, metres (paper: 8 x 4 x 2 m).
    spacing : float
        Grid spacing, metres (paper: 0.05 m in 3D, 0.02 m in 2D).
    chunk_mb : float
        Memory budget of one prediction chunk, MB.
    voxels_per_lengthscale : float
        The mesh grid spacing is ``max(spacing, l / voxels_per_lengthscale)`` with the learnt
        length scale l: the field has no detail below l, so ``spacing`` is only a floor.
    coarse_factor : int
        Stride (in fine voxels) of the first coarse pass of the narrow-band evaluation; 1
        evaluates the whole grid.
    band_voxels : float
        Half-width, in fine voxels, of the band around the zero set evaluated exactly.
    region_margin : float
        Metres added around the contacts' bounding box; the meshed region is that box
        intersected with ``[region_min, region_max]``.
    """

    region_min: tuple[float, ...] = (0.0, 0.0, 0.0)
    region_max: tuple[float, ...] = (8.0, 4.0, 2.0)
    spacing: float = 0.05
    chunk_mb: float = 64.0
    voxels_per_lengthscale: float = 5.0
    coarse_factor: int = 4
    band_voxels: float = 2.0
    region_margin: float = 0.5

    def __post_init__(self) -> None:
        if len(self.region_min) != len(self.region_max) or len(self.region_min) not in (2, 3):
            raise ValueError(
                f"surface.region_min/region_max must both have 2 or 3 coordinates, got "
                f"{self.region_min!r} and {self.region_max!r}"
            )
        if any(hi <= lo for lo, hi in zip(self.region_min, self.region_max, strict=True)):
            raise ValueError(
                f"surface.region_max {self.region_max!r} must exceed region_min {self.region_min!r}"
            )
        if not self.spacing > 0:
            raise ValueError(f"surface.spacing must be > 0, got {self.spacing!r}")
        if not self.chunk_mb > 0:
            raise ValueError(f"surface.chunk_mb must be > 0, got {self.chunk_mb!r}")
        if not self.voxels_per_lengthscale > 0:
            raise ValueError(
                f"surface.voxels_per_lengthscale must be > 0, got {self.voxels_per_lengthscale!r}"
            )
        cf = self.coarse_factor
        if isinstance(cf, bool) or not isinstance(cf, int) or cf < 1 or cf & (cf - 1):
            raise ValueError(f"surface.coarse_factor must be a power of two >= 1, got {cf!r}")
        if not self.band_voxels >= 0:
            raise ValueError(f"surface.band_voxels must be >= 0, got {self.band_voxels!r}")
        if not self.region_margin >= 0:
            raise ValueError(f"surface.region_margin must be >= 0 m, got {self.region_margin!r}")
