"""End to end: the paper2d bench on tiny settings, with the real estimators."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest

from groundstation.bench import paper2d
from groundstation.bench.paper2d import BenchSettings, run_one
from groundstation.cli import bench as cli_bench
from groundstation.errors import ConfigError

# The protocol's data (n ~ 590, 2 % outlier pairs) on the --quick grid (0.04 m).
SMALL = BenchSettings(spacing=0.04)
# For the determinism check only: tiny data (n ~ 220) and a very coarse grid.
TINY = BenchSettings(spacing=0.2, n_free=100, outlier_prob=0.06)


def _close(a, b) -> bool:
    if isinstance(a, list):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and isinstance(b, float):
        return math.isclose(a, b, rel_tol=1e-6, abs_tol=1e-12)
    return a == b


def _finite(x) -> bool:
    return x is not None and math.isfinite(x)


@pytest.mark.timeout(120)
def test_run_one_outputs_are_finite_and_robust_is_clearer():
    r = run_one("circle", 0, SMALL, keep_fields=True)
    assert r["counts"]["false_contact"] >= 5
    for model in paper2d.MODELS:
        rec = r[model]
        assert "error" not in rec, rec
        for key in ("e", "chamfer", "Q", "phantom_length", "fit_s", "predict_s"):
            assert _finite(rec[key]), (model, key, rec[key])
        assert len(rec["Q_per_outlier"]) == r["counts"]["false_contact"]
        assert rec["n_iter"] >= 1
        mean = r["fields"][model]["mean"]
        assert mean.shape == r["fields"]["grid"].shape and np.all(np.isfinite(mean))
    # The robust model singles out the planted false contacts (Q << 1); GPIS does not.
    assert r["robust"]["Q"] < 0.5 * r["gpis"]["Q"]
    json.dumps({k: v for k, v in r.items() if k != "fields"}, allow_nan=False)


@pytest.mark.timeout(180)
def test_process_pool_gives_the_same_numbers_as_one_process():
    tasks = [("square", 0, False), ("cross", 1, False)]
    serial = paper2d._run_all(tasks, TINY, jobs=1)
    pooled = paper2d._run_all(tasks, TINY, jobs=2)
    for a, b in zip(serial, pooled, strict=True):
        for model in paper2d.MODELS:
            ra, rb = a[model], b[model]
            assert ra.keys() == rb.keys()
            for key in ra.keys() - {"fit_s", "predict_s"}:
                # Same BLAS thread count (1) in both: equal up to rounding (numpy's SIMD
                # reductions may round differently with another memory alignment).
                assert _close(ra[key], rb[key]), (model, key, ra[key], rb[key])


def _args(tmp_path, **kw) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    cli_bench.add_paper2d_arguments(parser)
    argv = ["--out", str(tmp_path)]
    for k, v in kw.items():
        argv += [f"--{k.replace('_', '-')}"] + ([] if v is True else [str(v)])
    return parser.parse_args(argv)


@pytest.mark.timeout(180)
def test_run_writes_summary_results_and_figure(tmp_path, capsys):
    args = _args(tmp_path, seeds=1, shapes="circle", quick=True, jobs=1)
    assert cli_bench.run_paper2d(args) == 0
    summary = (tmp_path / "summary.md").read_text()
    assert "| circle |" in summary and "Table II" in summary and "Table III" in summary
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["seeds"] == 1 and results["shapes"] == ["circle"]
    assert results["settings"]["spacing"] == 0.04 and results["settings"]["prior_mean"] == 0.0
    assert "numpy" in results["versions"]
    (run,) = results["runs"]
    assert _finite(run["robust"]["e"]) and _finite(run["gpis"]["e"])
    png = tmp_path / "fig6_circle.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert png.stat().st_size < 300_000
    assert "Shape error" in capsys.readouterr().out


def test_run_rejects_unknown_shape_and_bad_counts(tmp_path):
    with pytest.raises(ConfigError, match="hexagon"):
        cli_bench.run_paper2d(_args(tmp_path, shapes="circle,hexagon"))
    with pytest.raises(ConfigError, match="--seeds"):
        cli_bench.run_paper2d(_args(tmp_path, seeds=0))
