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


@dataclasses.dataclass(frozen=True)
class TileLayout:
    """Cubic tiles of ``edge_m`` with a halo of ``halo_m`` (metres)."""

    edge_m: float = 2.0
    halo_m: float = 0.75

    def keys(self, X: np.ndarray) -> np.ndarray:
        """(n, d) int64 tile index of each point (its core tile)."""
        return np.floor(np.asarray(X, dtype=np.float64) / self.edge_m).astype(np.int64)

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


def signature(*arrays: np.ndarray) -> str:
    """A digest of a tile's inputs: equal digests, equal fits."""
    h = hashlib.sha1()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str(a.dtype).encode())
        h.update(str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()
