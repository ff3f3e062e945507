"""Grid, chunked field evaluation and zero-level-set extraction (2D contours, 3D meshes)."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.mapping.grid import Grid, GridError, evaluate_field, rows_per_chunk
from groundstation.mapping.surface import (
    SurfaceMesh,
    extract_contours,
    extract_surface,
    std_colors,
    to_open3d,
    weld_lattice,
    write_ply,
)

# Marching cubes/squares interpolate linearly between grid points; on a smooth signed distance
# the vertices sit within a small fraction of the spacing of the true surface.
TOL_FRACTION = 0.05


def sdf_predict(center: np.ndarray, radius: float):
    """A 'model' whose mean is the signed distance to a sphere/circle, std = distance to centre."""
    calls: list[int] = []

    def predict(Xq: np.ndarray, return_std: bool = False):
        calls.append(len(Xq))
        r = np.linalg.norm(Xq - center, axis=1)
        return (r - radius, r.copy()) if return_std else r - radius

    predict.calls = calls  # type: ignore[attr-defined]
    return predict


def test_grid_from_bounds_counts_and_order():
    g = Grid.from_bounds((-1.0, 0.0, 2.0), (1.0, 0.5, 2.2), 0.1)
    assert g.shape == (21, 6, 3)
    pts = g.points()
    assert pts.shape == (21 * 6 * 3, 3)
    np.testing.assert_allclose(pts[0], [-1.0, 0.0, 2.0])
    np.testing.assert_allclose(pts[-1], g.region_max)
    np.testing.assert_allclose(g.region_max, [1.0, 0.5, 2.2])
    # C order with ij indexing: reshape gives value[i, j, k] at point (i, j, k).
    i, j, k = 4, 2, 1
    np.testing.assert_allclose(
        pts.reshape(*g.shape, 3)[i, j, k], g.origin + 0.1 * np.array([i, j, k])
    )
    np.testing.assert_allclose(g.points(5, 9), pts[5:9])


@pytest.mark.parametrize(
    ("lo", "hi", "spacing"),
    [((0, 0), (1,), 0.1), ((0, 0), (0, 1), 0.1), ((0, 0), (1, 1), 0.0), ((0, 0), (1, 1), 5.0)],
)
def test_grid_rejects_bad_definitions(lo, hi, spacing):
    with pytest.raises(GridError):
        Grid.from_bounds(lo, hi, spacing)


def test_chunked_evaluation_equals_unchunked_and_bounds_chunks():
    g = Grid.from_bounds((-1, -1, -1), (1, 1, 1), 0.05)
    pred = sdf_predict(np.array([0.1, 0.0, -0.05]), 0.6)
    whole = evaluate_field(pred, g, return_std=True, chunk_mb=1e6, n_train=1)
    assert pred.calls == [g.size]
    pred.calls.clear()
    small = evaluate_field(pred, g, return_std=True, chunk_mb=0.5, n_train=500)
    rows = rows_per_chunk(0.5, 500, 3)
    assert len(pred.calls) == -(-g.size // rows) > 1
    assert max(pred.calls) == rows
    np.testing.assert_array_equal(small.mean, whole.mean)
    np.testing.assert_array_equal(small.std, whole.std)


def test_memory_budget_for_paper_grid():
    # 5.4e5 grid points with n = 2700: one call must hold at most the budget.
    rows = rows_per_chunk(64.0, 2700, 3)
    assert rows * 3 * 2700 * 8 <= 64 * 2**20
    assert rows > 100


def test_evaluation_rejects_bad_predict_output():
    g = Grid.from_bounds((0, 0), (1, 1), 0.25)
    with pytest.raises(GridError, match="non-finite"):
        evaluate_field(lambda X, return_std: np.full(len(X), np.nan), g)
    with pytest.raises(GridError, match="values for"):
        evaluate_field(lambda X, return_std: np.zeros(len(X) + 1), g)


def test_sphere_mesh_vertices_on_true_radius_with_outward_normals():
    spacing, radius, center = 0.05, 0.7, np.array([0.2, -0.1, 0.05])
    g = Grid.from_bounds((-1, -1, -1), (1.2, 1, 1), spacing)
    f = evaluate_field(sdf_predict(center, radius), g, return_std=True)
    mesh = extract_surface(f.mean, g, std=f.std)
    assert mesh.faces.shape[0] > 1000
    rel = mesh.vertices - center
    r = np.linalg.norm(rel, axis=1)
    assert np.max(np.abs(r - radius)) < TOL_FRACTION * spacing
    # Outward unit normals; std interpolated at the vertices (std field = |x - c| ~ radius).
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-9)
    assert np.min(np.sum(mesh.normals * rel / r[:, None], axis=1)) > 0.95
    assert np.max(np.abs(mesh.std - radius)) < 0.01
    # Faces wound counter-clockwise seen from outside: face normals point outwards.
    a, b, c = (mesh.vertices[mesh.faces[:, i]] for i in range(3))
    fn = np.cross(b - a, c - a)
    assert np.mean(np.sum(fn * ((a + b + c) / 3 - center), axis=1) > 0) > 0.99


def test_no_zero_crossing_gives_empty_mesh_and_contours():
    g3 = Grid.from_bounds((0, 0, 0), (1, 1, 1), 0.1)
    mesh = extract_surface(np.ones(g3.shape), g3, std=np.ones(g3.shape))
    assert mesh.is_empty and mesh.vertices.shape == (0, 3) and mesh.std.shape == (0,)
    assert extract_surface(-np.ones(g3.shape), g3).is_empty
    g2 = Grid.from_bounds((0, 0), (1, 1), 0.1)
    assert extract_contours(np.full(g2.shape, 0.5), g2) == []


def test_surface_rejects_wrong_shape_and_nan():
    g = Grid.from_bounds((0, 0, 0), (1, 1, 1), 0.1)
    with pytest.raises(GridError, match="shape"):
        extract_surface(np.zeros((3, 3, 3)), g)
    bad = np.zeros(g.shape)
    bad[1, 1, 1] = np.nan
    with pytest.raises(GridError, match="non-finite"):
        extract_surface(bad, g)
    with pytest.raises(GridError, match="2D"):
        extract_contours(np.zeros(g.shape), g)


def test_circle_contour_on_true_radius():
    spacing, radius, center = 0.02, 0.8, np.array([-0.3, 0.25])
    g = Grid.from_bounds((-1.5, -1.5), (1.5, 1.5), spacing)
    f = evaluate_field(sdf_predict(center, radius), g)
    contours = extract_contours(f.mean, g)
    assert len(contours) == 1
    c = contours[0]
    np.testing.assert_allclose(c[0], c[-1])  # closed
    assert np.max(np.abs(np.linalg.norm(c - center, axis=1) - radius)) < TOL_FRACTION * spacing
    # Covers the whole circle: every direction within one grid step.
    ang = np.sort(np.arctan2(c[:, 1] - center[1], c[:, 0] - center[0]))
    assert np.max(np.diff(np.concatenate([ang, [ang[0] + 2 * np.pi]]))) < 2 * spacing / radius


def test_std_colors_documented_range():
    colors, rng = std_colors(np.array([0.0, 0.5, 1.0, 2.0]), (0.0, 1.0))
    assert rng == (0.0, 1.0) and colors.shape == (4, 3)
    np.testing.assert_allclose(colors[2], colors[3])  # clipped at the top of the range
    assert not np.allclose(colors[0], colors[1])


def test_ply_roundtrip_keeps_vertices_and_colours(tmp_path):
    import open3d as o3d

    g = Grid.from_bounds((-1, -1, -1), (1, 1, 1), 0.1)
    f = evaluate_field(sdf_predict(np.zeros(3), 0.6), g, return_std=True)
    mesh = extract_surface(f.mean, g, std=f.std - 0.55)  # std varies 0.04..0.06 on the sphere
    o3 = to_open3d(mesh, std_range=(0.04, 0.06))
    assert o3.has_vertex_normals() and o3.has_vertex_colors()
    path = write_ply(o3, tmp_path / "sphere.ply")
    back = o3d.io.read_triangle_mesh(str(path))
    assert len(back.vertices) == len(mesh.vertices)
    assert len(back.triangles) == len(mesh.faces)
    np.testing.assert_allclose(np.asarray(back.vertices), mesh.vertices, atol=1e-6)
    # PLY stores colours as 8-bit channels.
    np.testing.assert_allclose(
        np.asarray(back.vertex_colors), np.asarray(o3.vertex_colors), atol=1 / 255
    )
    assert np.ptp(np.asarray(back.vertex_colors)) > 0.1


def test_write_ply_missing_folder(tmp_path):
    from groundstation.mapping.surface import SurfaceWriteError

    with pytest.raises(SurfaceWriteError, match="missing"):
        write_ply(SurfaceMesh.empty(), tmp_path / "nope" / "x.ply")


def test_meshes_of_grids_sharing_a_plane_weld_into_the_one_grid_mesh():
    """Two grids on one lattice (spacing 0.05 m) meeting at x = 0.5 mesh a tilted plane (through
    no lattice point); welded, their union has the vertices and faces of the mesh of one grid
    over both, at its places."""
    s = 0.05

    def field(grid):
        p = grid.points()
        return (p[:, 0] + 0.3 * p[:, 1] - 0.2 * p[:, 2] - 0.6237).reshape(grid.shape)

    a = Grid.from_bounds((0.0, 0.0, 0.0), (0.5, 1.0, 1.0), s)
    b = Grid.from_bounds((0.5, 0.0, 0.0), (1.0, 1.0, 1.0), s)
    whole = Grid.from_bounds((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), s)
    ma, mb = extract_surface(field(a), a), extract_surface(field(b), b)
    joined = SurfaceMesh(
        np.vstack([ma.vertices, mb.vertices]),
        np.vstack([ma.faces, mb.faces + len(ma.vertices)]),
        np.vstack([ma.normals, mb.normals]),
    )
    one = extract_surface(field(whole), whole)
    welded = weld_lattice(joined, s)
    assert len(joined.vertices) > len(one.vertices)  # the shared plane's vertices, twice
    assert len(welded.vertices) == len(one.vertices) and len(welded.faces) == len(one.faces)
    order = lambda v: v[np.lexsort(v.T)]  # noqa: E731
    np.testing.assert_allclose(order(welded.vertices), order(one.vertices), atol=1e-9)
    assert weld_lattice(one, s) is one  # nothing to weld
    with pytest.raises(GridError):
        weld_lattice(joined, 0.0)


def test_weld_keys_lattices_too_wide_for_one_int64_by_rows():
    # vertices 4e6 lattice steps apart on every axis: the edge keys do not fit one int64, and
    # the row-wise path must give the same weld (the two copies of one edge's vertex become one)
    s = 0.05
    v = np.array([[0.0125, 0.0, 0.0], [0.0126, 0.0, 0.0], [2e5, 2e5, 2e5 + 0.01], [0.0, 0.05, 0.0]])
    mesh = SurfaceMesh(v, np.array([[0, 2, 3], [1, 2, 3]]), np.tile([0.0, 0.0, 1.0], (4, 1)))
    welded = weld_lattice(mesh, s)
    assert len(welded.vertices) == 3 and welded.faces.max() == 2
    np.testing.assert_allclose(welded.vertices[np.argmin(welded.vertices[:, 1])], [0.01255, 0, 0])
