"""Truth scores of a replay without a mesh (``pipeline/scoring.py``)."""

from __future__ import annotations

import math

from groundstation.pipeline.scoring import surface_scores


def _grid_faces(n):
    """Triangles of an n x n grid of vertices numbered row by row."""
    import numpy as np

    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, i * n + j + 1, (i + 1) * n + j, (i + 1) * n + j + 1
            faces += [[a, b, d], [a, d, c]]
    return np.asarray(faces)


def test_without_a_mesh_all_touched_surface_is_missing_and_an_untouched_flight_misses_none():
    touched = {"contacts": [{"kind": "touch", "point": [1.0, 0.0, 1.0], "start": 3.0}]}
    gusts_only = {"contacts": [{"kind": "gust", "point": None, "start": 3.0}]}
    assert surface_scores(None, touched)["missing_share"] == 1.0
    assert math.isnan(surface_scores(None, gusts_only)["missing_share"])
    assert math.isnan(surface_scores(None, {"contacts": []})["missing_share"])
    assert math.isnan(surface_scores(None, touched)["chamfer_m"])


def test_near_missing_counts_only_the_surface_around_the_touches():
    import numpy as np

    from groundstation.mapping.surface import SurfaceMesh

    # a wall x = 1 (a thin box), touched once at (1, 0, 1); the mesh is a 0.5 m square on the
    # wall around the touch: all of the surface within 0.2 m is there, not all within 0.5 m
    scene = {
        "region": {"min": [-1, -2, 0], "max": [3, 2, 2]},
        "objects": [{"type": "box", "min": [1.0, -2.0, 0.0], "max": [1.2, 2.0, 2.0]}],
    }
    truth = {"scene": scene, "contacts": [{"kind": "touch", "point": [1.0, 0.0, 1.0]}]}
    n = 11
    yy, zz = np.meshgrid(np.linspace(-0.25, 0.25, n), np.linspace(0.75, 1.25, n))
    v = np.column_stack([np.ones(n * n), yy.ravel(), zz.ravel()])
    faces = _grid_faces(n)
    mesh = SurfaceMesh(v, faces, np.tile([-1.0, 0.0, 0.0], (n * n, 1)))
    s = surface_scores(mesh, truth)
    assert s["missing_share_near"] < 0.02
    assert s["missing_share"] > 0.3  # the wall's other face and the disk beyond 0.25 m


def test_a_mesh_on_the_floor_is_real_surface_and_one_below_it_is_phantom():
    import numpy as np

    from groundstation.mapping.surface import SurfaceMesh

    # a 1 m square drawn at height z0 far from the only structure: on the floor (z = 0, the
    # region's bottom, which both engines' drones can touch) it exists; 0.5 m below, it does not
    scene = {
        "region": {"min": [-1, -2, 0], "max": [3, 2, 2]},
        "objects": [{"type": "box", "min": [1.0, -2.0, 0.0], "max": [1.2, 2.0, 2.0]}],
    }
    truth = {"scene": scene, "contacts": [{"kind": "touch", "point": [1.0, 0.0, 1.0]}]}
    n = 11
    xx, yy = np.meshgrid(np.linspace(-0.9, 0.1, n), np.linspace(-1.0, 0.0, n))
    faces = _grid_faces(n)

    def square(z0):
        v = np.column_stack([xx.ravel(), yy.ravel(), np.full(n * n, z0)])
        return SurfaceMesh(v, faces, np.tile([0.0, 0.0, 1.0], (n * n, 1)))

    assert surface_scores(square(0.02), truth)["phantom_max_patch_m2"] == 0.0
    below = surface_scores(square(-0.5), truth)
    assert below["phantom_max_patch_m2"] > 0.9
    (where,) = below["phantom_patches"]  # one patch, listed with where it lies
    assert abs(where["centre"][2] + 0.5) < 1e-9 and where["area_m2"] > 0.9
    assert below["mesh_to_truth_median_m"] > 0.4
