"""The pareto bench: metrics on meshes whose answer is known, measuring, and small end-to-end
runs with the real models."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest
from tqdm import tqdm

from groundstation.bench import pareto, scenes3d
from groundstation.cli import bench as cli_bench
from groundstation.errors import ConfigError
from groundstation.mapping.grid import Grid
from groundstation.mapping.surface import extract_surface


def _bar():
    return tqdm(disable=True)


@pytest.fixture(scope="module")
def small_set() -> scenes3d.ObservationSet3D:
    return scenes3d.paper3d(3, n_contacts=200, n_external=100, n_truth=5000)


def _truth_mesh(data: scenes3d.ObservationSet3D, shift: float = 0.0):
    """The scene's own zero level set (optionally grown by ``shift`` metres)."""
    sc = data.scene
    grid = Grid.from_bounds(sc.region_min, sc.region_max, 0.03)
    sdf = data.sdf(grid.points()).reshape(grid.shape) - shift
    return extract_surface(sdf, grid)


def test_pareto_front_keeps_only_non_dominated_points():
    pts = [(1.0, 5.0), (2.0, 3.0), (3.0, 4.0), (0.5, 9.0), (2.0, 3.0), (None, 0.1), (4.0, None)]
    assert pareto.pareto_front(pts) == [True, True, False, True, True, False, False]


def test_peak_rss_sees_a_large_allocation():
    with pareto.PeakRSS() as mem:
        block = np.ones(25_000_000)  # 200 MB, touched
        block[::4096] += 1.0
    assert mem.peak_mb > 150
    del block


def test_surface_metrics_of_the_true_surface_and_of_a_displaced_one(small_set):
    exact = pareto.surface_metrics(_truth_mesh(small_set), small_set)
    assert exact["chamfer_near"] < 0.02
    assert exact["missing"] < 0.01 and exact["phantom_share"] == 0.0
    assert exact["phantom_max_patch_m2"] == 0.0
    # Grown by 0.2 m everywhere: all of it is phantom and the touched surface is missing.
    grown = pareto.surface_metrics(_truth_mesh(small_set, 0.2), small_set)
    assert grown["missing"] > 0.95 and grown["phantom_share"] > 0.95
    assert grown["phantom_max_patch_m2"] > 1.0
    assert grown["chamfer_near"] > 0.15
    assert pareto.surface_metrics(None, small_set)["missing"] == 1.0


def test_flag_metrics_count_events_not_rows(small_set):
    d = small_set
    false = d.kind == scenes3d.FALSE_CONTACT
    cluster_events = set(d.event[false & d.cluster].tolist())
    touch_events = sorted(set(d.event[d.kind == scenes3d.CONTACT].tolist()))
    assert cluster_events and touch_events
    flagged = cluster_events | {touch_events[0]}
    m = pareto.flag_metrics(flagged, d)
    assert m["cluster_flagged"] == 1.0 and m["isolated_flagged"] == 0.0
    assert m["touch_flagged"] == pytest.approx(1 / len(touch_events))


def test_refit_summary_and_render(tmp_path):
    refits = [
        {"method": m, "t_s": 30.0 * k, "n_raw": 100 * k, "total_s": s * k, "fit_s": 0.1,
         "mesh_s": 0.1, "n_train": 50, "covered": k > 2}
        for m, s in ((pareto.DEFAULT, 0.1), (pareto.LEGACY, 1.0)) for k in range(1, 6)
    ]  # fmt: skip
    summary = pareto.refit_summary(refits)
    assert summary[pareto.LEGACY]["median_s"] == pytest.approx(3.0)
    assert summary[pareto.DEFAULT]["covered_median_s"] == pytest.approx(0.4)
    assert summary[pareto.DEFAULT]["refits"] == 5
    rows = [
        {"method": pareto.DEFAULT, "set": "full", "status": "ok", "total_s": 2.0,
         "chamfer_near": 0.02, "missing": 0.01},
        {"method": pareto.DEFAULT, "set": "clean", "status": "ok", "total_s": 1.5,
         "chamfer_near": 0.019, "missing": 0.01},
        {"method": "gpis", "set": "full", "status": "error: ValueError: boom"},
    ]  # fmt: skip
    text = pareto.render(rows, summary, "a note")
    assert "a note" in text and "error: ValueError: boom" in text and "| 20.0 |" in text
    pareto.plot_pareto(rows, tmp_path / "p.png")
    pareto.plot_refits(refits, 60.0, tmp_path / "r.png")
    assert (tmp_path / "p.png").stat().st_size > 0 and (tmp_path / "r.png").stat().st_size > 0


@pytest.mark.timeout(600)
def test_run_paper3d_measures_each_method_and_the_clean_control(small_set):
    rows = pareto.run_paper3d(small_set, ("gpis", pareto.DEFAULT), 0.08, _bar())
    assert [(r["method"], r["set"]) for r in rows] == [
        ("gpis", "full"), (pareto.DEFAULT, "full"), (pareto.DEFAULT, "clean")]  # fmt: skip
    assert len(rows) == pareto.count_points(("gpis", pareto.DEFAULT))
    for r in rows:
        assert r["status"] == "ok", r
        for key in ("total_s", "chamfer_near", "missing", "phantom_share", "peak_mb"):
            assert r[key] is not None and math.isfinite(r[key]) and r[key] >= 0, (r, key)
    clean = rows[2]
    assert clean["n_raw"] < rows[1]["n_raw"]
    assert clean["cluster_flagged"] is None  # no false contacts in the control
    json.dumps(rows, default=pareto.json_default, allow_nan=False)


@pytest.mark.timeout(300)
def test_refit_session_on_a_short_session():
    obs = scenes3d.session40(1, duration_s=40.0, n_truth=2000)
    refits = pareto.refit_session(obs, 20.0, _bar())
    by = {m: [r for r in refits if r["method"] == m] for m in (pareto.DEFAULT, pareto.LEGACY)}
    for rs in by.values():
        assert [r["t_s"] for r in rs] == [20.0, 40.0]
        assert rs[0]["n_raw"] < rs[1]["n_raw"] == len(obs.y)
        for r in rs:
            assert math.isfinite(r["total_s"]) and r["total_s"] >= 0
        final = rs[-1]["final"]  # the session's last map is scored
        assert "final" not in rs[0] and 0.0 <= final["missing"] <= 1.0
        assert final["chamfer_near"] is not None and final["phantom_max_patch_m2"] >= 0.0
    summary = pareto.refit_summary(refits)
    assert summary[pareto.DEFAULT]["final"] == by[pareto.DEFAULT][-1]["final"]
    assert "The map each ends the session with" in pareto.render([], summary, "")


def test_cli_refuses_unknown_scenes_and_methods(tmp_path):
    base = dict(out=str(tmp_path), quick=True, refit_every=None, seed=0)
    with pytest.raises(ConfigError, match="moon"):
        cli_bench.run_pareto(argparse.Namespace(scenes="moon", methods="gpis", **base))
    with pytest.raises(ConfigError, match="magic"):
        cli_bench.run_pareto(argparse.Namespace(scenes="paper3d", methods="magic", **base))
    with pytest.raises(ConfigError, match="refit-every"):
        cli_bench.run_pareto(
            argparse.Namespace(scenes="session40", methods="gpis", **base | {"refit_every": 0.0})
        )


@pytest.mark.soak
@pytest.mark.timeout(3600)
def test_cli_quick_all_scenes(tmp_path):
    methods = ",".join(pareto.METHODS)
    args = argparse.Namespace(
        out=str(tmp_path), quick=True, scenes="paper3d,session40", methods=methods,
        refit_every=None, seed=0,
    )  # fmt: skip
    assert cli_bench.run_pareto(args) == 0
    for name in ("pareto.png", "pareto.md", "results.json", "refit_vs_session.png"):
        assert (tmp_path / name).stat().st_size > 0
    res = json.loads((tmp_path / "results.json").read_text())
    assert all(r["status"] == "ok" for r in res["paper3d"]), res["paper3d"]
