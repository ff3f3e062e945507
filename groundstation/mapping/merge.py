"""Observation budget: merge redundant observations per voxel (DESIGN.md §3, pure).

While the drone slides along a wall, 25 Hz contacts pile up near-duplicates; an exact GP costs
O(n^3) in them. Merging per voxel (edge tied to the kernel length scale) makes the training set
grow with the structure's surface area instead of with flight time.

Rule (:func:`merge_observations`):

* observations are grouped per label (contacts y = 0, internal y = -1, external y = +1 are never
  mixed) and per voxel ``floor(x / voxel)``; external points (y > 0) use the coarser
  ``external_voxel_m``;
* a suspected false contact (an id in ``suspects``) is never merged with a trusted observation,
  in either direction: suspects form their own cells, merged only with other suspects of the
  same label and voxel (so their number stays bounded too);
* a cell's representative position is the mean of its members, its label the members' label,
  ``counts`` its size and ``rep_ids`` the id of its most recent member (largest ``t_ns``);
* cells are ordered by the time of their first member, so a growing session appends new cells
  after the old ones.

:class:`ObservationStore` keeps every raw observation (by id) and serves the merged view.

The mapper's default is the radius rule (:class:`StreamingMerger`, :func:`radius_merge`, at the
end of this module): no cell doubling on voxel boundaries, incremental between refits.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable

import numpy as np

from groundstation.errors import InputDataError


@dataclasses.dataclass(frozen=True)
class TrainingSet:
    """Merged training set.

    Attributes
    ----------
    X : (m, d) float64, metres, mean position of each cell's members
    y : (m,) float64, label of the cell
    counts : (m,) int64, number of raw observations in the cell
    rep_ids : (m,) int64, id of the cell's most recent member
    members : list of m int64 arrays, row indices (into the merged input) of each cell's members
    cell_of : (n,) int64, cell index of every input row
    suspect : (m,) bool, the cell holds suspected false contacts
    ids : (n,) int64, ids of the input rows (``ids[cell_of == j]`` are cell j's ids)
    """

    X: np.ndarray
    y: np.ndarray
    counts: np.ndarray
    rep_ids: np.ndarray
    members: list[np.ndarray]
    cell_of: np.ndarray
    suspect: np.ndarray
    ids: np.ndarray

    def __len__(self) -> int:
        return int(self.y.shape[0])


def _check(X, y, ids, t_ns) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    X = np.asarray(X, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] not in (2, 3):
        raise InputDataError(f"X must have shape (n, 2) or (n, 3), metres; got {X.shape}")
    n = X.shape[0]
    y = np.asarray(y, dtype=np.float64).reshape(-1)
    ids_a = np.asarray(ids).reshape(-1)
    t_a = np.asarray(t_ns).reshape(-1)
    for name, arr in (("y", y), ("ids", ids_a), ("t_ns", t_a)):
        if arr.shape[0] != n:
            raise InputDataError(f"{name} has {arr.shape[0]} entries, X has {n} rows")
    for name, arr in (("ids", ids_a), ("t_ns", t_a)):
        if arr.size and not np.issubdtype(arr.dtype, np.integer):
            raise InputDataError(f"{name} must be integers (int64), got dtype {arr.dtype}")
    bad = ~(np.isfinite(X).all(axis=1) & np.isfinite(y))
    if bad.any():
        raise InputDataError(
            f"{int(bad.sum())} observations hold NaN/inf (first row {int(np.argmax(bad))})"
        )
    return X, y, ids_a.astype(np.int64), t_a.astype(np.int64)


def merge_observations(
    X: np.ndarray,
    y: np.ndarray,
    ids: np.ndarray,
    t_ns: np.ndarray,
    voxel_m: float,
    suspects: Iterable[int] | np.ndarray = (),
    external_voxel_m: float | None = None,
) -> TrainingSet:
    """Merge observations per (label, voxel, suspect flag); see the module docstring.

    Parameters
    ----------
    X : (n, d) float64, metres
    y : (n,) float64 labels (-1 internal, 0 contact, +1 external)
    ids : (n,) int64 observation ids
    t_ns : (n,) int64 observation times, ns (data clock)
    voxel_m : float
        Voxel edge for contacts and internal points, metres.
    suspects : iterable of int
        Ids of suspected false contacts: never merged with trusted observations.
    external_voxel_m : float, optional
        Voxel edge for external points (y > 0), metres (default ``voxel_m``).

    Returns
    -------
    TrainingSet
    """
    X, y, ids, t_ns = _check(X, y, ids, t_ns)
    if not (np.isfinite(voxel_m) and voxel_m > 0):
        raise InputDataError(f"voxel_m must be a positive number of metres, got {voxel_m!r}")
    ext = voxel_m if external_voxel_m is None else float(external_voxel_m)
    if not (np.isfinite(ext) and ext > 0):
        raise InputDataError(f"external_voxel_m must be > 0 metres, got {external_voxel_m!r}")
    n, d = X.shape
    if n == 0:
        return TrainingSet(
            np.zeros((0, d)),
            np.zeros(0),
            np.zeros(0, np.int64),
            np.zeros(0, np.int64),
            [],
            np.zeros(0, np.int64),
            np.zeros(0, bool),
            ids,
        )
    sus_ids = np.asarray(suspects if isinstance(suspects, np.ndarray) else list(suspects))
    sus = np.isin(ids, sus_ids.astype(np.int64)) if sus_ids.size else np.zeros(n, dtype=bool)
    size = np.where(y > 0, ext, voxel_m)
    vox = np.floor(X / size[:, None]).astype(np.int64)
    _, label = np.unique(y, return_inverse=True)
    keys = np.column_stack([label.reshape(-1), sus.astype(np.int64), vox])
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    m = int(inv.max()) + 1
    # Order cells by their first member's time (then row), so old cells keep their places.
    order = np.lexsort((np.arange(n), t_ns))
    first_pos = np.full(m, n, dtype=np.int64)
    np.minimum.at(first_pos, inv[order], np.arange(n))
    rank = np.empty(m, dtype=np.int64)
    rank[np.argsort(first_pos, kind="stable")] = np.arange(m)
    cell = rank[inv]
    counts = np.bincount(cell, minlength=m)
    Xm = np.stack([np.bincount(cell, X[:, j], minlength=m) for j in range(d)], axis=1)
    Xm /= counts[:, None]
    ym = np.empty(m)
    ym[cell] = y
    susm = np.zeros(m, dtype=bool)
    susm[cell] = sus
    # Members grouped by cell, each in time order; the last one is the most recent.
    by_cell = order[np.argsort(cell[order], kind="stable")]
    bounds = np.concatenate([[0], np.cumsum(counts)])
    members = [by_cell[bounds[j] : bounds[j + 1]] for j in range(m)]
    rep_ids = ids[by_cell[bounds[1:] - 1]]
    return TrainingSet(Xm, ym, counts.astype(np.int64), rep_ids, members, cell, susm, ids)


class ObservationStore:
    """Every raw observation of a session (by id) and its merged view for fitting.

    Parameters
    ----------
    voxel_m : float
        Voxel edge for contacts and internal points, metres.
    external_voxel_m : float, optional
        Voxel edge for external points, metres (default ``voxel_m``).
    """

    def __init__(self, voxel_m: float, external_voxel_m: float | None = None) -> None:
        self.set_voxel(voxel_m, external_voxel_m)
        self._X: list[np.ndarray] = []
        self._y: list[np.ndarray] = []
        self._ids: list[np.ndarray] = []
        self._t: list[np.ndarray] = []
        self._n = 0
        self._suspects = np.zeros(0, dtype=np.int64)
        self._cache: TrainingSet | None = None
        self._seen: set[int] = set()

    def set_voxel(self, voxel_m: float, external_voxel_m: float | None = None) -> None:
        """Change the voxel sizes (metres); the merged view is rebuilt on next use."""
        if not (np.isfinite(voxel_m) and voxel_m > 0):
            raise InputDataError(f"voxel_m must be a positive number of metres, got {voxel_m!r}")
        if external_voxel_m is not None and not (
            np.isfinite(external_voxel_m) and external_voxel_m > 0
        ):
            raise InputDataError(f"external_voxel_m must be > 0 metres, got {external_voxel_m!r}")
        self.voxel_m = float(voxel_m)
        self.external_voxel_m = None if external_voxel_m is None else float(external_voxel_m)
        self._cache = None

    def add(self, ids: np.ndarray, X: np.ndarray, y: np.ndarray, t_ns: np.ndarray) -> None:
        """Append observations: ids (n,) int64, X (n, d) metres, y (n,), t_ns (n,) int64.

        Raises
        ------
        InputDataError
            Bad shapes/values, a dimension different from earlier data, or an id seen before.
        """
        X, y, ids_a, t_a = _check(X, y, ids, t_ns)
        if ids_a.size == 0:
            return
        if self._X and X.shape[1] != self._X[0].shape[1]:
            raise InputDataError(
                f"X has {X.shape[1]} columns, earlier observations had {self._X[0].shape[1]}"
            )
        new = ids_a.tolist()
        dup = self._seen.intersection(new)
        if dup or len(set(new)) != len(new):
            shown = sorted(dup)[:5] if dup else "within the batch"
            raise InputDataError(f"observation ids must be unique; repeated: {shown}")
        self._seen.update(new)
        self._X.append(X)
        self._y.append(y)
        self._ids.append(ids_a)
        self._t.append(t_a)
        self._n += ids_a.size
        self._cache = None

    def set_suspects(self, ids: Iterable[int] | np.ndarray) -> None:
        """Ids currently flagged as suspected false contacts (replaces the previous set)."""
        arr = np.unique(np.asarray(list(ids) if not isinstance(ids, np.ndarray) else ids))
        arr = arr.astype(np.int64)
        if not np.array_equal(arr, self._suspects):
            self._suspects = arr
            self._cache = None

    def _compact(self) -> None:
        if len(self._X) > 1:
            self._X = [np.concatenate(self._X)]
            self._y = [np.concatenate(self._y)]
            self._ids = [np.concatenate(self._ids)]
            self._t = [np.concatenate(self._t)]

    def raw(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """All raw observations in arrival order: ids (N,), X (N, d), y (N,), t_ns (N,)."""
        if not self._X:
            return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64)
        self._compact()
        return self._ids[0], self._X[0], self._y[0], self._t[0]

    def training_set(self) -> TrainingSet:
        """The merged view (cached until data, suspects or voxel sizes change)."""
        if self._cache is None:
            ids, X, y, t = self.raw()
            self._cache = merge_observations(
                X, y, ids, t, self.voxel_m, self._suspects, self.external_voxel_m
            )
        return self._cache

    @property
    def raw_count(self) -> int:
        """Number of raw observations."""
        return self._n

    @property
    def merged_count(self) -> int:
        """Number of merged cells (training points)."""
        return len(self.training_set())


# --------------------------------------------------------------------------- radius merge
#
# Voxel cells double where a face lies on a voxel boundary (noise puts its contacts on both
# sides), and they shift when the voxel follows the learnt length scale. The radius rule has
# neither problem: leader clustering in time order, per label, where a point joins the nearest
# existing anchor of its label within ``radius`` and otherwise becomes a new anchor. Anchors are
# never closer than ``radius`` to each other, so the number of cells on a surface is bounded by
# its area over ~radius^2 whatever the flight time, and a revisited face adds no cells. Anchors
# only depend on the past, so a growing session can be processed incrementally
# (:class:`StreamingMerger`) with the same result as a batch run on the same rows.

_CHUNK = 512  # rows per KD-tree query against the anchors (the rest is a short Python loop)


def _leader(P: np.ndarray, radius: float, anchors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Leader clustering of rows ``P`` (n, d) in order, continuing from ``anchors`` (k, d).

    Returns the anchor index of every row (n,) and the updated anchors (k', d).
    """
    from scipy.spatial import cKDTree

    n, d = P.shape
    assign = np.empty(n, dtype=np.int64)
    r2 = radius * radius
    for start in range(0, n, _CHUNK):
        Q = P[start : start + _CHUNK]
        k = anchors.shape[0]
        free = np.ones(Q.shape[0], dtype=bool)
        if k:
            dist, j = cKDTree(anchors).query(Q, distance_upper_bound=radius)
            hit = np.isfinite(dist)
            assign[start : start + Q.shape[0]][hit] = j[hit]
            free = ~hit
        rest = np.flatnonzero(free)
        if rest.size:
            new = np.empty((rest.size, d))
            cnt = 0
            for i in rest:
                if cnt:
                    dd = np.sum((new[:cnt] - Q[i]) ** 2, axis=1)
                    j = int(np.argmin(dd))
                    if dd[j] <= r2:
                        assign[start + i] = k + j
                        continue
                new[cnt] = Q[i]
                assign[start + i] = k + cnt
                cnt += 1
            anchors = np.vstack([anchors, new[:cnt]])
    return assign, anchors


class StreamingMerger:
    """Incremental radius merge of a growing session (see the section comment above).

    Parameters
    ----------
    radius_m : float
        Cell radius for contacts and internal points, metres.
    external_radius_m : float, optional
        Cell radius for external points (y > 0), metres (default ``radius_m``).
    suspect_radius_m : float, optional
        Radius within which suspected false contacts of one label merge among themselves
        (default ``external_radius_m``): one gust cluster gives one cell per label.

    Notes
    -----
    Every row is given an anchor when first seen (``update``); rows are recognised by id, so
    pass each observation with the same id, position and label every time. Cells are
    ``(label, anchor, trusted)`` for trusted rows and ``(label, suspect cluster)`` for suspects,
    so a suspect never shares a cell with a trusted row. Cells are ordered by their first
    member's time; each cell's position is its members' mean.
    """

    def __init__(
        self,
        radius_m: float,
        external_radius_m: float | None = None,
        suspect_radius_m: float | None = None,
    ) -> None:
        self.radius_m = _positive("radius_m", radius_m)
        self.external_radius_m = _positive(
            "external_radius_m", radius_m if external_radius_m is None else external_radius_m
        )
        self.suspect_radius_m = _positive(
            "suspect_radius_m",
            self.external_radius_m if suspect_radius_m is None else suspect_radius_m,
        )
        self._anchors: dict[float, np.ndarray] = {}
        self._known = np.zeros(0, dtype=np.int64)  # sorted ids seen so far
        self._anchor_of = np.zeros(0, dtype=np.int64)  # global anchor key per sorted id
        self._offset: dict[float, int] = {}  # label -> key offset (keys unique across labels)

    def _key_base(self, label: float) -> int:
        if label not in self._offset:
            self._offset[label] = len(self._offset)
        return self._offset[label]

    def update(
        self,
        X: np.ndarray,
        y: np.ndarray,
        ids: np.ndarray,
        t_ns: np.ndarray,
        suspects: Iterable[int] | np.ndarray = (),
    ) -> TrainingSet:
        """Merged view of ALL observations so far (rows not seen before are anchored first).

        Parameters
        ----------
        X : (n, d) float64, metres; y : (n,) labels; ids : (n,) int64 unique ids;
        t_ns : (n,) int64 times, ns; suspects : ids of suspected false contacts.

        Returns
        -------
        TrainingSet
        """
        X, y, ids, t_ns = _check(X, y, ids, t_ns)
        n, d = X.shape
        if np.unique(ids).size != n:
            raise InputDataError("observation ids must be unique")
        if n == 0:
            return merge_observations(X, y, ids, t_ns, self.radius_m)
        pos = np.searchsorted(self._known, ids)
        seen = pos < self._known.size
        seen[seen] = self._known[pos[seen]] == ids[seen]
        if not seen.all():
            new = np.flatnonzero(~seen)
            new = new[np.lexsort((new, t_ns[new]))]  # time order (then row order)
            keys = np.empty(new.size, dtype=np.int64)
            for label in np.unique(y[new]):
                sel = y[new] == label
                base = self._key_base(float(label))
                radius = self.external_radius_m if label > 0 else self.radius_m
                anchors = self._anchors.get(float(label), np.zeros((0, d)))
                a, self._anchors[float(label)] = _leader(X[new[sel]], radius, anchors)
                keys[sel] = a * 8 + base  # at most a handful of labels
            known = np.concatenate([self._known, ids[new]])
            anchor_of = np.concatenate([self._anchor_of, keys])
            order = np.argsort(known, kind="stable")
            self._known, self._anchor_of = known[order], anchor_of[order]
        key = self._anchor_of[np.searchsorted(self._known, ids)] * 2  # trusted: even keys
        sus_ids = np.asarray(suspects if isinstance(suspects, np.ndarray) else list(suspects))
        sus = np.isin(ids, sus_ids.astype(np.int64)) if sus_ids.size else np.zeros(n, bool)
        if sus.any():
            rows = np.flatnonzero(sus)
            rows = rows[np.lexsort((rows, t_ns[rows]))]
            for label in np.unique(y[rows]):
                sel = rows[y[rows] == label]
                a, _ = _leader(X[sel], self.suspect_radius_m, np.zeros((0, d)))
                key[sel] = (a * 8 + self._key_base(float(label))) * 2 + 1  # suspects: odd keys
        return _cells(X, y, ids, t_ns, key, sus)


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not (np.isfinite(value) and value > 0):
        raise InputDataError(f"{name} must be a positive number of metres, got {value!r}")
    return value


def _cells(X, y, ids, t_ns, key, sus) -> TrainingSet:
    """TrainingSet of the cells given by an integer ``key`` per row (ordered by first time)."""
    n, d = X.shape
    _, inv = np.unique(key, return_inverse=True)
    inv = inv.reshape(-1)
    m = int(inv.max()) + 1
    order = np.lexsort((np.arange(n), t_ns))
    first_pos = np.full(m, n, dtype=np.int64)
    np.minimum.at(first_pos, inv[order], np.arange(n))
    rank = np.empty(m, dtype=np.int64)
    rank[np.argsort(first_pos, kind="stable")] = np.arange(m)
    cell = rank[inv]
    counts = np.bincount(cell, minlength=m)
    Xm = np.stack([np.bincount(cell, X[:, j], minlength=m) for j in range(d)], axis=1)
    Xm /= counts[:, None]
    ym = np.empty(m)
    ym[cell] = y
    susm = np.zeros(m, dtype=bool)
    susm[cell] = sus
    by_cell = order[np.argsort(cell[order], kind="stable")]
    bounds = np.concatenate([[0], np.cumsum(counts)])
    members = [by_cell[bounds[j] : bounds[j + 1]] for j in range(m)]
    rep_ids = ids[by_cell[bounds[1:] - 1]]
    return TrainingSet(Xm, ym, counts.astype(np.int64), rep_ids, members, cell, susm, ids)


def radius_merge(
    X: np.ndarray,
    y: np.ndarray,
    ids: np.ndarray,
    t_ns: np.ndarray,
    radius_m: float,
    suspects: Iterable[int] | np.ndarray = (),
    external_radius_m: float | None = None,
    suspect_radius_m: float | None = None,
) -> TrainingSet:
    """Batch radius merge (identical to one :meth:`StreamingMerger.update` on these rows)."""
    merger = StreamingMerger(radius_m, external_radius_m, suspect_radius_m)
    return merger.update(X, y, ids, t_ns, suspects)
