"""Cavities: mesh surface inside a touched structure, facing its own inside (pure).

The field's prior mean says 'outside' wherever the data say nothing. Deep inside a structure
touched all round, farther behind its walls than the internal points (``d_in``) plus about a
length scale, the field goes back to that prior, and marching cubes draws a second, inward-facing
shell there: on the dense 40-minute session (l = 0.1 m) the inside of the 1.4 m box and of the
0.7 m pillar, 2.8 m² of surface 0.2 m from anything true, the largest phantom patch of its map.
No vehicle was ever in there to touch it.

A face belongs to such a cavity when

1. it lies behind the touch nearest to it (more than ``depth_m`` behind that touch's tangent
   plane) and faces away from it (its outward normal against the touch's), and
2. looking out along its normal, the first thing met is a touch *from behind* (that touch's
   outward normal along the look: the far wall of the same structure, seen from inside), before
   any free-space sample (the vehicle was there: the face looks at open space) or a touch
   facing it (another structure, seen from outside).

The back side of a thin wall passes 1 but not 2: its outward look goes into open space. Faces
that pass 1 are grouped into connected pieces, and a piece whose faces mostly pass 2 is a cavity
(one ray that slips between sparse touches does not decide a piece). Rays are cast from at most
``RAYS_PER_PIECE`` faces of each piece (drawn at random, seeded), stepping ``radius_m`` for
``ray_m``: on an ordinary flight's 16,000-face map the check costs about 10 ms.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from groundstation.mapping.surface import SurfaceMesh

#: Rays cast at most per piece (its vote needs a sample of its faces, not all of them).
RAYS_PER_PIECE = 64
#: A touch met from behind counts when its normal is within ~73 deg of the look.
ALONG_COS = 0.3


def cavity_faces(
    mesh: SurfaceMesh,
    contacts: np.ndarray,
    normals: np.ndarray,
    free: np.ndarray,
    *,
    depth_m: float,
    radius_m: float = 0.1,
    ray_m: float = 2.0,
    seed: int = 0,
) -> np.ndarray:
    """(F,) bool: the faces of ``mesh`` that belong to a cavity (module docstring).

    Parameters
    ----------
    mesh : SurfaceMesh
        Its vertex normals point outwards (towards the positive field).
    contacts : (k, 3) float64
        Trusted contact points.
    normals : (k, 3) float64
        Their outward normals (any length > 0; zero rows are never 'behind' anything).
    free : (m, 3) float64
        Free-space samples (where the vehicle was).
    depth_m : float
        How far behind its nearest touch a face must lie to be a candidate (deeper than the
        internal points).
    radius_m : float
        A look meets a touch or a free sample passing within this distance.
    ray_m : float
        How far a face looks out.
    seed : int
        Seed of the faces drawn when a piece has more than ``RAYS_PER_PIECE``.
    """
    n_faces = int(mesh.faces.shape[0])
    out = np.zeros(n_faces, dtype=bool)
    if n_faces == 0 or len(contacts) == 0:
        return out
    V, F = mesh.vertices, mesh.faces
    C = np.asarray(contacts, dtype=np.float64).reshape(-1, 3)
    N = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    N = N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
    v0, v1, v2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    cent = (v0 + v1 + v2) / 3.0
    fn = np.cross(v1 - v0, v2 - v0)
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-12)
    vn = mesh.normals[F[:, 0]] + mesh.normals[F[:, 1]] + mesh.normals[F[:, 2]]
    fn *= np.where(np.einsum("ij,ij->i", fn, vn) < 0, -1.0, 1.0)[:, None]  # outwards
    touches = cKDTree(C)
    _, j = touches.query(cent)
    behind = np.einsum("ij,ij->i", C[j] - cent, N[j]) > depth_m
    cand = np.flatnonzero(behind & (np.einsum("ij,ij->i", fn, N[j]) < 0.0))
    if cand.size == 0:
        return out
    # connected pieces of candidate faces
    Fc = F[cand]
    a, b = Fc.reshape(-1), Fc[:, [1, 2, 0]].reshape(-1)
    nv = V.shape[0]
    _, piece = connected_components(
        coo_matrix((np.ones(a.size), (a, b)), shape=(nv, nv)), directed=False
    )
    piece_of = piece[Fc[:, 0]]
    shuffled = np.random.default_rng(seed).permutation(cand.size)
    by_piece = shuffled[np.argsort(piece_of[shuffled], kind="stable")]
    starts = np.searchsorted(piece_of[by_piece], piece_of[by_piece], side="left")
    look = np.sort(by_piece[np.arange(by_piece.size) - starts < RAYS_PER_PIECE])
    f = cand[look]
    s = radius_m * np.arange(1, int(ray_m / radius_m) + 1)
    Q = (cent[f][:, None, :] + s[None, :, None] * fn[f][:, None, :]).reshape(-1, 3)
    K = s.size
    d_c, j_c = touches.query(Q, distance_upper_bound=radius_m)
    hit_c = np.isfinite(d_c).reshape(-1, K)
    j_c = j_c.reshape(-1, K)
    if len(free):
        d_f, _ = cKDTree(np.asarray(free, dtype=np.float64).reshape(-1, 3)).query(
            Q, distance_upper_bound=radius_m
        )
        hit_f = np.isfinite(d_f).reshape(-1, K)
    else:
        hit_f = np.zeros_like(hit_c)
    first_c = np.where(hit_c.any(axis=1), hit_c.argmax(axis=1), K)
    first_f = np.where(hit_f.any(axis=1), hit_f.argmax(axis=1), K)
    met = (first_c < K) & (first_c <= first_f)  # a touch before any free sample
    rows = np.arange(f.size)
    along = np.einsum("ij,ij->i", N[j_c[rows, np.minimum(first_c, K - 1)] % len(C)], fn[f])
    inside = met & (along > ALONG_COS)
    n_pieces = int(piece.max()) + 1
    votes = np.bincount(piece_of[look], weights=inside.astype(np.float64), minlength=n_pieces)
    rays = np.bincount(piece_of[look], minlength=n_pieces)
    cavity = votes >= 0.5 * np.maximum(rays, 1)
    out[cand] = cavity[piece_of] & (rays[piece_of] > 0)
    return out
