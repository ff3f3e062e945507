"""Narrow-band, coarse-to-fine evaluation of a field around its zero level set (pure numerics).

DESIGN.md §3 "evaluate the field only where the surface can be": a dense GP mean over the
paper's 8 x 4 x 2 m grid at 0.05 m (5.4e5 points) costs seconds, while the points within two
voxels of the surface are only 8-17 % of it. :func:`narrow_band_field` evaluates the mean on a
lattice ``coarse_factor`` times coarser than ``grid``, then halves the stride level by level,
refining only the cells that can contain the zero set:

* a cell is refined when its corners change sign, or when the smallest ``|mean|`` at a corner is
  below ``safety * G * (half cell diagonal + band_voxels * spacing)``, where ``G`` is the largest
  finite-difference slope of the field on the cell's edges and its neighbours' edges (a local
  Lipschitz estimate), i.e. when the zero set (widened by a band of ``band_voxels`` fine voxels)
  could pass through it;
* values of nodes that are not evaluated are the multilinear interpolation of the coarser level.
  Inside an unrefined cell all corners share one sign, so the fill keeps that sign and marching
  cubes finds no spurious surface there.

The result is a dense array on ``grid`` that ``surface.extract_surface`` can mesh directly.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable

import numpy as np
from scipy import ndimage

from groundstation.mapping.grid import Grid, GridError


@dataclasses.dataclass(frozen=True)
class BandField:
    """A field evaluated in a narrow band around its zero set.

    Attributes
    ----------
    grid : Grid
    values : float64 array of shape ``grid.shape``
        Exact mean where ``evaluated``, sign-preserving multilinear fill elsewhere.
    evaluated : bool array of shape ``grid.shape``
        Nodes where ``predict_mean`` was called.
    n_evaluated : int
        Number of ``predict_mean`` evaluations, including coarse nodes outside ``grid``.
    coarse_factor : int
    """

    grid: Grid
    values: np.ndarray
    evaluated: np.ndarray
    n_evaluated: int
    coarse_factor: int

    @property
    def fraction_evaluated(self) -> float:
        """Evaluations per grid point (the dense grid costs 1)."""
        return self.n_evaluated / self.grid.size


def _upsample(V: np.ndarray) -> np.ndarray:
    """Multilinear upsampling by 2 on a node lattice: shape s -> 2 s - 1."""
    out = V
    for ax in range(V.ndim):
        shape = list(out.shape)
        shape[ax] = 2 * shape[ax] - 1
        new = np.empty(shape)
        sl_even = [slice(None)] * V.ndim
        sl_odd = [slice(None)] * V.ndim
        sl_even[ax] = slice(0, None, 2)
        sl_odd[ax] = slice(1, None, 2)
        new[tuple(sl_even)] = out
        lo = [slice(None)] * V.ndim
        hi = [slice(None)] * V.ndim
        lo[ax] = slice(0, -1)
        hi[ax] = slice(1, None)
        new[tuple(sl_odd)] = 0.5 * (out[tuple(lo)] + out[tuple(hi)])
        out = new
    return out


def _corner_views(V: np.ndarray) -> list[np.ndarray]:
    """The 2^d corner arrays of the cells of a node lattice (each of shape ``V.shape - 1``)."""
    views = []
    for off in itertools.product((0, 1), repeat=V.ndim):
        views.append(V[tuple(slice(o, o + s - 1) for o, s in zip(off, V.shape, strict=True))])
    return views


def _cells_to_nodes(cells: np.ndarray) -> np.ndarray:
    """Nodes in the closure of the marked cells: cell shape c -> node shape c + 1."""
    nodes = np.zeros(tuple(s + 1 for s in cells.shape), dtype=bool)
    for off in itertools.product((0, 1), repeat=cells.ndim):
        nodes[tuple(slice(o, o + s) for o, s in zip(off, cells.shape, strict=True))] |= cells
    return nodes


def _node_slope(V: np.ndarray, step_m: float) -> np.ndarray:
    """Largest |finite-difference slope| (label units per metre) on the edges at each node."""
    S = np.zeros(V.shape)
    for ax in range(V.ndim):
        g = np.abs(np.diff(V, axis=ax)) / step_m
        lo = [slice(None)] * V.ndim
        hi = [slice(None)] * V.ndim
        lo[ax] = slice(0, -1)
        hi[ax] = slice(1, None)
        np.maximum(S[tuple(lo)], g, out=S[tuple(lo)])
        np.maximum(S[tuple(hi)], g, out=S[tuple(hi)])
    return S


def _may_contain_zero(V: np.ndarray, step_m: float, margin_m: float, safety: float) -> np.ndarray:
    """Cells (shape ``V.shape - 1``) through which the widened zero set may pass."""
    corners = _corner_views(V)
    cmin = np.minimum.reduce(corners)
    cmax = np.maximum.reduce(corners)
    amin = np.minimum.reduce([np.abs(c) for c in corners])
    slope = np.maximum.reduce(_corner_views(_node_slope(V, step_m)))
    slope = ndimage.maximum_filter(slope, size=3, mode="nearest")  # neighbours' edges too
    reach = 0.5 * step_m * math.sqrt(V.ndim) + margin_m
    return ((cmin <= 0.0) & (cmax >= 0.0)) | (amin <= safety * slope * reach)


def narrow_band_field(
    predict_mean: Callable[[np.ndarray], np.ndarray],
    grid: Grid,
    coarse_factor: int = 4,
    band_voxels: float = 2.0,
    *,
    safety: float = 2.0,
    chunk_rows: int = 32768,
    active: Callable[[np.ndarray], np.ndarray] | None = None,
    fill: float = 1.0,
) -> BandField:
    """Evaluate ``predict_mean`` coarse-to-fine, only where the zero set can be.

    Parameters
    ----------
    predict_mean : callable
        ``predict_mean(Xq (m, d) float64 metres) -> (m,) float64`` (e.g. a fitted model's
        ``predict``). It is also called at coarse nodes up to ``coarse_factor - 1`` voxels
        beyond ``grid``'s max corner.
    grid : Grid
        The fine grid.
    coarse_factor : int
        Stride of the first pass, in fine voxels: 1 (dense), 2, 4, 8, ...
    band_voxels : float
        Half-width, in fine voxels, of the band around the zero set that is evaluated exactly.
    safety : float
        Factor on the local slope estimate (larger refines more; >= 1).
    chunk_rows : int
        Points per ``predict_mean`` call.
    active : callable, optional
        ``active(points (m, d)) -> (m,) bool``: where the surface can be. Other nodes are not
        evaluated and get ``fill`` (so no band forms there); the caller drops the faces they
        make.
    fill : float
        Value of inactive nodes.

    Returns
    -------
    BandField
    """
    cf = int(coarse_factor)
    if cf < 1 or cf & (cf - 1):
        raise GridError(f"coarse_factor must be a power of two >= 1, got {coarse_factor!r}")
    if not (band_voxels >= 0 and safety >= 1 and chunk_rows >= 1):
        raise GridError(
            f"need band_voxels >= 0, safety >= 1, chunk_rows >= 1; got {band_voxels}, "
            f"{safety}, {chunk_rows}"
        )
    sp = grid.spacing
    n_eval = 0

    def evaluate(idx_fine: np.ndarray) -> np.ndarray:
        nonlocal n_eval
        pts_all = grid.index_to_world(idx_fine)
        out = np.full(pts_all.shape[0], float(fill))
        on = np.ones(pts_all.shape[0], dtype=bool) if active is None else active(pts_all)
        pts = pts_all[on]
        vals_all = np.empty(pts.shape[0])
        for start in range(0, pts.shape[0], chunk_rows):
            stop = min(start + chunk_rows, pts.shape[0])
            vals = np.asarray(predict_mean(pts[start:stop]), dtype=np.float64).reshape(-1)
            if vals.shape[0] != stop - start or not np.all(np.isfinite(vals)):
                raise GridError("predict_mean returned a wrong number of values or NaN/inf")
            vals_all[start:stop] = vals
        out[on] = vals_all
        n_eval += pts.shape[0]
        return out

    # Pad so that the coarse lattice covers the grid: P = ceil((s - 1)/cf) * cf + 1 nodes.
    coarse_shape = tuple(-(-(s - 1) // cf) + 1 for s in grid.shape)
    idx = np.stack(np.meshgrid(*[np.arange(c) for c in coarse_shape], indexing="ij"), -1)
    V = evaluate(idx.reshape(-1, grid.ndim) * float(cf)).reshape(coarse_shape)
    exact = np.ones(coarse_shape, dtype=bool)
    margin = band_voxels * sp
    candidates = np.ones(tuple(s - 1 for s in coarse_shape), dtype=bool)
    h = cf
    while h > 1:
        refine = candidates & _may_contain_zero(V, h * sp, margin, safety)
        h //= 2
        V = _upsample(V)
        was_exact = np.zeros(V.shape, dtype=bool)
        was_exact[tuple(slice(0, None, 2) for _ in range(grid.ndim))] = exact
        # Child cells of refined cells; their nodes are evaluated exactly.
        candidates = refine
        for ax in range(grid.ndim):
            candidates = np.repeat(candidates, 2, axis=ax)
        need = _cells_to_nodes(candidates) & ~was_exact
        where = np.argwhere(need)
        if where.size:
            V[need] = evaluate(where * float(h))
        exact = was_exact | need
    crop = tuple(slice(0, s) for s in grid.shape)
    return BandField(
        grid=grid,
        values=np.ascontiguousarray(V[crop]),
        evaluated=np.ascontiguousarray(exact[crop]),
        n_evaluated=n_eval,
        coarse_factor=cf,
    )
