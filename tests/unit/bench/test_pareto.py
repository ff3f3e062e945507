"""The pareto bench: front/ratio logic, measuring, and tiny end-to-end runs with real models."""

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


def _bar():
    return tqdm(disable=True)


def test_pareto_front_keeps_only_non_dominated_points():
    pts = [(1.0, 5.0), (2.0, 3.0), (3.0, 4.0), (0.5, 9.0), (2.0, 3.0), (None, 0.1), (4.0, None)]
    assert pareto.pareto_front(pts) == [True, True, False, True, True, False, False]


def test_ratios_against_the_exact_model():
    rows = [
        {"label": pareto.REFERENCE, "status": "ok", "merge_s": 0.0, "fit_s": 100.0,
         "field_mesh_s": 40.0, "chamfer_near": 0.010, "chamfer": 0.02},
        {"label": pareto.DEFAULT, "status": "ok", "merge_s": 1.0, "fit_s": 9.0,
         "field_mesh_s": 2.0, "chamfer_near": 0.0105, "chamfer": 0.01},
    ]  # fmt: skip
    r = pareto.ratios(rows)
    assert r["fit_speedup"] == pytest.approx(10.0)
    assert r["field_mesh_speedup"] == pytest.approx(20.0)
    assert r["chamfer_ratio"] == pytest.approx(1.05)
    rows[1]["status"] = "error: boom"
    assert pareto.ratios(rows)["fit_speedup"] is None


def test_refit_ratio_uses_the_first_covered_refit():
    refits = [
        {"t_s": 60.0, "n_raw": 10, "total_s": 1.0, "covered": False},
        {"t_s": 120.0, "n_raw": 20, "total_s": 2.0, "covered": True},
        {"t_s": 180.0, "n_raw": 30, "total_s": 3.0, "covered": True},
    ]
    r = pareto.refit_ratio(refits)
    assert r["ratio"] == pytest.approx(1.5) and r["covered_t_s"] == 120.0
    assert pareto.refit_ratio(refits[:2])["ratio"] is None


def test_peak_rss_sees_a_large_allocation():
    with pareto.PeakRSS() as mem:
        block = np.ones(25_000_000)  # 200 MB, touched
        block[::4096] += 1.0
    assert mem.peak_mb > 150
    del block


def test_method_specs_cover_every_configuration_of_the_issue():
    for ndim in (2, 3):
        specs = pareto.method_specs(ndim, quick=False)
        fits = {s.fit for s in specs}
        assert {"gpis", pareto.REFERENCE, pareto.DEFAULT, "sklearn"} <= fits
        assert sum(f.startswith("merge") for f in fits) >= 3
        assert sum(f.startswith("sparse") for f in fits) >= 3
        default_fields = {(s.field, s.spacing) for s in specs if s.fit == pareto.DEFAULT}
        assert len({sp for f, sp in default_fields if f == "dense"}) >= 3
        assert len({sp for f, sp in default_fields if f == "band"}) >= 3
        assert sum(s.label == pareto.DEFAULT for s in specs) == 1


@pytest.mark.timeout(180)
def test_run_scene_measures_every_point_and_shares_fits():
    scene = pareto.scene_2d("square", 1, n_free=200)
    core = pareto._core()
    specs = [
        pareto.PointSpec(pareto.REFERENCE, pareto.REFERENCE, "dense", 0.1),
        pareto.PointSpec("ref band", pareto.REFERENCE, "band", 0.1),
        pareto.PointSpec("merge", "merge0.02", "dense", 0.1, 0.02),
        pareto.PointSpec("sparse", "sparse60", "dense", 0.1, 60),
    ]
    points = pareto.run_scene(scene, specs, core, _bar())
    assert [p["label"] for p in points] == [s.label for s in specs]
    for p in points:
        if core is None and p["label"] != pareto.REFERENCE:
            assert p["status"].startswith("skipped")
            continue
        assert p["status"] == "ok", p
        for key in ("fit_s", "field_s", "mesh_s", "total_s", "Q", "peak_mb"):
            assert p[key] is not None and math.isfinite(p[key]) and p[key] >= 0, (p["label"], key)
        assert p["total_s"] >= p["fit_s"]
    # The two reference points share one fit; the exact robust model finds the square.
    assert points[0]["fit_s"] == points[1]["fit_s"]
    assert points[0]["chamfer"] < 0.03 and points[0]["Q"] < 0.2
    rows = pareto.aggregate(points, "2d")
    assert any(r["pareto"] for r in rows)
    json.dumps(points, default=pareto.json_default, allow_nan=False)


@pytest.mark.timeout(120)
def test_refit_session_on_a_short_session():
    core = pareto._core()
    if core is None:
        pytest.skip("speed core (groundstation.mapping.model) not installed")
    obs = scenes3d.session40(1, duration_s=40.0, n_truth=2000)
    refits = pareto.refit_session(obs, 20.0, core, _bar())
    assert [r["t_s"] for r in refits] == [20.0, 40.0]
    assert refits[0]["n_raw"] < refits[1]["n_raw"] == len(obs.y)
    for r in refits:
        assert r["n_train"] <= r["n_raw"]
        assert all(math.isfinite(r[k]) and r[k] >= 0 for k in ("merge_s", "fit_s", "total_s"))


def test_render_and_charts_from_measured_points(tmp_path):
    def point(label, total, chamfer, scene="s1"):
        return {"scene": scene, "label": label, "fit": label, "field": "dense", "spacing": 0.05,
                "status": "ok", "merge_s": 0.0, "fit_s": total - 1.0, "field_s": 0.8,
                "mesh_s": 0.2, "total_s": total, "chamfer": chamfer, "chamfer_near": chamfer,
                "e": None, "e_near": 0.01, "Q": 0.1, "peak_mb": 10.0, "n_train": 100,
                "grid_spacing": 0.05, "fraction_evaluated": 1.0}  # fmt: skip

    pts = [point(pareto.REFERENCE, 100.0, 0.010), point(pareto.DEFAULT, 5.0, 0.011),
           point("slow and bad", 200.0, 0.5),
           {"scene": "s1", "label": "missing", "fit": "x", "field": "dense", "spacing": 0.05,
            "status": "skipped: no module"}]  # fmt: skip
    rows = pareto.aggregate(pts, "3d")
    assert [r["pareto"] for r in rows] == [True, True, False, False]
    refits = [{"t_s": 60.0 * k, "n_raw": 1000 * k, "n_train": 300, "merge_s": 0.1, "fit_s": 1.0,
               "field_s": 0.2, "mesh_s": 0.1, "total_s": 1.4, "covered": k > 1}
              for k in (1, 2, 3)]  # fmt: skip
    text = pareto.render({"3d": rows}, {"3d": pareto.ratios(rows)}, pareto.refit_ratio(refits),
                         {"note": "test"})  # fmt: skip
    assert f"**{pareto.DEFAULT}** ★" in text and "skipped: no module" in text
    assert "fit speed-up 24.8x" in text and "ratio 1.00 (goal <= 2)" in text
    pareto.plot_pareto({"3d": rows}, tmp_path / "p.png")
    pareto.plot_refits(refits, 2000, tmp_path / "r.png")
    assert (tmp_path / "p.png").stat().st_size > 0 and (tmp_path / "r.png").stat().st_size > 0


@pytest.mark.soak
@pytest.mark.timeout(600)
def test_cli_2d_quick_writes_the_outputs(tmp_path):
    args = argparse.Namespace(out=str(tmp_path), quick=True, scenes="2d", refit_every=None, seed=0)
    assert cli_bench.run_pareto(args) == 0
    for name in ("pareto.png", "pareto.md", "results.json"):
        assert (tmp_path / name).stat().st_size > 0
    res = json.loads((tmp_path / "results.json").read_text())
    rows = {r["label"]: r for r in res["groups"]["2d"]}
    ref = rows[pareto.REFERENCE]
    assert ref["status"] == "ok" and 0 < ref["chamfer"] < 0.02 and ref["Q"] < 0.1
    assert rows["gpis"]["Q"] > 0.5  # GPIS variance does not single out false contacts
    assert "★" in (tmp_path / "pareto.md").read_text()


def test_cli_refuses_unknown_scenes(tmp_path):
    args = argparse.Namespace(out=str(tmp_path), quick=True, scenes="moon", refit_every=None,
                              seed=0)  # fmt: skip
    with pytest.raises(ConfigError, match="moon"):
        cli_bench.run_pareto(args)


@pytest.mark.soak
@pytest.mark.timeout(3600)
def test_cli_quick_all_scenes(tmp_path):
    args = argparse.Namespace(out=str(tmp_path), quick=True, scenes="2d,paper3d,session40",
                              refit_every=None, seed=0)  # fmt: skip
    assert cli_bench.run_pareto(args) == 0
    assert (tmp_path / "refit_vs_session.png").stat().st_size > 0
