"""Test scenes for the viewer: a marching-cubes sphere from the real meshing code, contacts on
it, a fit flagging some of them, and a circular flight around it."""

from __future__ import annotations

import numpy as np

from groundstation.mapping.grid import Grid
from groundstation.mapping.surface import SurfaceMesh, extract_surface
from groundstation.viewer.scene import ViewModel, ViewSettings

CENTER = np.array([0.0, 0.0, 1.0])
RADIUS = 0.6


def sphere_mesh(radius: float = RADIUS, spacing: float = 0.05) -> SurfaceMesh:
    """Sphere of ``radius`` around :data:`CENTER`; std grows with x (0.05 .. 0.15)."""
    g = Grid.from_bounds((-1, -1, 0), (1, 1, 2), spacing)
    P = g.points().reshape(*g.shape, 3)
    sdf = np.linalg.norm(P - CENTER, axis=-1) - radius
    std = 0.05 + 0.05 * (P[..., 0] + 1)
    return extract_surface(sdf, g, std=std)


def contact_points(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    return CENTER + RADIUS * d / np.linalg.norm(d, axis=1, keepdims=True)


def circle_pose(k: int, dt_ns: int = 20_000_000) -> tuple[int, np.ndarray, np.ndarray]:
    """(t_ns, position (3,), q_wxyz (4,)) of pose ``k`` flying around the sphere."""
    a = 0.05 * k
    p = CENTER + np.array([1.2 * np.cos(a), 1.2 * np.sin(a), 0.2 * np.sin(3 * a)])
    q = np.array([np.cos(a / 2), 0.0, 0.0, np.sin(a / 2)])
    return k * dt_ns, p, q


def populated_model(settings: ViewSettings | None = None, n_contacts: int = 40) -> ViewModel:
    """A model with a mesh, ``n_contacts`` contacts (ids 0..), internal points (ids 1000..),
    a fit over the first 30 contacts flagging every 7th, and 200 poses."""
    vm = ViewModel(settings)
    for i, x in enumerate(contact_points(n_contacts)):
        vm.ingest_observation(i, 0, x)
        vm.ingest_observation(1000 + i, -1, CENTER + 0.8 * (x - CENTER))
    ids = np.arange(30)
    vm.ingest_fit(ids, np.ones(30), (ids % 7 == 0).astype(np.uint8), fit_index=3)
    for k in range(200):
        vm.ingest_pose(*circle_pose(k))
    m = sphere_mesh()
    vm.ingest_mesh(m.vertices, m.faces, m.std, fit_index=3, stamp_ns=0)
    return vm
