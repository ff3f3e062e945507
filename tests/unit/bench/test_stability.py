"""The stability bench: planted data of each sweep, one-run classification, breakdown logic."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from groundstation.bench import shapes2d, stability
from groundstation.bench.stability import StabilitySettings
from groundstation.cli import bench as cli_bench
from groundstation.errors import ConfigError

S = StabilitySettings(spacing=0.1)


def test_outlier_rate_sweep_changes_the_number_of_false_pairs():
    few = stability.make_data("outlier_rate", 0.0, 0, S)
    many = stability.make_data("outlier_rate", 0.4, 0, S)
    assert few.counts()["false_contact"] == 0
    assert 140 < many.counts()["false_contact"] < 230  # 40 % of ~460 external samples


def test_gust_is_one_tight_cluster_of_the_requested_size():
    d = stability.make_data("gust_size", 20, 1, S)
    fc = d.X[d.kind == shapes2d.FALSE_CONTACT]
    assert len(fc) == 20 and d.counts()["false_internal"] == 20
    assert np.ptp(fc, axis=0).max() < 0.1
    dist = shapes2d.make_shape("circle").sdf(fc)
    assert 0.2 < dist.mean() < 1.1


@pytest.mark.parametrize("dist", [0.1, 0.3])
def test_near_surface_outliers_sit_at_the_requested_distance(dist):
    d = stability.make_data("near_distance", dist, 2, S)
    fc = d.X[d.kind == shapes2d.FALSE_CONTACT]
    assert len(fc) == 10
    np.testing.assert_allclose(shapes2d.make_shape("circle").sdf(fc), dist, atol=1e-3)


def test_few_contacts_and_exact_duplicates():
    d = stability.make_data("n_contacts", 8, 0, S)
    assert d.counts()["contact"] == 8
    dup = stability.make_data("duplicates", 4, 0, S)
    xc = dup.X[dup.kind == shapes2d.CONTACT]
    assert len(xc) == 480 and len(np.unique(xc, axis=0)) == 120


def test_random_initial_hyperparameters_are_positive_and_deterministic():
    a, b = stability.init_params(3, 0), stability.init_params(3, 0)
    assert a == b and all(v > 0 for v in a.values())
    assert 0.02 <= a["lengthscale"] <= 5.0
    assert stability.init_params(4, 0) != a
    m = stability.make_model("robust", "init_draw", 3, 0)
    assert m.lengthscale == a["lengthscale"] and m.alpha == a["alpha"]
    assert stability.make_model("gpis", "max_iter", 5, 0).max_iter == 5


@pytest.mark.timeout(120)
def test_an_iteration_cap_is_measured_and_caught():
    rec = stability.run_one("gpis", "max_iter", 1, 0, S)
    assert rec["converged"] is False
    assert "not_converged" in rec["reasons"] and rec["reliable"] is False
    json.dumps(rec, allow_nan=False)


@pytest.mark.timeout(120)
def test_robust_survives_the_paper_outlier_rate():
    rec = stability.run_one("robust", "outlier_rate", 0.02, 0, S)
    assert rec["mode"] == "ok" and rec["shape_fail"] is False
    assert rec["chamfer"] < stability.CHAMFER_FAIL and rec["Q"] < stability.Q_FAIL
    assert rec["detect_fail"] is False


def _run(method, value, seed, shape_fail, detect_fail=False, reliable=True, mode="ok"):
    return {"method": method, "sweep": "outlier_rate", "value": value, "seed": seed,
            "shape_fail": shape_fail, "detect_fail": detect_fail, "reliable": reliable,
            "reasons": [] if reliable else ["not_converged"], "mode": mode, "chamfer": 0.01,
            "Q": 0.1, "converged": reliable}  # fmt: skip


def test_breakdown_is_the_first_value_where_half_the_seeds_fail():
    runs = [
        _run("robust", 0.0, 0, False), _run("robust", 0.0, 1, False),
        _run("robust", 0.2, 0, True, reliable=False, mode="distorted"),
        _run("robust", 0.2, 1, False),
        _run("robust", 0.4, 0, True, mode="no_surface"),
        _run("robust", 0.4, 1, True, mode="distorted"),
    ]  # fmt: skip
    s = stability.summarize(runs, {"outlier_rate": (0.0, 0.2, 0.4)})["outlier_rate/robust"]
    assert s["shape_breakdown"] == 0.2 and s["detect_breakdown"] is None
    assert s["failed"] == 3 and s["caught"] == 1 and s["false_alarms"] == 0
    assert s["modes"] == {"distorted": 2, "no_surface": 1}
    text = stability.render({"x": s}, 2, S, "test")
    assert "| outlier_rate | robust | 0.2 | never | 3/6 |" in text


@pytest.mark.timeout(180)
def test_cli_writes_table_chart_and_json(tmp_path):
    args = argparse.Namespace(out=str(tmp_path), seeds=1, sweeps="max_iter", methods="gpis",
                              quick=True, jobs=1)  # fmt: skip
    assert cli_bench.run_stability(args) == 0
    res = json.loads((tmp_path / "results.json").read_text())
    assert len(res["runs"]) == 2 and (tmp_path / "stability.png").stat().st_size > 0
    assert "max_iter" in (tmp_path / "stability.md").read_text()


def test_cli_refuses_unknown_sweeps(tmp_path):
    args = argparse.Namespace(out=str(tmp_path), seeds=1, sweeps="wind", methods="gpis",
                              quick=True, jobs=1)  # fmt: skip
    with pytest.raises(ConfigError, match="wind"):
        cli_bench.run_stability(args)


@pytest.mark.soak
@pytest.mark.timeout(3600)
def test_cli_quick_every_sweep(tmp_path):
    args = argparse.Namespace(out=str(tmp_path), seeds=None, sweeps=",".join(stability.SWEEPS),
                              methods=",".join(stability.METHODS), quick=True, jobs=2)  # fmt: skip
    assert cli_bench.run_stability(args) == 0
