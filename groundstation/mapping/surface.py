"""Zero level set of an implicit-surface field: triangle meshes (3D) and contours (2D).

The field follows the GPIS convention (DESIGN.md §3): the shape potential is negative inside,
zero on the surface and positive outside, so outward normals point along +grad(mu).

* 3D: :func:`extract_surface` runs ``skimage.measure.marching_cubes`` on the grid and returns a
  :class:`SurfaceMesh` (vertices in world coordinates, outward unit normals, the predictive std
  interpolated at each vertex). A field with no zero crossing gives an empty mesh, not an error.
  :func:`to_open3d` builds an ``open3d.geometry.TriangleMesh`` whose vertex colours encode the
  std (:data:`STD_COLORMAP`), and :func:`write_ply` saves it. Open3D is imported lazily inside
  those two functions because its import is slow.
* 2D: :func:`extract_contours` runs ``skimage.measure.find_contours`` and returns polylines in
  world coordinates.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage
from skimage import measure

from groundstation.errors import GroundstationError
from groundstation.mapping.grid import Grid, GridError

#: Matplotlib colormap that maps the predictive std to vertex colours: low std (confident) is
#: dark purple, high std (uncertain) is yellow. Values are clipped to the colour range.
STD_COLORMAP = "viridis"


class SurfaceWriteError(GroundstationError, OSError):
    """A mesh could not be written to disk."""


@dataclasses.dataclass(frozen=True)
class SurfaceMesh:
    """A triangle mesh of the zero level set.

    Attributes
    ----------
    vertices : (V, 3) float64, metres (world coordinates)
    faces : (F, 3) int64, vertex indices, counter-clockwise seen from outside
    normals : (V, 3) float64, outward unit normals (along +grad mu)
    std : (V,) float64 or None, predictive std at the vertices (label units)
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    std: np.ndarray | None = None

    @property
    def is_empty(self) -> bool:
        """True when the field has no zero crossing inside the grid."""
        return self.faces.shape[0] == 0

    @classmethod
    def empty(cls, with_std: bool = False) -> SurfaceMesh:
        """A mesh with no vertices or faces."""
        return cls(
            vertices=np.zeros((0, 3)),
            faces=np.zeros((0, 3), dtype=np.int64),
            normals=np.zeros((0, 3)),
            std=np.zeros(0) if with_std else None,
        )


def confident_part(mesh: SurfaceMesh, max_std: float) -> SurfaceMesh:
    """The faces of ``mesh`` whose three vertices have ``std <= max_std`` (unused vertices
    dropped, indices renumbered). Far from any observation the GP mean relaxes to its prior
    mean and crosses zero anywhere: those sheets are where the map knows nothing.

    Parameters
    ----------
    mesh : SurfaceMesh with ``std``
    max_std : float, label units

    Returns
    -------
    SurfaceMesh
    """
    if mesh.std is None:
        raise GridError("confident_part needs the vertex std (mesh(with_std=True))")
    keep = np.all(mesh.std[mesh.faces] <= max_std, axis=1)
    if keep.all():
        return mesh
    faces = mesh.faces[keep]
    used = np.unique(faces)
    index = np.full(len(mesh.vertices), -1, dtype=np.int64)
    index[used] = np.arange(len(used))
    return SurfaceMesh(mesh.vertices[used], index[faces], mesh.normals[used], mesh.std[used])


def weld_lattice(mesh: SurfaceMesh, spacing: float) -> SurfaceMesh:
    """One vertex per lattice edge: the meshes of grids that share lattice planes (the map's
    tiles, each on the global lattice of ``spacing`` metres through the origin) joined into one
    surface, without seams.

    Marching cubes puts every vertex on an edge of its grid, so a vertex is identified by that
    edge: the axis along which it is fractional, the lattice index before it on that axis and its
    lattice indices on the other two. Two tiles meshing their shared plane put a vertex on the
    same edge, each from its own field (they agree to the tiles' fit, not to the last bit): the
    two become one, at their mean position, with their mean normal and std. Left apart, a patch
    of surface crossing a tile boundary was two patches (``metrics.phantom_patches`` counted a
    0.34 m^2 phantom patch as 0.13 m^2) and the seam a crack in the mesh.

    A vertex at a lattice point is keyed by that point; one on no edge keeps its own place."""
    v = mesh.vertices
    if v.shape[0] == 0:
        return mesh
    if not (np.isfinite(spacing) and spacing > 0):
        raise GridError(f"weld spacing must be a positive number of metres, got {spacing}")
    idx = v / spacing
    near = np.rint(idx)
    on = np.abs(idx - near) <= 1e-4  # marching cubes' float32 grid indices: ~1e-5 off
    axis = np.where(on.sum(axis=1) == 2, np.argmin(on, axis=1), -1)  # the fractional axis
    key = near.astype(np.int64)
    rows = np.flatnonzero(axis >= 0)
    key[rows, axis[rows]] = np.floor(idx[rows, axis[rows]]).astype(np.int64)
    point = on.all(axis=1)  # at a lattice point: that point is its key
    lone = (axis < 0) & ~point  # on no edge: its own key (its index, out of the lattice's way)
    key[lone] = 0
    key[lone, 0] = np.flatnonzero(lone)
    cols = np.column_stack([np.where(point, 3, np.where(lone, -1, axis)), key])
    cols -= cols.min(axis=0)
    size = cols.max(axis=0) + 1
    if float(np.prod(size.astype(np.float64))) < 2.0**62:  # one int64 per key: a 1D sort
        flat = cols[:, 0]
        for k in range(1, cols.shape[1]):
            flat = flat * size[k] + cols[:, k]
        _, inv = np.unique(flat, return_inverse=True)
    else:
        _, inv = np.unique(cols, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    m = int(inv.max()) + 1
    if m == v.shape[0]:
        return mesh
    count = np.bincount(inv, minlength=m).astype(np.float64)

    def mean(a: np.ndarray) -> np.ndarray:
        if a.ndim == 1:
            return np.bincount(inv, weights=a, minlength=m) / count
        return np.column_stack(
            [np.bincount(inv, weights=a[:, j], minlength=m) / count for j in range(a.shape[1])]
        )

    normals = mean(mesh.normals)
    norm = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, norm, out=np.zeros_like(normals), where=norm > 0)
    faces = inv[mesh.faces]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2])
    keep &= faces[:, 0] != faces[:, 2]
    return SurfaceMesh(
        vertices=mean(v),
        faces=faces[keep],
        normals=normals,
        std=None if mesh.std is None else mean(mesh.std),
    )


def _check_field(values: np.ndarray, grid: Grid, what: str) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float64)
    if arr.shape != grid.shape:
        raise GridError(f"{what} has shape {arr.shape}, the grid has shape {grid.shape}")
    if not np.all(np.isfinite(arr)):
        raise GridError(f"{what} holds {int(np.sum(~np.isfinite(arr)))} non-finite values")
    return arr


def _crosses(field: np.ndarray, level: float) -> bool:
    return bool(field.min() < level < field.max())


def extract_surface(
    mean: np.ndarray, grid: Grid, *, std: np.ndarray | None = None, level: float = 0.0
) -> SurfaceMesh:
    """Triangle mesh of ``{x : mean(x) = level}`` by marching cubes.

    Parameters
    ----------
    mean : float64 array of shape ``grid.shape`` (3 axes)
        Predictive mean of the shape potential on the grid.
    grid : Grid
        A 3D grid.
    std : float64 array of shape ``grid.shape``, optional
        Predictive std; trilinearly interpolated at the vertices.
    level : float
        Iso-level (0 for the surface).

    Returns
    -------
    SurfaceMesh
        Empty (0 vertices, 0 faces) when the field does not cross ``level``.
    """
    if grid.ndim != 3:
        raise GridError(f"extract_surface needs a 3D grid, got {grid.ndim}D (use extract_contours)")
    field = _check_field(mean, grid, "mean")
    sd = None if std is None else _check_field(std, grid, "std")
    if not _crosses(field, level):
        return SurfaceMesh.empty(with_std=sd is not None)
    # 'descent' winds faces counter-clockwise seen from the side where the field is larger
    # (outside); its normals point down the gradient, i.e. inwards, so they are negated.
    verts_idx, faces, normals, _ = measure.marching_cubes(
        field, level=level, gradient_direction="descent", allow_degenerate=False
    )
    normals = -np.asarray(normals, dtype=np.float64)
    norm = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, norm, out=np.zeros_like(normals), where=norm > 0)
    vertex_std = None
    if sd is not None:
        vertex_std = ndimage.map_coordinates(sd, verts_idx.T, order=1, mode="nearest")
    return SurfaceMesh(
        vertices=grid.index_to_world(verts_idx),
        faces=np.asarray(faces, dtype=np.int64),
        normals=normals,
        std=vertex_std,
    )


def extract_contours(mean: np.ndarray, grid: Grid, *, level: float = 0.0) -> list[np.ndarray]:
    """Polylines of ``{x : mean(x) = level}`` on a 2D grid (marching squares).

    Parameters
    ----------
    mean : float64 array of shape ``grid.shape`` (2 axes)
    grid : Grid
        A 2D grid (axis 0 is x, axis 1 is y).
    level : float

    Returns
    -------
    list of (k, 2) float64 arrays, metres
        One polyline per contour; a closed contour repeats its first point at the end.
        Empty list when the field does not cross ``level``.
    """
    if grid.ndim != 2:
        raise GridError(f"extract_contours needs a 2D grid, got {grid.ndim}D (use extract_surface)")
    field = _check_field(mean, grid, "mean")
    if not _crosses(field, level):
        return []
    return [grid.index_to_world(c) for c in measure.find_contours(field, level)]


def std_colors(
    std: np.ndarray, std_range: tuple[float, float] | None = None
) -> tuple[np.ndarray, tuple[float, float]]:
    """Map std values to RGB in [0, 1] with :data:`STD_COLORMAP`.

    Parameters
    ----------
    std : (V,) float64
    std_range : (lo, hi), optional
        Colour range; values are clipped to it. Default ``(0, max(std))``.

    Returns
    -------
    colors : (V, 3) float64 in [0, 1]
    std_range : the (lo, hi) used
    """
    import matplotlib

    std = np.asarray(std, dtype=np.float64).reshape(-1)
    if std_range is None:
        hi = float(std.max()) if std.size else 1.0
        std_range = (0.0, hi if hi > 0 else 1.0)
    lo, hi = float(std_range[0]), float(std_range[1])
    if not hi > lo:
        raise GridError(f"std colour range {std_range} must have hi > lo")
    t = np.clip((std - lo) / (hi - lo), 0.0, 1.0)
    return matplotlib.colormaps[STD_COLORMAP](t)[:, :3].astype(np.float64), (lo, hi)


def to_open3d(mesh: SurfaceMesh, *, std_range: tuple[float, float] | None = None) -> Any:
    """Build an ``open3d.geometry.TriangleMesh`` with vertex normals and std colours.

    Parameters
    ----------
    mesh : SurfaceMesh
    std_range : (lo, hi), optional
        Colour range of the std (see :func:`std_colors`); ignored when ``mesh.std`` is None
        (the mesh is then uncoloured).
    """
    import open3d as o3d

    out = o3d.geometry.TriangleMesh()
    out.vertices = o3d.utility.Vector3dVector(np.ascontiguousarray(mesh.vertices))
    out.triangles = o3d.utility.Vector3iVector(np.ascontiguousarray(mesh.faces, dtype=np.int32))
    out.vertex_normals = o3d.utility.Vector3dVector(np.ascontiguousarray(mesh.normals))
    if mesh.std is not None and mesh.std.size:
        colors, _ = std_colors(mesh.std, std_range)
        out.vertex_colors = o3d.utility.Vector3dVector(np.ascontiguousarray(colors))
    return out


def write_ply(mesh: Any, path: str | Path) -> Path:
    """Write an Open3D triangle mesh (or a :class:`SurfaceMesh`) to a binary PLY file.

    Raises
    ------
    SurfaceWriteError
        If Open3D reports a failure (unwritable folder, ...).
    """
    import open3d as o3d

    if isinstance(mesh, SurfaceMesh):
        mesh = to_open3d(mesh)
    path = Path(path)
    if not path.parent.is_dir():
        raise SurfaceWriteError(
            f"cannot write {str(path)!r}: folder {str(path.parent)!r} is missing"
        )
    ok = o3d.io.write_triangle_mesh(
        str(path), mesh, write_ascii=False, write_vertex_normals=True, write_vertex_colors=True
    )
    if not ok:
        raise SurfaceWriteError(f"Open3D could not write the mesh to {str(path)!r}")
    return path
