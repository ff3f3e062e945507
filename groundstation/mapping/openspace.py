"""The open-space offset: away from the touches, surface only where the field is sure (pure).

The map draws its surface where the GP's posterior mean crosses zero. Where the data say little,
that mean relaxes to the prior mean over about a length scale, so a touched face carries on past
the data by roughly that much: a pier deck touched at mid-height on its side (the guard ring at
the vehicle's centre height) and on its top only half a metre in from that edge was drawn
0.13-0.26 m above its top along the edge (field probed over the deck's long edges, a tuning
flight), and as much below its underside. Nothing flew there, and no touch reached there.

Yet a point in front of a touched face and away from every point a touch showed to be surface is
open space more often than surface. The offset says so: it is added to the posterior mean
wherever the field is evaluated (the mesh, ``SurfaceModel.predict``), never to the fit, so every
decision the mixture takes (flags, settling, the kernel) is exactly what it is without it:

    b(x) = b_max * S((d(x) - start) / (end - start)) * S(front(x) / front_m),
    S(t) = 3 t^2 - 2 t^3 on t clipped to [0, 1]

with ``d(x)`` the distance from ``x`` to the nearest surface row (contacts and a lone touch's
plane points, whatever the fit decides of their events: a gust's point keeps its field as
today) and ``front(x)`` how far ``x`` lies in front of the tangent plane of the touch within
``reach_m`` that it is most in front of (no touch within reach: open space). The surface is then
the level set ``f = -b``: within ``start`` of the evidence it is the GP's own zero set; in open
space away from it the field must be clearly inside for surface to be drawn there.

A point behind every touch near it is the inside of a structure, and has no offset: a 0.8 m
box's centre, 0.4 m from its touches, would otherwise be drawn as a cavity. So is a point deeper
than ``inside_m`` behind the touch nearest to it when no free-space sample (a place the vehicle
was) lies nearer to it than that touch (the offset fades out by ``2 inside_m``): the inside of a
box next to a wall touched on its far side, in front of the wall's touches. Behind a thin wall
touched on one side the vehicle flew, and the bulge drawn there keeps its offset.

Past an edge of a convex solid that fade does not apply (``solid``): a point deep behind the
nearest touch but in front of another face of its solid (a touch within reach, each of the two
on or behind the other's tangent plane: ``mapping.training.one_solid``, the plane guard's test)
is outside that solid: over a pier deck's edge, deeper behind the touched side than d_in but
above the touched top, and behind a thin wall touched on both faces. Without it the side face
was carried on up there (on the unit tests' deck 4.4 % of the mesh lay over 8 cm above the top,
none with it). The inside of a box next to a wall fails the test (the wall's touch is in front
of the box's face) and keeps no offset.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from groundstation.mapping.training import one_solid

#: Touches the front test looks at (the nearest ones within ``reach_m``).
FRONT_NEIGHBOURS = 16


class OpenSpaceOffset:
    """The offset ``b(x)`` of the module docstring.

    Parameters
    ----------
    offset : float
        ``b_max`` (label units; 0: none).
    start_m, end_m : float
        Where the rise with the distance to the nearest anchor starts and ends, metres
        (``0 <= start_m < end_m``).
    anchors : (k, d) float64
        Surface rows: points the data showed to be on the surface.
    faces, face_normals : (j, d) float64, optional
        Touches and their outward normals, for the front test (None: every point is open).
    reach_m, front_m : float
        The front test's reach, and how far in front of a touch's plane the full offset applies.
    inside_m : float
        Depth behind the nearest touch's plane from which the offset fades (to 0 at twice it)
        where no free-space sample is nearer than that touch.
    free : (f, d) float64, optional
        Free-space samples (None: none).
    solid : bool
        Cancel the fade in front of another face of the nearest touch's solid.
    """

    def __init__(
        self,
        offset: float,
        start_m: float,
        end_m: float,
        anchors: np.ndarray,
        faces: np.ndarray | None = None,
        face_normals: np.ndarray | None = None,
        reach_m: float = 0.8,
        front_m: float = 0.1,
        inside_m: float = 0.1,
        free: np.ndarray | None = None,
        solid: bool = False,
    ) -> None:
        if not 0.0 <= start_m < end_m:
            raise ValueError(f"need 0 <= start_m < end_m, got {start_m!r}, {end_m!r}")
        if not (reach_m > 0.0 and front_m > 0.0 and inside_m > 0.0):
            raise ValueError(
                f"need reach_m, front_m, inside_m > 0, got {reach_m!r}, {front_m!r}, {inside_m!r}"
            )
        self.offset = float(offset)
        self.start_m = float(start_m)
        self.end_m = float(end_m)
        self.reach_m = float(reach_m)
        self.front_m = float(front_m)
        self.inside_m = float(inside_m)
        self.solid = bool(solid)
        self.anchors = np.asarray(anchors, dtype=np.float64)
        none = self.offset == 0.0 or self.anchors.shape[0] == 0
        self._tree = None if none else cKDTree(self.anchors)
        self._faces = None
        if not none and faces is not None and len(faces):
            n = np.asarray(face_normals, dtype=np.float64)
            n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            self._faces = (cKDTree(np.asarray(faces, dtype=np.float64)), n)
            j = len(n)  # the one_solid rows worked out so far (_solid_rows)
            self._solid = np.zeros((j, j), dtype=bool)
            self._solid_done = np.zeros(j, dtype=bool)
        self._free = None
        if self._faces is not None and free is not None and len(free):
            self._free = cKDTree(np.asarray(free, dtype=np.float64))

    @classmethod
    def none(cls) -> OpenSpaceOffset:
        """No offset anywhere."""
        return cls(0.0, 0.0, 1.0, np.zeros((0, 3)))

    @property
    def is_zero(self) -> bool:
        """Whether the offset is 0 everywhere."""
        return self._tree is None

    def __call__(self, X: np.ndarray) -> np.ndarray:
        """(m,) float64: ``b`` at ``X`` (m, d)."""
        X = np.asarray(X, dtype=np.float64)
        if self._tree is None or X.shape[0] == 0:
            return np.zeros(X.shape[0])
        d, _ = self._tree.query(X, distance_upper_bound=self.end_m)
        out = self.offset * _step((d - self.start_m) / (self.end_m - self.start_m))
        rising = np.flatnonzero(out != 0.0)
        if self._faces is not None and rising.size:
            out[rising] *= self._open(X[rising])
        return out

    def _open(self, X: np.ndarray) -> np.ndarray:
        """(m,) in [0, 1]: how far in front of the touches near it each point lies (1: open
        space; 0: behind every touch within ``reach_m``, or deep behind the nearest one)."""
        tree, n = self._faces
        # No touch within reach, or ``front_m`` or more in front of the nearest one: open space
        # (the front test saturates and nothing is behind), found with the nearest touch alone.
        d, j = tree.query(X, k=1, distance_upper_bound=self.reach_m)
        found = np.isfinite(d)
        jj = np.where(found, j, 0)
        near = found & (np.einsum("md,md->m", X - tree.data[jj], n[jj]) < self.front_m)
        out = np.ones(X.shape[0])
        if near.any():
            out[near] = self._open_near(X[near])
        return out

    def _open_near(self, X: np.ndarray) -> np.ndarray:
        """:meth:`_open` at points with touches near them, from the ``FRONT_NEIGHBOURS`` nearest."""
        tree, n = self._faces
        k = min(FRONT_NEIGHBOURS, tree.n)
        d, j = tree.query(X, k=k, distance_upper_bound=self.reach_m)
        d, j = d.reshape(len(X), k), j.reshape(len(X), k)
        found = np.isfinite(d)
        jj = np.where(found, j, 0)
        front_k = np.einsum("mkd,mkd->mk", X[:, None, :] - tree.data[jj], n[jj])
        depth = -front_k[:, 0]  # behind the nearest touch (the query sorts by distance)
        front = np.where(found, front_k, -np.inf).max(axis=1)
        inside = _step((depth - self.inside_m) / self.inside_m)
        if self.solid and k > 1:  # ... unless it is in front of another face of that solid
            first, row = np.unique(jj[:, 0], return_inverse=True)
            table = self._solid_rows(first)
            one = table[row.reshape(-1, 1), jj] & found & found[:, :1]
            one[:, 0] = False
            past = np.where(one, _step(np.where(found, front_k, 0.0) / self.front_m), 0.0)
            inside *= 1.0 - past.max(axis=1)
        if self._free is not None:  # ... unless the vehicle was nearer than that touch
            d_free, _ = self._free.query(X, distance_upper_bound=self.reach_m)
            inside *= _step((np.minimum(d_free, self.reach_m) - d[:, 0]) / self.inside_m)
        return np.where(found[:, 0], _step(front / self.front_m) * (1.0 - inside), 1.0)

    def _solid_rows(self, first: np.ndarray) -> np.ndarray:
        """(len(first), j) bool: ``one_solid`` of each touch ``first[i]`` against every touch.
        A pair's test depends on the two touches only, so each nearest touch's row is worked
        out once per offset (a mesh evaluates the offset in hundreds of calls, each with a few
        dozen nearest touches), not once per call or point."""
        tree, n = self._faces
        todo = np.flatnonzero(~self._solid_done[first])
        if todo.size:
            new = first[todo]
            a, b = np.repeat(new, tree.n), np.tile(np.arange(tree.n), new.size)
            self._solid[new] = one_solid(tree.data[a], n[a], tree.data[b], n[b]).reshape(
                new.size, -1
            )
            self._solid_done[new] = True
        return self._solid[first]

    def digest_near(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """(k,) float64: the anchors and touches that shape the offset inside the box
        ``[lo, hi]`` (those within ``end_m``, or ``reach_m + end_m``, of it), sorted and
        flattened: a tile whose mesh was drawn with another offset must be drawn again."""
        if self._tree is None:
            return np.zeros(0)
        A = self.anchors[_in_box(self.anchors, lo, hi, self.end_m)]
        parts = [A[np.lexsort(A.T[::-1])].ravel()]
        if self._faces is not None:
            tree, n = self._faces
            sel = _in_box(tree.data, lo, hi, self.reach_m + self.end_m)
            B = np.column_stack([tree.data[sel], n[sel]])
            parts.append(B[np.lexsort(B.T[::-1])].ravel())
        return np.concatenate(parts)


def _step(t: np.ndarray) -> np.ndarray:
    """Smooth step 3 t^2 - 2 t^3 of ``t`` clipped to [0, 1]."""
    t = np.clip(t, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _in_box(P: np.ndarray, lo, hi, grow: float) -> np.ndarray:
    """(k,) bool: the points of ``P`` within ``grow`` of the box ``[lo, hi]`` (by box)."""
    lo = np.asarray(lo, dtype=np.float64) - grow
    hi = np.asarray(hi, dtype=np.float64) + grow
    return np.all((P >= lo) & (P <= hi), axis=1)
