"""LegacySurfaceModel (legacy.py): merge -> fit (exact or sparse) -> narrow-band field -> mesh."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import scipy.linalg
from threadpoolctl import threadpool_limits

from groundstation.errors import ConvergenceWarning, NotFittedError
from groundstation.mapping.legacy import LegacySurfaceModel as SurfaceModel
from groundstation.mapping.settings import MappingSettings, SurfaceSettings

assert scipy.linalg

CENTER = np.array([1.5, 1.5, 1.0])
SURFACE = SurfaceSettings(region_min=(0.0, 0.0, 0.0), region_max=(3.0, 3.0, 2.0), spacing=0.05)


@pytest.fixture(autouse=True, scope="module")
def _single_thread_blas():
    with threadpool_limits(1):
        yield


def sphere_session(n_strokes=30, per_stroke=12, n_free=120, n_false=5, seed=0):
    """Contacts on a 0.6 m sphere in 25 Hz strokes (near-duplicates), internal points 0.1 m in,
    free-space points, and ``n_false`` false contacts; returns X, y, ids, t_ns, false ids."""
    rng = np.random.default_rng(seed)
    C = []
    for _ in range(n_strokes):
        a = rng.standard_normal(3)
        a /= np.linalg.norm(a)
        b = np.cross(a, rng.standard_normal(3))
        b /= np.linalg.norm(b)
        ang = np.linspace(0.0, 0.25, per_stroke)
        C.append(np.cos(ang)[:, None] * a + np.sin(ang)[:, None] * b)
    N = np.concatenate(C)
    C = CENTER + (0.6 + 0.005 * rng.standard_normal(N.shape[0]))[:, None] * N
    E = rng.standard_normal((n_free, 3))
    E = CENTER + rng.uniform(0.9, 1.3, n_free)[:, None] * E / np.linalg.norm(E, axis=1)[:, None]
    # False contacts in free space, each beside a free-space point that contradicts it.
    F = CENTER + 0.95 * (E[:n_false] - CENTER)
    X = np.vstack([C, F, C - 0.1 * N, E])
    nc = C.shape[0] + n_false
    y = np.r_[np.zeros(nc), -np.ones(C.shape[0]), np.ones(n_free)]
    t = np.r_[np.arange(nc), np.arange(C.shape[0]), np.linspace(0, nc, n_free)] * 40_000_000
    order = np.argsort(t, kind="stable")
    ids = np.arange(X.shape[0], dtype=np.int64) + 1000
    false_ids = ids[C.shape[0] : nc]
    return X[order], y[order], ids[order], t[order].astype(np.int64), false_ids


def fit(model: SurfaceModel, *args) -> SurfaceModel:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        return model.fit(*args)


@pytest.mark.parametrize("budget", [2000, 500, 60])
def test_default_pipeline_merges_flags_and_meshes_the_sphere(budget: int) -> None:
    X, y, ids, t, false_ids = sphere_session()
    model = SurfaceModel(
        MappingSettings(exact_budget=budget, merge_min_raw=min(budget, 1000), n_inducing=150),
        SURFACE,
    )
    fit(model, X, y, ids, t)
    assert model.mode_ == ("sparse" if budget == 60 else "exact")
    assert model.n_raw_ == X.shape[0]
    if budget == 2000:  # 845 raw rows, merge_min_raw 1000: nothing is merged
        assert model.n_train_ == X.shape[0]
    else:
        assert model.n_train_ < 0.7 * X.shape[0]
    assert set(model.timings_) == {"merge_s", "fit_s"}
    # u for every raw id; the false contacts are the suspects.
    by_id = model.uncertainty_by_id()
    assert np.array_equal(np.sort(by_id.ids), np.sort(ids)) and by_id.u.shape == ids.shape
    assert set(false_ids) <= set(model.suspect_ids_.tolist())
    u_false = by_id.u[np.isin(by_id.ids, false_ids)]
    contacts = (y == 0) & ~np.isin(ids, false_ids)
    # Sparse (M = 150 for ~200 radius-merged cells): ~9x measured, exact: > 10x.
    ratio = 5 if budget == 60 else 10
    assert u_false.min() > ratio * np.median(by_id.u[np.isin(by_id.ids, ids[contacts])])
    mesh = model.mesh()
    assert {"field_s", "mesh_s"} <= set(model.timings_)
    assert not mesh.is_empty and mesh.std is not None and mesh.std.shape == (len(mesh.vertices),)
    r = np.linalg.norm(mesh.vertices - CENTER, axis=1)
    assert np.median(np.abs(r - 0.6)) < 0.05
    # The zero level passes through the trusted contacts (not a point between strokes).
    mean = model.predict(X[contacts])
    assert np.median(np.abs(mean)) < 0.2 and np.percentile(np.abs(mean), 90) < 0.4


def test_refit_warm_starts_and_keeps_suspects_apart_from_new_trusted_contacts() -> None:
    X, y, ids, t, false_ids = sphere_session()
    # budget below the 845 raw rows: the merged path (the one that could mix suspects in)
    model = fit(SurfaceModel(MappingSettings(merge_min_raw=500), SURFACE), X, y, ids, t)
    cold_iter = model.fit_.n_iter_
    assert set(false_ids) <= set(model.suspect_ids_.tolist())
    # New trusted-looking contacts right next to a suspect arrive later.
    fx = X[np.isin(ids, false_ids)][0]
    X2 = np.vstack([X, fx + [[0.002, 0.0, 0.0], [0.0, 0.002, 0.0]]])
    y2 = np.r_[y, 0.0, 0.0]
    ids2 = np.r_[ids, 99_001, 99_002]
    t2 = np.r_[t, t.max() + 1, t.max() + 2]
    est = model.fit_
    fit(model, X2, y2, ids2, t2)
    assert model.fit_ is est and model.fit_.n_iter_ < cold_iter  # warm refit
    ts = model.training_set_
    sus = np.isin(ts.ids, false_ids)
    for mem in ts.members:
        assert sus[mem].all() or not sus[mem].any()


def test_no_merge_and_gpis_modes_and_unfitted_errors() -> None:
    X, y, ids, t, _ = sphere_session(n_strokes=10, n_free=40, n_false=0)
    model = SurfaceModel(MappingSettings(merge=False, model="gpis"), SURFACE)
    with pytest.raises(NotFittedError):
        model.mesh()
    with pytest.raises(NotFittedError):
        model.uncertainty_by_id()
    fit(model, X, y)
    assert model.n_train_ == X.shape[0] and model.mode_ == "exact"
    assert model.uncertainty_by_id().u.shape == (X.shape[0],)


def test_merging_waits_for_the_exact_budget() -> None:
    """Up to merge_min_raw raw rows every one is fitted (merging would drop the free-space points
    that refute false contacts); above it the set is merged."""
    X, y, ids, t, _ = sphere_session(n_strokes=10, n_free=60, n_false=0)
    n = X.shape[0]
    small = fit(SurfaceModel(MappingSettings(merge_min_raw=n), SURFACE), X, y, ids, t)
    assert small.n_train_ == n and small._merger is None
    big = fit(SurfaceModel(MappingSettings(merge_min_raw=n - 1), SURFACE), X, y, ids, t)
    assert big.n_train_ < n and big.training_set_.counts.sum() == n


def test_confident_part_drops_faces_far_from_the_data() -> None:
    X, y, ids, t, _ = sphere_session(n_false=0)
    surface = SurfaceSettings(
        region_min=(0.0, 0.0, 0.0), region_max=(3.0, 3.0, 2.0), spacing=0.05, region_margin=1.5
    )
    full = fit(SurfaceModel(MappingSettings(), surface), X, y, ids, t).mesh()
    cut_settings = SurfaceSettings(**{**surface.__dict__, "max_std_fraction": 0.5})
    model = fit(SurfaceModel(MappingSettings(), cut_settings), X, y, ids, t)
    cut = model.mesh()
    limit = 0.5 * np.sqrt(model.fit_.signal_var_)
    assert 0 < len(cut.faces) <= len(full.faces)
    assert np.all(cut.std[cut.faces].max(axis=1) <= limit)
    assert cut.faces.max() < len(cut.vertices) and len(np.unique(cut.faces)) == len(cut.vertices)
    r = np.linalg.norm(cut.vertices - CENTER, axis=1)
    assert np.median(np.abs(r - 0.6)) < 0.05  # the sphere itself stays


def test_settings_validate_new_fields() -> None:
    with pytest.raises(ValueError, match="exact_budget"):
        MappingSettings(exact_budget=1)
    with pytest.raises(ValueError, match="merge_voxel_factor"):
        MappingSettings(merge_voxel_factor=0.0)
    with pytest.raises(ValueError, match="coarse_factor"):
        SurfaceSettings(coarse_factor=3)
    with pytest.raises(ValueError, match="region_margin"):
        SurfaceSettings(region_margin=-1.0)


def test_refits_freeze_the_merge_radius_and_revisits_add_no_cells() -> None:
    X, y, ids, t, _ = sphere_session(n_free=60, n_false=0)
    model = fit(SurfaceModel(MappingSettings(merge_min_raw=500), SURFACE), X, y, ids, t)
    merger, n0 = model._merger, model.n_train_
    # The same strokes flown again (new ids, new noise, later times): no new cells.
    rng = np.random.default_rng(7)
    X2 = np.vstack([X, X + 0.003 * rng.standard_normal(X.shape)])
    y2 = np.r_[y, y]
    ids2 = np.r_[ids, ids + 100_000]
    t2 = np.r_[t, t + t.max() + 1]
    fit(model, X2, y2, ids2, t2)
    assert model._merger is merger  # radius frozen (hysteresis): no full re-merge
    assert model.n_raw_ == 2 * X.shape[0]
    assert model.n_train_ <= n0 + 0.05 * n0
    assert model.training_set_.counts.sum() == X2.shape[0]


def test_a_high_noise_fit_does_not_flag_every_contact() -> None:
    X, y, ids, t, _ = sphere_session(n_false=0)
    # suspect_u far below every u: only the suspect_ratio x median rule can hold flags back.
    model = fit(SurfaceModel(MappingSettings(suspect_u=1e-12), SURFACE), X, y, ids, t)
    contacts = np.sum(y == 0)
    assert model.suspect_ids_.size < 0.1 * contacts
