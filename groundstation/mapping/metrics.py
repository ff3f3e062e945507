"""Accuracy measures of an estimated implicit surface (pure).

* :func:`shape_error` - the paper's e (DESIGN.md §3): mean distance to the true surface of the
  grid points with ``|mu| < band`` (band 0.01). It only looks where the estimate puts a surface,
  so a missing part of the surface costs nothing.
* :func:`chamfer_distance` - symmetric mean nearest-neighbour distance between the extracted
  zero set and the true surface, both sampled uniformly (:func:`sample_polylines`,
  :func:`sample_mesh_surface`). Unlike e it also charges for missing surface.
* :func:`false_positive_clarity` - the paper's Q: for each outlier o, the mean uncertainty u of
  the normal data within 0.5 m of o divided by u_o (smaller is clearer).
* :func:`phantom_length` - length of extracted 2D zero contour farther than a threshold from the
  true boundary: the "phantom surface" that a zero prior mean leaves where data is sparse.
* :func:`phantom_patches` - the 3D counterpart on a mesh: its faces farther than a threshold
  from the true surface, joined into patches, each with its area and where it lies.

The true surface is given either as a callable returning the (signed or unsigned) distance of
(m, d) points, or as dense (k, d) samples of the surface.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
from scipy.spatial import cKDTree

from groundstation.errors import InputDataError

DistanceFn = Callable[[np.ndarray], np.ndarray]
Truth = DistanceFn | np.ndarray


def _points(a: np.ndarray, name: str, d: int | None = None) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] not in (2, 3) or (d is not None and arr.shape[1] != d):
        want = f"(m, {d})" if d is not None else "(m, 2) or (m, 3)"
        raise InputDataError(f"{name} must have shape {want}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputDataError(f"{name} holds {int(np.sum(~np.isfinite(arr)))} non-finite values")
    return arr


def distance_to(truth: Truth, points: np.ndarray) -> np.ndarray:
    """Unsigned distance (metres) of (m, d) ``points`` to the true surface.

    ``truth`` is a distance function (its absolute value is taken, so a signed distance works)
    or a (k, d) array of dense surface samples (nearest-sample distance via a k-d tree; its
    error is at most half the sample spacing).
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[0] == 0:
        return np.zeros(0)
    if callable(truth):
        dist = np.abs(np.asarray(truth(pts), dtype=np.float64).reshape(-1))
        if dist.shape[0] != pts.shape[0]:
            raise InputDataError(
                f"the distance function returned {dist.shape[0]} values for {pts.shape[0]} points"
            )
        return dist
    samples = _points(truth, "true surface samples", pts.shape[1])
    if samples.shape[0] == 0:
        raise InputDataError("the true surface has no samples")
    return cKDTree(samples).query(pts)[0]


def shape_error(mean: np.ndarray, points: np.ndarray, truth: Truth, *, band: float = 0.01) -> float:
    """The paper's shape error e: mean distance to the true surface of points with |mu| < band.

    Parameters
    ----------
    mean : (m,) or grid-shaped float64
        Predictive mean at ``points`` (same number of values, C order).
    points : (m, d) float64, metres
        Grid points.
    truth : distance function or (k, d) surface samples
    band : float
        Half-width of the level band, label units (paper: 0.01).

    Returns
    -------
    float
        e in metres; NaN when no point lies in the band (no estimated surface at all).
    """
    mu = np.asarray(mean, dtype=np.float64).reshape(-1)
    pts = _points(points, "points")
    if mu.shape[0] != pts.shape[0]:
        raise InputDataError(f"mean has {mu.shape[0]} values for {pts.shape[0]} points")
    if not band > 0:
        raise InputDataError(f"band must be > 0, got {band}")
    sel = np.abs(mu) < band
    if not np.any(sel):
        return float("nan")
    return float(np.mean(distance_to(truth, pts[sel])))


def chamfer_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance: ``(mean_a d(a, B) + mean_b d(b, A)) / 2``, metres.

    Parameters
    ----------
    a, b : (m, d), (k, d) float64 point sets (uniform samples of two curves/surfaces)

    Returns
    -------
    float
        NaN if either set is empty.
    """
    pa = np.asarray(a, dtype=np.float64)
    pb = np.asarray(b, dtype=np.float64)
    if pa.size == 0 or pb.size == 0:
        return float("nan")
    pa = _points(pa, "a")
    pb = _points(pb, "b", pa.shape[1])
    d_ab = cKDTree(pb).query(pa)[0]
    d_ba = cKDTree(pa).query(pb)[0]
    return float(0.5 * (d_ab.mean() + d_ba.mean()))


def _segments(polylines: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    starts, ends = [], []
    for line in polylines:
        p = _points(line, "polyline")
        if p.shape[0] >= 2:
            starts.append(p[:-1])
            ends.append(p[1:])
    if not starts:
        return np.zeros((0, 2)), np.zeros((0, 2))
    return np.concatenate(starts), np.concatenate(ends)


def _subdivide(polylines: Sequence[np.ndarray], step: float) -> tuple[np.ndarray, np.ndarray]:
    """Midpoints (m, d) and lengths (m,) of pieces no longer than ``step`` covering the lines."""
    if not step > 0:
        raise InputDataError(f"sampling step must be > 0 metres, got {step}")
    a, b = _segments(polylines)
    if a.shape[0] == 0:
        return np.zeros((0, 2)), np.zeros(0)
    seg_len = np.linalg.norm(b - a, axis=1)
    pieces = np.maximum(1, np.ceil(seg_len / step)).astype(int)
    seg = np.repeat(np.arange(a.shape[0]), pieces)
    within = np.arange(seg.size) - np.repeat(np.cumsum(pieces) - pieces, pieces)
    t = (within + 0.5) / pieces[seg]
    mid = a[seg] + t[:, None] * (b[seg] - a[seg])
    return mid, seg_len[seg] / pieces[seg]


def polyline_length(polylines: Sequence[np.ndarray]) -> float:
    """Total length of a list of (k, d) polylines, metres."""
    a, b = _segments(polylines)
    return float(np.linalg.norm(b - a, axis=1).sum())


def sample_polylines(polylines: Sequence[np.ndarray], spacing: float) -> np.ndarray:
    """Points spread uniformly along polylines, about one per ``spacing`` metres.

    Returns the midpoints of pieces of length <= ``spacing`` covering every segment, so the
    sample density is uniform in arc length to within one piece per segment. (m, d) float64.
    """
    return _subdivide(polylines, spacing)[0]


def sample_mesh_surface(
    vertices: np.ndarray, faces: np.ndarray, n: int, *, seed: int = 0
) -> np.ndarray:
    """Draw ``n`` points uniformly (by area) on a triangle mesh.

    Parameters
    ----------
    vertices : (V, 3) float64, metres
    faces : (F, 3) int vertex indices
    n : int
        Number of samples.
    seed : int
        Seed of the numpy Generator (deterministic).

    Returns
    -------
    (n, 3) float64; (0, 3) when the mesh has no area.
    """
    return sample_mesh_faces(vertices, faces, n, seed=seed)[0]


def sample_mesh_faces(
    vertices: np.ndarray, faces: np.ndarray, n: int, *, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`sample_mesh_surface` with the face each point lies on: ((n, 3) float64 points,
    (n,) int64 face indices). The points on any subset of the faces are an area-uniform
    sample of that subset, at the same density: one draw scores a mesh and every part of it
    (``pipeline.scoring.mask_curve``)."""
    v = _points(vertices, "vertices", 3) if len(vertices) else np.zeros((0, 3))
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if f.size and (f.min() < 0 or f.max() >= v.shape[0]):
        raise InputDataError(f"faces index vertices outside 0..{v.shape[0] - 1}")
    none = (np.zeros((0, 3)), np.zeros(0, dtype=np.int64))
    if f.shape[0] == 0 or n <= 0:
        return none
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    total = area.sum()
    if not total > 0:
        return none
    rng = np.random.default_rng(seed)
    tri = rng.choice(f.shape[0], size=n, p=area / total)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    # Uniform barycentric sampling (Osada et al. 2002): P = (1-s) A + s(1-r2) B + s r2 C.
    pts = (1 - s)[:, None] * a[tri] + (s * (1 - r2))[:, None] * b[tri] + (s * r2)[:, None] * c[tri]
    return pts, tri.astype(np.int64)


@dataclasses.dataclass(frozen=True)
class Clarity:
    """False-positive clarity Q (DESIGN.md §3).

    Attributes
    ----------
    per_outlier : (k,) float64
        Q_o for each outlier, in the order given; NaN for skipped outliers.
    mean : float
        Mean of the non-NaN Q_o (NaN if all were skipped). Smaller is clearer.
    n_skipped : int
        Outliers with no normal datum within the radius (Q_o undefined).
    """

    per_outlier: np.ndarray
    mean: float
    n_skipped: int


def false_positive_clarity(
    X: np.ndarray,
    u: np.ndarray,
    outlier: np.ndarray,
    *,
    normal: np.ndarray | None = None,
    radius: float = 0.5,
) -> Clarity:
    """Q_o = mean(u of normal data within ``radius`` of o) / u_o for each outlier o.

    Parameters
    ----------
    X : (n, d) float64, metres
        Training inputs.
    u : (n,) float64 > 0
        Per-datum uncertainty (``uncertainty_`` of the fitted model).
    outlier : (n,) bool
        Which data are the outliers to score (the false contacts).
    normal : (n,) bool, optional
        Which data count as normal; default ``~outlier``. (Pass False for other known-bad data,
        e.g. the interior points emitted together with false contacts.)
    radius : float
        Neighbourhood radius, metres (paper: 0.5).
    """
    pts = _points(X, "X")
    uu = np.asarray(u, dtype=np.float64).reshape(-1)
    out = np.asarray(outlier, dtype=bool).reshape(-1)
    norm = ~out if normal is None else np.asarray(normal, dtype=bool).reshape(-1)
    n = pts.shape[0]
    if uu.shape[0] != n or out.shape[0] != n or norm.shape[0] != n:
        raise InputDataError(
            f"X has {n} rows but u, outlier, normal have {uu.shape[0]}, {out.shape[0]}, "
            f"{norm.shape[0]}"
        )
    if not np.all(np.isfinite(uu)) or np.any(uu <= 0):
        raise InputDataError("u must be finite and > 0 for every datum")
    idx_out = np.flatnonzero(out)
    idx_norm = np.flatnonzero(norm & ~out)
    q = np.full(idx_out.size, np.nan)
    if idx_out.size and idx_norm.size:
        tree = cKDTree(pts[idx_norm])
        for k, neigh in enumerate(tree.query_ball_point(pts[idx_out], r=radius)):
            if neigh:
                q[k] = uu[idx_norm[neigh]].mean() / uu[idx_out[k]]
    valid = np.isfinite(q)
    return Clarity(
        per_outlier=q,
        mean=float(q[valid].mean()) if np.any(valid) else float("nan"),
        n_skipped=int(np.sum(~valid)),
    )


def phantom_length(
    polylines: Sequence[np.ndarray], truth: Truth, *, threshold: float = 0.1, step: float = 0.005
) -> float:
    """Length (metres) of 2D contour farther than ``threshold`` from the true boundary.

    Each segment is cut into pieces of at most ``step`` metres; a piece counts when its midpoint
    is farther than ``threshold`` (metres) from the true boundary.
    """
    if not threshold >= 0:
        raise InputDataError(f"threshold must be >= 0 metres, got {threshold}")
    mid, length = _subdivide(polylines, step)
    if mid.shape[0] == 0:
        return 0.0
    return float(length[distance_to(truth, mid) > threshold].sum())


@dataclasses.dataclass(frozen=True)
class PhantomPatch:
    """One connected piece of invented surface (metres, m^2)."""

    area_m2: float
    centre: tuple[float, ...]  # area-weighted mean of its face centroids
    lo: tuple[float, ...]  # bounding box of its face centroids
    hi: tuple[float, ...]
    farthest_m: float  # largest distance of a face centroid to the true surface

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def phantom_patches(
    vertices: np.ndarray,
    faces: np.ndarray,
    truth: Truth,
    *,
    threshold: float = 0.15,
    join_m: float = 1e-3,
) -> tuple[PhantomPatch, ...]:
    """Patches of mesh faces whose centroid lies farther than ``threshold`` from the true
    surface, largest first. Faces sharing a vertex belong to one patch, and so do faces whose
    vertices lie within ``join_m`` metres of each other: a mesh assembled from pieces (tiles)
    whose seams repeat a vertex is one surface, not one patch per piece (unjoined, the tiled
    map's largest patches read up to 2.5x too small)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    if not threshold >= 0:
        raise InputDataError(f"threshold must be >= 0 metres, got {threshold}")
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if f.shape[0] == 0:
        return ()
    cent = v[f].mean(axis=1)
    dist = distance_to(truth, cent)
    far = dist > threshold
    if not far.any():
        return ()
    ff, c, dd = f[far], cent[far], dist[far]
    area = 0.5 * np.linalg.norm(
        np.cross(v[ff[:, 1]] - v[ff[:, 0]], v[ff[:, 2]] - v[ff[:, 0]]), axis=1
    )
    k = ff.shape[0]
    rows = np.repeat(np.arange(k), 3)  # faces and vertices in one graph: face -- its vertices
    cols = k + ff.reshape(-1)
    used = np.unique(ff)
    if join_m > 0 and used.size > 1:  # ... and vertex -- vertex where they (nearly) coincide
        from scipy.spatial import cKDTree

        pairs = cKDTree(v[used]).query_pairs(join_m, output_type="ndarray")
        rows = np.concatenate([rows, k + used[pairs[:, 0]]])
        cols = np.concatenate([cols, k + used[pairs[:, 1]]])
    g = coo_matrix((np.ones(rows.size), (rows, cols)), shape=(k + len(v),) * 2)
    _, labels = connected_components(g, directed=False)
    order = np.argsort(labels[:k], kind="stable")  # faces grouped by patch, one pass each
    lab = labels[:k][order]
    starts = np.flatnonzero(np.r_[True, lab[1:] != lab[:-1]])
    a, c, dd = area[order], c[order], dd[order]
    total = np.add.reduceat(a, starts)
    count = np.add.reduceat(np.ones_like(a), starts)
    weighted = np.add.reduceat(a[:, None] * c, starts, axis=0)
    plain = np.add.reduceat(c, starts, axis=0) / count[:, None]  # a patch of zero area
    centre = np.where(total[:, None] > 0, weighted / np.maximum(total, 1e-300)[:, None], plain)
    lo, hi = np.minimum.reduceat(c, starts, axis=0), np.maximum.reduceat(c, starts, axis=0)
    farthest = np.maximum.reduceat(dd, starts)
    out = [
        PhantomPatch(
            area_m2=float(total[j]),
            centre=tuple(float(x) for x in centre[j]),
            lo=tuple(float(x) for x in lo[j]),
            hi=tuple(float(x) for x in hi[j]),
            farthest_m=float(farthest[j]),
        )
        for j in range(starts.size)
    ]
    return tuple(sorted(out, key=lambda p: -p.area_m2))
