"""Local blocks: the map's space cut into cubic tiles, each fitted on its own rows (pure).

A GP with a squared-exponential kernel of length scale l <= 0.5 m correlates nothing beyond a
metre or two, so the map is fitted tile by tile: a tile's model sees the rows inside its cube
grown by a halo of ``halo_m`` (at least three length scales, so its core is predicted as a model
of everything would predict it), and answers for its core. A refit then costs the tiles whose rows
changed, not the whole session: cost follows the structure's size and where the vehicle is,
not the flight's duration (DESIGN.md §3).

Tiles are keyed by integer indices on a lattice of ``edge_m`` anchored at the world origin, so
their cores never move as the map grows.
"""

from __future__ import annotations

import dataclasses
import hashlib

import numpy as np
from scipy.spatial import cKDTree


@dataclasses.dataclass(frozen=True)
class TileLayout:
    """Cubic tiles of ``edge_m`` with a halo of ``halo_m`` (metres)."""

    edge_m: float = 2.0
    halo_m: float = 0.75

    def keys(self, X: np.ndarray) -> np.ndarray:
        """(n, d) int64 tile index of each point (its core tile)."""
        return np.floor(np.asarray(X, dtype=np.float64) / self.edge_m).astype(np.int64)

    def keys_near(self, X: np.ndarray, reach_m: float) -> np.ndarray:
        """(k, d) int64 keys of the tiles whose core comes within ``reach_m`` of a point (by
        box: a superset of the ball), sorted: a tile with no point of its own in its core can
        still hold surface drawn from its neighbours' points."""
        X = np.asarray(X, dtype=np.float64)
        d = X.shape[1]
        if X.shape[0] == 0:
            return np.zeros((0, d), dtype=np.int64)
        lo = np.unique(np.floor((X - reach_m) / self.edge_m).astype(np.int64), axis=0)
        span = int(np.ceil(2.0 * reach_m / self.edge_m)) + 1
        offsets = np.stack(np.meshgrid(*[np.arange(span)] * d, indexing="ij"), -1).reshape(-1, d)
        cand = np.unique((lo[:, None, :] + offsets[None]).reshape(-1, d), axis=0)
        # a point's box [x - r, x + r] meets a core when the point lies within (edge / 2 + r)
        # of the core's centre in the max norm
        centre = (cand + 0.5) * self.edge_m
        bound = 0.5 * self.edge_m + reach_m + 1e-9
        _, idx = cKDTree(X).query(centre, p=np.inf, distance_upper_bound=bound)
        return cand[idx < X.shape[0]]

    def core(self, key: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper corners of a tile's core, metres."""
        k = np.asarray(key, dtype=np.float64)
        return k * self.edge_m, (k + 1.0) * self.edge_m

    def members(
        self, X: np.ndarray, key: tuple[int, ...], halo_m: float | None = None
    ) -> np.ndarray:
        """Indices of the rows inside the tile's core grown by the halo."""
        lo, hi = self.core(key)
        h = self.halo_m if halo_m is None else halo_m
        inside = np.all((X >= lo - h) & (X < hi + h), axis=1)
        return np.flatnonzero(inside)

    def members_of(self, X: np.ndarray, keys) -> dict[tuple, np.ndarray]:
        """:meth:`members` of every tile in ``keys`` (default halo), sharing the per-axis
        tests: tiles in one row of the lattice test each coordinate once between them."""
        h = self.halo_m
        inside: dict[tuple[int, int], np.ndarray] = {}  # (axis, index) -> rows within it
        out = {}
        for key in keys:
            masks = []
            for axis, k in enumerate(key):
                m = inside.get((axis, k))
                if m is None:  # as members(): core (k * edge, (k + 1) * edge) grown by h
                    x = X[:, axis]
                    lo, hi = float(k) * self.edge_m, (float(k) + 1.0) * self.edge_m
                    m = inside[(axis, k)] = (x >= lo - h) & (x < hi + h)
                masks.append(m)
            out[key] = np.flatnonzero(np.logical_and.reduce(masks))
        return out


def signature(*arrays: np.ndarray) -> str:
    """A digest of a tile's inputs: equal digests, equal fits."""
    h = hashlib.sha1()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(a.dtype.str.encode())  # '<f8' (str(dtype) costs 15x more, per array)
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()
