"""Cavities (cavities.py): an inward-facing shell inside a structure touched all round is
dropped; the back of a thin wall, with open space or nothing behind it, is kept."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.mapping.cavities import cavity_faces
from groundstation.mapping.grid import Grid
from groundstation.mapping.model import SurfaceModel
from groundstation.mapping.settings import MappingSettings, SurfaceSettings
from groundstation.mapping.surface import extract_surface


def _mesh(field, lo, hi, spacing=0.025):
    grid = Grid.from_bounds(np.asarray(lo, float), np.asarray(hi, float), spacing)
    return extract_surface(field(grid.points()).reshape(grid.shape), grid)


def _sphere_points(n, r, seed=0):
    u = np.random.default_rng(seed).normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return r * u, u


def test_the_hollow_inside_a_ball_touched_all_round_is_a_cavity_and_its_outside_is_not():
    # a ball of radius 0.5 m whose field is positive again inside 0.25 m (what the prior mean
    # does deep inside a solid): two shells, the inner one facing its own centre
    def field(p):
        r = np.linalg.norm(p, axis=1)
        return np.maximum(r - 0.5, 0.25 - r)

    mesh = _mesh(field, (-0.7, -0.7, -0.7), (0.7, 0.7, 0.7))
    touches, normals = _sphere_points(600, 0.5)
    free, _ = _sphere_points(300, 0.9, seed=1)
    drop = cavity_faces(mesh, touches, normals, free, depth_m=0.15)
    r = np.linalg.norm(mesh.vertices[mesh.faces].mean(axis=1), axis=1)
    inner = r < 0.375
    assert inner.any() and (~inner).any()
    assert drop[inner].all() and not drop[~inner].any()


def test_the_back_of_a_thin_wall_is_kept_with_open_space_or_nothing_behind_it():
    # a 0.3 m thick wall (0 < x < 0.3) touched on its front (x = 0.3) only
    def field(p):
        return np.maximum(-p[:, 0], p[:, 0] - 0.3)

    mesh = _mesh(field, (-0.2, 0.0, 0.0), (0.5, 1.0, 1.0))
    rng = np.random.default_rng(2)
    yz = rng.uniform(0.1, 0.9, (200, 2))
    touches = np.column_stack([np.full(200, 0.3), yz])
    normals = np.tile([1.0, 0.0, 0.0], (200, 1))
    cent = mesh.vertices[mesh.faces].mean(axis=1)
    back = cent[:, 0] < 0.05
    assert back.any()
    in_front = np.column_stack([np.full(50, 0.7), rng.uniform(0, 1, (50, 2))])
    behind = np.column_stack([np.full(50, -0.4), rng.uniform(0, 1, (50, 2))])
    for free in (in_front, np.vstack([in_front, behind]), np.zeros((0, 3))):
        assert not cavity_faces(mesh, touches, normals, free, depth_m=0.15).any()


def test_the_model_drops_what_the_rule_names_and_gives_it_the_trusted_touches(monkeypatch):
    import groundstation.mapping.model as model_module
    from tests.unit.mapping.test_surface_model import box_flight

    seen = {}

    def every_face(mesh, contacts, normals, free, *, depth_m):
        seen.update(contacts=contacts, normals=normals, free=free, depth_m=depth_m)
        return np.ones(len(mesh.faces), dtype=bool)

    monkeypatch.setattr(model_module, "cavity_faces", every_face)
    obs = box_flight()  # 25 touches on the face x = 0 (normal +x), one gust at x = 0.9
    kept = SurfaceModel(MappingSettings(), SurfaceSettings(drop_cavities=False))
    kept.fit(obs)
    assert not kept.mesh().is_empty and not seen
    model = SurfaceModel(MappingSettings(), SurfaceSettings())
    model.fit(obs)
    assert model.mesh().is_empty  # every face named is dropped
    assert seen["depth_m"] == pytest.approx(0.15)  # 1.5 internal-point depths
    assert np.all(np.abs(seen["contacts"][:, 0]) < 0.01)  # the touches, not the flagged gust
    n = seen["normals"] / np.linalg.norm(seen["normals"], axis=1, keepdims=True)
    np.testing.assert_allclose(n, np.tile([1.0, 0.0, 0.0], (len(n), 1)), atol=1e-9)
    assert len(seen["contacts"]) >= 25 and np.all(seen["free"][:, 0] > 0.25)
