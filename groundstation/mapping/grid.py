"""Regular evaluation grids and chunked evaluation of a predictive field over them (pure).

A :class:`Grid` is an axis-aligned lattice ``origin + index * spacing`` in 2D or 3D. Points are
enumerated in C order of ``Grid.shape`` with ``indexing="ij"``: axis 0 is x, axis 1 is y, axis 2
is z, so ``values.reshape(grid.shape)[i, j, k]`` is the value at ``grid.point(i, j, k)``.

:func:`evaluate_field` calls any ``predict(Xq, return_std)`` callable (the estimators'
scikit-learn style method) on consecutive blocks of grid points, so that the memory of one call
is bounded by a budget in MB whatever the grid size (DESIGN.md §3 "evaluate the field only where
the surface can be"; ALGORITHM.md §6 "work in chunks of about 64 MB").
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from groundstation.errors import InputDataError
from groundstation.mapping.settings import SurfaceSettings

#: float64 values held per (query point, training point) pair by an exact GP prediction:
#: the cross-kernel row, its scaled copy, and the triangular-solve workspace for the variance.
_VALUES_PER_PAIR = 3


class GridError(InputDataError):
    """A grid definition or a field evaluated on a grid is malformed."""


@dataclasses.dataclass(frozen=True)
class Grid:
    """An axis-aligned regular lattice.

    Attributes
    ----------
    origin : (d,) float64 array, metres
        Coordinates of the point with index ``(0, ..., 0)`` (the region's min corner).
    spacing : float
        Distance between neighbouring points along every axis, metres.
    shape : tuple of int, length d
        Number of points along each axis (d = 2 or 3).
    """

    origin: np.ndarray
    spacing: float
    shape: tuple[int, ...]

    def __post_init__(self) -> None:
        origin = np.asarray(self.origin, dtype=np.float64).reshape(-1)
        object.__setattr__(self, "origin", origin)
        object.__setattr__(self, "shape", tuple(int(s) for s in self.shape))
        if origin.size not in (2, 3) or len(self.shape) != origin.size:
            raise GridError(
                f"grid origin {origin.tolist()} and shape {self.shape} must both have 2 or 3 axes"
            )
        if not np.all(np.isfinite(origin)):
            raise GridError(f"grid origin {origin.tolist()} is not finite")
        if not (math.isfinite(self.spacing) and self.spacing > 0):
            raise GridError(f"grid spacing must be a positive number of metres, got {self.spacing}")
        if any(s < 2 for s in self.shape):
            raise GridError(
                f"grid shape {self.shape} needs at least 2 points per axis",
                hint="make the region larger than the spacing",
            )

    @classmethod
    def from_bounds(
        cls, region_min: Sequence[float], region_max: Sequence[float], spacing: float
    ) -> Grid:
        """Grid covering ``[region_min, region_max]`` (metres) at ``spacing`` (metres).

        The number of points per axis is ``floor((max - min) / spacing) + 1`` (with a 1e-9
        relative allowance so that an exact multiple includes the max corner).
        """
        lo = np.asarray(region_min, dtype=np.float64).reshape(-1)
        hi = np.asarray(region_max, dtype=np.float64).reshape(-1)
        if lo.shape != hi.shape or lo.size not in (2, 3):
            raise GridError(f"region corners {lo.tolist()} / {hi.tolist()} need 2 or 3 coordinates")
        if not np.all(hi > lo):
            raise GridError(f"region_max {hi.tolist()} must exceed region_min {lo.tolist()}")
        if not (math.isfinite(spacing) and spacing > 0):
            raise GridError(f"grid spacing must be a positive number of metres, got {spacing}")
        counts = np.floor((hi - lo) / spacing * (1 + 1e-9)).astype(int) + 1
        return cls(origin=lo, spacing=float(spacing), shape=tuple(int(c) for c in counts))

    @classmethod
    def from_settings(cls, settings: SurfaceSettings) -> Grid:
        """Grid of a :class:`~groundstation.mapping.settings.SurfaceSettings` region."""
        return cls.from_bounds(settings.region_min, settings.region_max, settings.spacing)

    @property
    def ndim(self) -> int:
        """Number of axes (2 or 3)."""
        return len(self.shape)

    @property
    def size(self) -> int:
        """Total number of points."""
        return math.prod(self.shape)

    @property
    def region_max(self) -> np.ndarray:
        """(d,) coordinates of the last point, metres."""
        return self.origin + self.spacing * (np.asarray(self.shape) - 1)

    def axes(self) -> list[np.ndarray]:
        """Coordinates along each axis, metres: a list of d arrays of lengths ``shape``."""
        return [
            o + self.spacing * np.arange(n) for o, n in zip(self.origin, self.shape, strict=True)
        ]

    def points(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Points with flat (C order) indices ``start..stop-1``: (m, d) float64, metres."""
        stop = self.size if stop is None else min(stop, self.size)
        flat = np.arange(start, stop)
        idx = np.unravel_index(flat, self.shape)
        return self.origin + self.spacing * np.stack(idx, axis=1).astype(np.float64)

    def index_to_world(self, index: np.ndarray) -> np.ndarray:
        """Convert (m, d) fractional grid indices to (m, d) world coordinates, metres."""
        return self.origin + self.spacing * np.asarray(index, dtype=np.float64)


@dataclasses.dataclass(frozen=True)
class Field:
    """A predictive field sampled on a grid.

    Attributes
    ----------
    grid : Grid
    mean : float64 array of shape ``grid.shape``
        Predictive mean of the shape potential (label units; < 0 inside, > 0 outside).
    std : float64 array of shape ``grid.shape``, or None
        Predictive standard deviation (label units), when requested.
    """

    grid: Grid
    mean: np.ndarray
    std: np.ndarray | None = None


def rows_per_chunk(chunk_mb: float, n_train: int, ndim: int) -> int:
    """Query points per prediction call so one call holds at most ``chunk_mb`` MB.

    An exact GP prediction at m points with n training points holds about
    ``3 * m * n`` float64 values (ALGORITHM.md §6), plus the m x d queries and two outputs.
    """
    if not chunk_mb > 0:
        raise GridError(f"chunk_mb must be > 0, got {chunk_mb}")
    bytes_per_row = 8 * (ndim + 2 + _VALUES_PER_PAIR * max(int(n_train), 1))
    return max(1, int(chunk_mb * 2**20 // bytes_per_row))


def evaluate_field(
    predict: Callable[..., Any],
    grid: Grid,
    *,
    return_std: bool = False,
    chunk_mb: float = 64.0,
    n_train: int = 1000,
) -> Field:
    """Evaluate ``predict`` over every grid point, one bounded block at a time.

    Parameters
    ----------
    predict : callable
        ``predict(Xq (m, d) float64, return_std=bool)`` returning the mean (m,) or
        ``(mean (m,), std (m,))``, e.g. ``GPIS.predict`` / ``RobustGPIS.predict``.
    grid : Grid
    return_std : bool
        Also evaluate the predictive standard deviation.
    chunk_mb : float
        Memory budget of one ``predict`` call, MB (see :func:`rows_per_chunk`).
    n_train : int
        Number of training points of the model behind ``predict`` (sets the chunk size).

    Returns
    -------
    Field
        Mean (and std) reshaped to ``grid.shape``.

    Raises
    ------
    GridError
        If ``predict`` returns the wrong shape or non-finite values.
    """
    rows = rows_per_chunk(chunk_mb, n_train, grid.ndim)
    mean = np.empty(grid.size, dtype=np.float64)
    std = np.empty(grid.size, dtype=np.float64) if return_std else None
    for start in range(0, grid.size, rows):
        stop = min(start + rows, grid.size)
        out = predict(grid.points(start, stop), return_std=return_std)
        if return_std:
            mu, sd = out
            std[start:stop] = _check_block(sd, stop - start, "std")
        else:
            mu = out
        mean[start:stop] = _check_block(mu, stop - start, "mean")
    return Field(
        grid=grid,
        mean=mean.reshape(grid.shape),
        std=None if std is None else std.reshape(grid.shape),
    )


def _check_block(values: Any, m: int, what: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64).reshape(-1)
    if arr.size != m:
        raise GridError(f"predict returned {arr.size} {what} values for {m} query points")
    if not np.all(np.isfinite(arr)):
        raise GridError(
            f"predict returned {int(np.sum(~np.isfinite(arr)))} non-finite {what} values",
            hint="check the fitted model (NaN hyperparameters?)",
        )
    return arr
