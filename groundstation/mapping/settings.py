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

    def __post_init__(self) -> None:
        for name in ("lengthscale", "signal_var", "alpha", "beta", "noise_var", "tol"):
            value = getattr(self, name)
            if not value > 0:
                raise ValueError(f"mapping.{name} must be > 0, got {value!r}")
        if self.max_iter < 1:
            raise ValueError(f"mapping.max_iter must be >= 1, got {self.max_iter!r}")


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
    """

    region_min: tuple[float, ...] = (0.0, 0.0, 0.0)
    region_max: tuple[float, ...] = (8.0, 4.0, 2.0)
    spacing: float = 0.05
    chunk_mb: float = 64.0

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
