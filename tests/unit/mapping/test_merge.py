"""Observation budget (merge.py): the per-voxel merge rule, suspects kept apart, the store."""

from __future__ import annotations

import numpy as np
import pytest

from groundstation.errors import InputDataError
from groundstation.mapping.merge import (
    ObservationStore,
    StreamingMerger,
    merge_observations,
    radius_merge,
)


def wall_slide(n=400, seed=0):
    """25 Hz contacts sliding along the wall x = 1.03 (near-duplicates), plus internal points."""
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 2.0, n)
    C = np.c_[np.full(n, 1.03), s, 0.55 + 0.002 * rng.standard_normal(n)]
    Xi = C - [0.1, 0.0, 0.0]
    X = np.vstack([C, Xi])
    y = np.r_[np.zeros(n), -np.ones(n)]
    t = np.r_[np.arange(n), np.arange(n)] * 40_000_000
    ids = np.arange(2 * n, dtype=np.int64)
    return X, y, ids, t.astype(np.int64)


def test_near_duplicates_merge_per_label_with_counts_mean_and_most_recent_id() -> None:
    X, y, ids, t = wall_slide()
    ts = merge_observations(X, y, ids, t, voxel_m=0.1)
    assert len(ts) < 0.1 * X.shape[0]  # ~20 voxels per label instead of 400 rows
    assert ts.counts.sum() == X.shape[0]
    for j in range(len(ts)):
        mem = ts.members[j]
        assert np.all(y[mem] == ts.y[j])  # labels never mixed
        np.testing.assert_allclose(ts.X[j], X[mem].mean(axis=0))
        assert ts.rep_ids[j] == ids[mem][np.argmax(t[mem])]
        assert np.all(ts.cell_of[mem] == j)
        keys = np.floor(X[mem] / 0.1)
        assert np.all(keys == keys[0])  # one voxel per cell
    # Cells are ordered by their first member's time.
    first = np.array([t[m].min() for m in ts.members])
    assert np.all(np.diff(first) >= 0)


def test_external_points_use_the_coarser_voxel() -> None:
    rng = np.random.default_rng(1)
    X = rng.uniform(0, 1, (200, 3))
    y = np.ones(200)
    y[:2] = 0.0
    fine = merge_observations(X, y, np.arange(200), np.arange(200), 0.1)
    coarse = merge_observations(X, y, np.arange(200), np.arange(200), 0.1, external_voxel_m=0.5)
    assert len(coarse) < len(fine)
    assert np.sum(coarse.y == 1.0) <= 8  # 2 x 2 x 2 voxels of 0.5 m
    assert np.sum(coarse.y == 0.0) == np.sum(fine.y == 0.0)


@pytest.mark.parametrize("seed", range(5))
def test_no_suspect_is_merged_into_a_trusted_cell_and_vice_versa(seed: int) -> None:
    X, y, ids, t = wall_slide(seed=seed)
    rng = np.random.default_rng(seed)
    # False contacts in the same voxels as true ones (the hard case) and some in free space.
    contacts = np.flatnonzero(y == 0)
    suspects = rng.choice(ids[contacts], size=25, replace=False)
    ts = merge_observations(X, y, ids, t, voxel_m=0.1, suspects=suspects)
    is_sus = np.isin(ids, suspects)
    for j, mem in enumerate(ts.members):
        flags = is_sus[mem]
        assert flags.all() or not flags.any(), f"cell {j} mixes suspects and trusted rows"
        assert ts.suspect[j] == flags[0]
    # Every suspect still lands in a cell of suspects only, and nothing was lost.
    assert np.all(ts.suspect[ts.cell_of[is_sus]])
    assert not np.any(ts.suspect[ts.cell_of[~is_sus]])
    assert ts.counts.sum() == X.shape[0]
    # Without suspects those same voxels would have merged them with trusted contacts.
    plain = merge_observations(X, y, ids, t, voxel_m=0.1)
    mixed = [m for m in plain.members if is_sus[m].any() and not is_sus[m].all()]
    assert mixed


def test_cells_keep_their_order_when_the_session_grows() -> None:
    X, y, ids, t = wall_slide(n=400)
    order = np.argsort(t, kind="stable")
    X, y, ids, t = X[order], y[order], ids[order], t[order]
    half = X.shape[0] // 2
    a = merge_observations(X[:half], y[:half], ids[:half], t[:half], 0.1)
    b = merge_observations(X, y, ids, t, 0.1)
    k = len(a)
    # Old cells keep their places (their means may move as members join).
    for j in range(k - 1):
        np.testing.assert_array_equal(b.members[j][: a.counts[j]], a.members[j])


def test_bad_input_is_named() -> None:
    X, y, ids, t = wall_slide(n=10)
    with pytest.raises(InputDataError, match="NaN"):
        merge_observations(np.where(np.arange(20)[:, None] == 3, np.nan, X), y, ids, t, 0.1)
    with pytest.raises(InputDataError, match="ids has"):
        merge_observations(X, y, ids[:-1], t, 0.1)
    with pytest.raises(InputDataError, match="voxel_m"):
        merge_observations(X, y, ids, t, 0.0)
    with pytest.raises(InputDataError, match="integers"):
        merge_observations(X, y, ids.astype(float), t, 0.1)


def test_store_accumulates_merges_and_tracks_suspects() -> None:
    X, y, ids, t = wall_slide(n=200)
    store = ObservationStore(voxel_m=0.1, external_voxel_m=0.5)
    store.add(ids[:150], X[:150], y[:150], t[:150])
    store.add(ids[150:], X[150:], y[150:], t[150:])
    assert store.raw_count == 400
    ts = store.training_set()
    assert store.merged_count == len(ts) < 100
    assert store.training_set() is ts  # cached
    sus = ids[:3]
    store.set_suspects(sus)
    ts2 = store.training_set()
    assert ts2 is not ts
    assert all(np.all(np.isin(ids[m], sus)) == ts2.suspect[j] for j, m in enumerate(ts2.members))
    with pytest.raises(InputDataError, match="unique"):
        store.add(ids[:1], X[:1], y[:1], t[:1])
    with pytest.raises(InputDataError, match="columns"):
        store.add(np.array([10_000]), np.zeros((1, 2)), np.zeros(1), np.zeros(1, np.int64))
    assert store.raw_count == 400


# --------------------------------------------------------------------------- radius merge


def plane_strokes(x0: float, n_strokes: int = 12, per: int = 40, seed: int = 0):
    """25 Hz strokes on the plane x = x0 (noise 3 mm across it) with their internal points."""
    rng = np.random.default_rng(seed)
    P = []
    for _ in range(n_strokes):
        start = rng.uniform([0.0, 0.0], [1.5, 1.5])
        ang = rng.uniform(0.0, 2.0 * np.pi)
        s = np.arange(per) * 0.01
        P.append(start + s[:, None] * [np.cos(ang), np.sin(ang)])
    P = np.concatenate(P)
    n = P.shape[0]
    C = np.c_[x0 + 0.003 * rng.standard_normal(n), P]
    X = np.vstack([C, C - [0.1, 0.0, 0.0]])
    y = np.r_[np.zeros(n), -np.ones(n)]
    t = np.r_[np.arange(n), np.arange(n)].astype(np.int64) * 40_000_000
    order = np.argsort(t, kind="stable")
    return X[order], y[order], np.arange(2 * n, dtype=np.int64)[order], t[order]


def test_a_face_on_a_voxel_boundary_is_not_doubled() -> None:
    X, y, ids, t = plane_strokes(x0=1.0)  # contacts straddle x = 1.0, a 0.1 m voxel boundary
    on = radius_merge(X, y, ids, t, 0.1)
    off = radius_merge(X + [0.05, 0.0, 0.0], y, ids, t, 0.1)  # mid-voxel
    assert len(on) == len(off)
    # One cell per r-neighbourhood: same-label cells are never closer than r to each other's
    # anchor, so their means are spread on the plane, not stacked across it.
    for label in (0.0, -1.0):
        P = on.X[on.y == label]
        d = np.sqrt(((P[:, None, :] - P[None, :, :]) ** 2).sum(-1))
        np.fill_diagonal(d, np.inf)
        assert np.min(d.min(axis=1)) > 0.02
    # The voxel rule splits the straddling face into two layers of cells.
    vox_on = merge_observations(X, y, ids, t, 0.1)
    vox_off = merge_observations(X + [0.05, 0.0, 0.0], y, ids, t, 0.1)
    assert len(vox_on) > 1.4 * len(vox_off)


def test_revisiting_the_same_faces_stops_the_growth_and_streaming_equals_batch() -> None:
    g = np.arange(0.0, 1.5, 0.03)
    yy, zz = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    C = np.c_[np.full(yy.size, 1.0), yy, zz]  # a raster pass covers the face [0, 1.5]^2
    X1 = np.vstack([C, C - [0.1, 0.0, 0.0]])
    y1 = np.r_[np.zeros(yy.size), -np.ones(yy.size)]
    ids1 = np.arange(X1.shape[0], dtype=np.int64)
    t1 = np.r_[np.arange(yy.size), np.arange(yy.size)].astype(np.int64)
    X2, y2, _, t2 = plane_strokes(x0=1.0, n_strokes=60, seed=2)  # revisits it
    inside = np.all((X2[:, 1:] > 0.0) & (X2[:, 1:] < 1.47), axis=1)
    X2, y2, t2 = X2[inside], y2[inside], t2[inside]
    X = np.vstack([X1, X2])
    y = np.r_[y1, y2]
    ids = np.r_[ids1, ids1.max() + 1 + np.arange(len(y2))]
    t = np.r_[t1, t1.max() + 1 + t2]
    merger = StreamingMerger(0.1)
    first = merger.update(X1, y1, ids1, t1)
    both = merger.update(X, y, ids, t)
    assert both.counts.sum() == X.shape[0]
    assert len(both) <= 1.05 * len(first)  # twice the data, (almost) no new cells
    np.testing.assert_array_equal(both.cell_of, radius_merge(X, y, ids, t, 0.1).cell_of)
    # Old cells keep their places as the session grows.
    k = len(first)
    np.testing.assert_array_equal(both.counts[:k] >= first.counts, True)


def test_radius_merge_keeps_suspects_apart_and_clusters_a_gust() -> None:
    X, y, ids, t = plane_strokes(x0=1.0)
    rng = np.random.default_rng(3)
    contacts = ids[y == 0]
    suspects = rng.choice(contacts, size=20, replace=False)  # inside trusted cells
    gust = np.c_[np.full(15, 1.6), 0.7 + 0.01 * rng.standard_normal((15, 2))]
    Xg = np.vstack([X, gust])
    yg = np.r_[y, np.zeros(15)]
    gust_ids = 10_000 + np.arange(15)
    idsg = np.r_[ids, gust_ids]
    tg = np.r_[t, t.max() + 1 + np.arange(15)]
    sus = np.r_[suspects, gust_ids]
    ts = radius_merge(Xg, yg, idsg, tg, 0.1, suspects=sus, suspect_radius_m=0.5)
    is_sus = np.isin(idsg, sus)
    for j, mem in enumerate(ts.members):
        assert is_sus[mem].all() or not is_sus[mem].any()
        assert ts.suspect[j] == is_sus[mem][0]
    assert len(np.unique(ts.cell_of[np.isin(idsg, gust_ids)])) == 1  # one gust, one cell
    assert ts.counts.sum() == Xg.shape[0]


def test_radius_merge_rejects_bad_input() -> None:
    X, y, ids, t = plane_strokes(x0=1.0, n_strokes=1, per=5)
    with pytest.raises(InputDataError, match="radius_m"):
        radius_merge(X, y, ids, t, 0.0)
    with pytest.raises(InputDataError, match="unique"):
        radius_merge(X, y, np.zeros_like(ids), t, 0.1)
    with pytest.raises(InputDataError, match="NaN"):
        radius_merge(np.where(np.arange(10)[:, None] == 2, np.nan, X), y, ids, t, 0.1)
