"""``groundstation bench stability``: where GPIS and robust GPIS break down, and whether we notice.

Data: the paper's 2D protocol on the circle (``bench.shapes2d``: 120 contacts, 460 free-space
samples, 2 % outlier pairs unless a sweep changes it), several seeds per value. Methods: GPIS,
exact robust GPIS, and the sparse default (``SparseRobustGPIS`` with its default settings; skipped
when the module is missing). Sweeps (:data:`SWEEPS`, ordered from easy to hard):

* ``outlier_rate`` - fraction of free-space samples replaced by false pairs, 0 to 40 %;
* ``gust_size`` - one gust: 5-50 consecutive false contacts within ~1 cm of one place 0.3-1 m off
  the surface (each with its internal point along the gust's direction), no other outliers;
* ``near_distance`` - 10 false pairs at 0.5 down to 0.1 m from the surface (hardest);
* ``n_contacts`` - very few contacts: 120 down to 5 (evenly spaced);
* ``duplicates`` - every contact repeated exactly 1-8 times;
* ``init_draw`` - random positive initial hyperparameters, log-uniform (l0 in [0.02, 5] m,
  sigma_f^2 in [0.01, 100], GPIS noise in [1e-4, 1], alpha in [0.1, 100], beta in [1e-3, 10]),
  as the paper's Algorithm 1 starts from random values; charted against l0;
* ``max_iter`` - EM (GPIS: L-BFGS-B) iteration cap 200 down to 1.

A run *fails its shape* when the fit raises, no zero contour exists, or the Chamfer distance to
the true circle exceeds :data:`CHAMFER_FAIL`; it *fails detection* when Q > :data:`Q_FAIL`. The
breakdown point of a method on a sweep is the first value at which at least half of the seeds
fail. Every run is also passed to :func:`groundstation.mapping.diagnostics.diagnose`; the table
says whether the failures were caught (and how often reliable runs were flagged).
Outputs in ``--out``: ``stability.md``, ``stability.png``, ``results.json``.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.bench import shapes2d
from groundstation.mapping.diagnostics import diagnose
from groundstation.mapping.grid import Grid, evaluate_field
from groundstation.mapping.metrics import (
    chamfer_distance,
    false_positive_clarity,
    sample_polylines,
    shape_error,
)
from groundstation.mapping.surface import extract_contours

SHAPE = "circle"
CHAMFER_FAIL = 0.02  # metres: ~10 % of the circle's radius, 15x the robust model's nominal value
Q_FAIL = 0.5  # outliers not at least twice as uncertain as their genuine neighbours
METHODS = ("gpis", "robust", "sparse")

#: sweep -> (full values, quick values, axis label), ordered from easy to hard.
SWEEPS: dict[str, tuple[tuple[float, ...], tuple[float, ...], str]] = {
    "outlier_rate": ((0.0, 0.02, 0.05, 0.1, 0.2, 0.3, 0.4), (0.0, 0.1, 0.4), "outlier rate"),
    "gust_size": ((5, 10, 20, 35, 50), (5, 50), "false contacts in one gust"),
    "near_distance": ((0.5, 0.3, 0.2, 0.1), (0.5, 0.1), "outlier distance to surface, m"),
    "n_contacts": ((120, 60, 30, 15, 8, 4), (120, 8), "number of contacts"),
    "duplicates": ((1, 2, 4, 8), (1, 3), "copies of every contact"),
    "init_draw": ((0, 1, 2, 3, 4, 5, 6, 7), (0, 1), "random initial lengthscale l0, m"),
    "max_iter": ((200, 50, 20, 10, 5, 2, 1), (200, 2), "iteration cap"),
}


@dataclasses.dataclass(frozen=True)
class StabilitySettings:
    spacing: float = 0.02  # grid spacing, metres
    region_half: float = shapes2d.REGION_HALF
    n_free: int = shapes2d.N_FREE
    base_outlier_prob: float = shapes2d.OUTLIER_PROB


# --------------------------------------------------------------------------- data


def _free_outlier_pairs(
    pts: np.ndarray, rng: np.random.Generator, direction: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """False contacts at ``pts`` (k, 2) plus internal points 0.1 m away (given or random dir)."""
    if direction is None:
        ang = rng.uniform(0, 2 * math.pi, len(pts))
        direction = np.stack([np.cos(ang), np.sin(ang)], 1)
    return pts, pts + shapes2d.PAIR_DISTANCE * np.broadcast_to(direction, pts.shape)


def _with_pairs(d: shapes2d.Dataset, fc: np.ndarray, fi: np.ndarray) -> shapes2d.Dataset:
    k = len(fc)
    n0 = len(d.y)
    X = np.concatenate([d.X, fc, fi])
    kind = np.concatenate(
        [
            d.kind,
            np.full(k, shapes2d.FALSE_CONTACT, np.int8),
            np.full(k, shapes2d.FALSE_INTERNAL, np.int8),
        ]
    )
    y = np.concatenate([d.y, np.zeros(k), -np.ones(k)])
    pair = np.concatenate([d.pair, np.full(k, -1), n0 + np.arange(k)])
    return shapes2d.Dataset(X=X, y=y, kind=kind, pair=pair)


def _boundary_offset(shape: shapes2d.Shape2D, dist: float, k: int, rng) -> np.ndarray:
    """``k`` points at distance ``dist`` (m) outside the shape's boundary (random places)."""
    b = shape.boundary(0.002)
    p = b[rng.integers(0, len(b), k)]
    eps = 1e-4
    grad = np.stack(
        [
            shape.sdf(p + [eps, 0]) - shape.sdf(p - [eps, 0]),
            shape.sdf(p + [0, eps]) - shape.sdf(p - [0, eps]),
        ],
        1,
    )
    n = grad / np.linalg.norm(grad, axis=1, keepdims=True)
    return p + dist * n


def make_data(sweep: str, value: float, seed: int, s: StabilitySettings) -> shapes2d.Dataset:
    """The data set of one (sweep, value, seed) cell (module docstring); deterministic."""
    shape = shapes2d.make_shape(SHAPE)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7, sum(map(ord, sweep))]))
    kw = dict(n_free=s.n_free, region_half=s.region_half)
    if sweep == "outlier_rate":
        return shapes2d.make_dataset(shape, rng, outlier_prob=float(value), **kw)
    if sweep in ("gust_size", "near_distance"):
        d = shapes2d.make_dataset(shape, rng, outlier_prob=0.0, **kw)
        if sweep == "gust_size":
            centre = _boundary_offset(shape, rng.uniform(0.3, 1.0), 1, rng)
            pts = centre + rng.normal(0.0, 0.01, (int(value), 2))
            ang = rng.uniform(0, 2 * math.pi)
            fc, fi = _free_outlier_pairs(pts, rng, np.array([math.cos(ang), math.sin(ang)]))
        else:
            fc, fi = _free_outlier_pairs(_boundary_offset(shape, float(value), 10, rng), rng)
        return _with_pairs(d, fc, fi)
    d = shapes2d.make_dataset(shape, rng, outlier_prob=s.base_outlier_prob, **kw)
    contact = d.kind == shapes2d.CONTACT
    idx_c = np.flatnonzero(contact)
    if sweep == "n_contacts":
        keep_c = idx_c[np.linspace(0, len(idx_c), int(value), endpoint=False).astype(int)]
        keep = np.concatenate([keep_c, np.flatnonzero(~contact)])
    elif sweep == "duplicates":
        keep = np.concatenate([np.repeat(idx_c, int(value)), np.flatnonzero(~contact)])
    else:
        return d
    # pair indices are not needed by the bench; rebuild without them.
    return shapes2d.Dataset(
        X=d.X[keep], y=d.y[keep], kind=d.kind[keep], pair=np.full(len(keep), -1, np.int64)
    )


def init_params(value: float, seed: int) -> dict[str, float]:
    """Random positive initial hyperparameters of draw ``value`` (log-uniform, docstring)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 11, int(value)]))

    def lu(lo: float, hi: float) -> float:
        return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))

    return {
        "lengthscale": lu(0.02, 5.0),
        "signal_var": lu(0.01, 100.0),
        "noise_var": lu(1e-4, 1.0),
        "alpha": lu(0.1, 100.0),
        "beta": lu(1e-3, 10.0),
    }


def make_model(method: str, sweep: str, value: float, seed: int) -> Any:
    """Unfitted estimator of ``method`` with the sweep's settings."""
    from groundstation.mapping import GPIS, RobustGPIS

    kw: dict[str, Any] = {}
    if sweep == "init_draw":
        p = init_params(value, seed)
        kw = {k: p[k] for k in ("lengthscale", "signal_var")}
        kw.update(
            {"noise_var": p["noise_var"]}
            if method == "gpis"
            else {"alpha": p["alpha"], "beta": p["beta"]}
        )
    elif sweep == "max_iter":
        kw = {"max_iter": int(value)}
    if method == "gpis":
        return GPIS(**kw)
    if method == "robust":
        return RobustGPIS(**kw)
    from groundstation.mapping.sparse import SparseRobustGPIS

    return SparseRobustGPIS(**kw)


# --------------------------------------------------------------------------- one run


def _f(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def run_one(method: str, sweep: str, value: float, seed: int, s: StabilitySettings) -> dict:
    """Fit one method on one data set; measure, classify and diagnose it (JSON-ready dict)."""
    shape = shapes2d.make_shape(SHAPE)
    d = make_data(sweep, value, seed, s)
    grid = Grid.from_bounds((-s.region_half,) * 2, (s.region_half,) * 2, s.spacing)
    rec: dict[str, Any] = {
        "method": method,
        "sweep": sweep,
        "value": value,
        "seed": seed,
        "n": int(len(d.y)),
    }
    if sweep == "init_draw":
        rec["l0"] = init_params(value, seed)["lengthscale"]
    t0 = time.perf_counter()
    try:
        model = make_model(method, sweep, value, seed)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model.fit(d.X, d.y)
        field = evaluate_field(model.predict, grid, n_train=len(d.y))
    except ImportError as exc:
        rec.update(skipped=f"{type(exc).__name__}: {exc}")
        return rec
    except Exception as exc:  # a failing fit is this bench's result, not a crash
        rec.update(
            error=f"{type(exc).__name__}: {exc}",
            shape_fail=True,
            mode="exception",
            detect_fail=None,
            reliable=False,
            reasons=["exception"],
        )
        return rec
    rec["fit_s"] = time.perf_counter() - t0
    contours = extract_contours(field.mean, grid)
    chamfer = _f(chamfer_distance(sample_polylines(contours, 0.005), shape.boundary(0.005)))
    u = np.maximum(np.asarray(model.uncertainty_, dtype=np.float64), 1e-300)
    q = None
    if np.any(d.outlier):
        q = _f(false_positive_clarity(d.X, u, d.outlier, normal=d.normal).mean)
    diag = diagnose(
        model, surface=contours, field=field.mean, outliers_expected=bool(np.any(d.outlier))
    )
    rec.update(
        chamfer=chamfer,
        e=_f(shape_error(field.mean.reshape(-1), grid.points(), shape.sdf)),
        Q=q,
        converged=bool(getattr(model, "converged_", True)),
        n_iter=int(getattr(model, "n_iter_", -1)),
        lengthscale=_f(getattr(model, "lengthscale_", None)),
        alpha=_f(getattr(model, "alpha_", None)),
        reliable=diag.reliable,
        reasons=list(diag.reasons),
        fallback=diag.fallback,
    )
    rec["mode"] = _mode(rec, contours)
    rec["shape_fail"] = rec["mode"] in ("no_surface", "distorted")
    rec["detect_fail"] = None if q is None else bool(q > Q_FAIL)
    return rec


def _mode(rec: dict, contours: list) -> str:
    """How a run failed: ok | no_surface | distorted (Chamfer above CHAMFER_FAIL)."""
    if not contours or rec["chamfer"] is None:
        return "no_surface"
    if rec["chamfer"] > CHAMFER_FAIL:
        return "distorted"
    return "ok"


# --------------------------------------------------------------------------- running


_ONE_THREAD_ENV = {k: "1" for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}


def _limit_blas() -> Any:
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits

    import groundstation.mapping.robust  # noqa: F401

    return threadpool_limits(limits=1)


def _run_task(task: tuple, s: StabilitySettings) -> dict:
    return run_one(*task, s)


def run_all(tasks: list[tuple], s: StabilitySettings, jobs: int) -> list[dict]:
    """Run (method, sweep, value, seed) tasks with a tqdm bar; 1 BLAS thread per process."""
    from tqdm import tqdm

    out: list[dict] = []
    bar = tqdm(total=len(tasks), file=sys.stderr, desc="stability", unit="fit")
    if jobs <= 1:
        with _limit_blas():
            for t in tasks:
                out.append(run_one(*t, s))
                bar.update()
    else:
        saved = {k: os.environ.get(k) for k in _ONE_THREAD_ENV}
        os.environ.update(_ONE_THREAD_ENV)
        try:
            ctx = get_context("spawn")
            with ProcessPoolExecutor(jobs, mp_context=ctx) as pool:
                for fut in as_completed([pool.submit(_run_task, t, s) for t in tasks]):
                    out.append(fut.result())
                    bar.update()
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
    bar.close()
    order = {m: i for i, m in enumerate(METHODS)}
    return sorted(
        out,
        key=lambda r: (list(SWEEPS).index(r["sweep"]), order[r["method"]], r["value"], r["seed"]),
    )


# --------------------------------------------------------------------------- analysis


def summarize(runs: list[dict], values: dict[str, tuple]) -> dict[str, Any]:
    """Per (sweep, method): medians per value, breakdown points, failure modes, detection."""
    out: dict[str, Any] = {}
    for sweep, vals in values.items():
        for method in METHODS:
            rs = [r for r in runs if r["sweep"] == sweep and r["method"] == method]
            if not rs or all("skipped" in r for r in rs):
                continue
            per_value = []
            shape_bp = detect_bp = None
            for v in vals:
                rv = [r for r in rs if r["value"] == v and "skipped" not in r]
                if not rv:
                    continue
                sf = float(np.mean([bool(r.get("shape_fail")) for r in rv]))
                dvals = [r["detect_fail"] for r in rv if r.get("detect_fail") is not None]
                df = float(np.mean(dvals)) if dvals else None
                per_value.append(
                    {
                        "value": v,
                        "runs": len(rv),
                        "shape_fail_frac": sf,
                        "detect_fail_frac": df,
                        "chamfer_median": _median([r.get("chamfer") for r in rv]),
                        "Q_median": _median([r.get("Q") for r in rv]),
                    }
                )
                if shape_bp is None and sf >= 0.5:
                    shape_bp = v
                if detect_bp is None and df is not None and df >= 0.5:
                    detect_bp = v
            ok = [r for r in rs if "skipped" not in r]
            failed = [r for r in ok if r.get("shape_fail") or r.get("detect_fail")]
            good = [r for r in ok if not (r.get("shape_fail") or r.get("detect_fail"))]
            modes: dict[str, int] = {}
            for r in failed:
                key = r.get("mode", "ok")
                if key == "ok":
                    key = f"outliers not flagged (Q > {Q_FAIL:.1f})"
                modes[key] = modes.get(key, 0) + 1
            reasons: dict[str, int] = {}
            for r in failed:
                for reason in r.get("reasons") or []:
                    reasons[reason] = reasons.get(reason, 0) + 1
            out[f"{sweep}/{method}"] = {
                "sweep": sweep,
                "method": method,
                "per_value": per_value,
                "shape_breakdown": shape_bp,
                "detect_breakdown": detect_bp,
                "runs": len(ok),
                "failed": len(failed),
                "modes": modes,
                "caught": sum(not r.get("reliable", True) for r in failed),
                "false_alarms": sum(not r.get("reliable", True) for r in good),
                "good": len(good),
                "reasons_on_failures": reasons,
                "not_converged": sum(r.get("converged") is False for r in ok),
            }
    return out


def _median(xs: list) -> float | None:
    v = [x for x in xs if x is not None]
    return float(np.median(v)) if v else None


def _fmt_value(v: Any) -> str:
    return "never" if v is None else f"{v:g}"


def render(summary: dict[str, Any], seeds: int, s: StabilitySettings, setting: str) -> str:
    """Markdown: breakdown points, failure modes and detection per sweep and method."""
    lines = [
        "# stability: where GPIS and robust GPIS break down",
        "",
        f"Setting: {setting}; {seeds} seeds per value; 2D circle (paper protocol), grid "
        f"{s.spacing} m. Shape failure: exception, no zero contour, or Chamfer > {CHAMFER_FAIL} m. "
        f"Detection failure: Q > {Q_FAIL}. Breakdown: first swept value (easy -> hard) where at "
        "least half of the seeds fail. Caught: failed runs that `diagnose` marked unreliable; "
        "false alarms: good runs it marked unreliable.",
        "",
        "| sweep | method | shape breakdown | detection breakdown | failed / runs | how it fails "
        "| caught | false alarms | diagnose reasons on failures |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in summary.values():
        modes = ", ".join(f"{k} x{v}" for k, v in sorted(row["modes"].items())) or "-"
        reasons = ", ".join(f"{k} x{v}" for k, v in sorted(row["reasons_on_failures"].items()))
        lines.append(
            f"| {row['sweep']} | {row['method']} | {_fmt_value(row['shape_breakdown'])} | "
            f"{_fmt_value(row['detect_breakdown'])} | {row['failed']}/{row['runs']} | {modes} | "
            f"{row['caught']}/{row['failed']} | {row['false_alarms']}/{row['good']} | "
            f"{reasons or '-'} |"
        )
    lines += [
        "",
        "## Medians per value",
        "",
        "| sweep | method | value | Chamfer m | Q | shape fail | detect fail |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in summary.values():
        for pv in row["per_value"]:
            c, q = pv["chamfer_median"], pv["Q_median"]
            dfr = pv["detect_fail_frac"]
            lines.append(
                f"| {row['sweep']} | {row['method']} | {pv['value']:g} | "
                f"{'n/a' if c is None else f'{c:.4f}'} | {'n/a' if q is None else f'{q:.3g}'} | "
                f"{pv['shape_fail_frac']:.0%} | {'n/a' if dfr is None else f'{dfr:.0%}'} |"
            )
    return "\n".join(lines) + "\n"


def plot(runs: list[dict], values: dict[str, tuple], path: Path) -> None:
    """Shape error (Chamfer) and Q against each swept variable, per method (median, seeds)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sweeps = list(values)
    fig, axes = plt.subplots(2, len(sweeps), figsize=(2.6 * len(sweeps), 5.2), squeeze=False)
    colors = {"gpis": "tab:red", "robust": "tab:blue", "sparse": "tab:green"}
    for j, sweep in enumerate(sweeps):
        for method in METHODS:
            rs = [
                r
                for r in runs
                if r["sweep"] == sweep and r["method"] == method and "skipped" not in r
            ]
            if not rs:
                continue
            for i, key in enumerate(("chamfer", "Q")):
                ax = axes[i, j]
                if sweep == "init_draw":  # scatter against the drawn l0
                    xs = [r["l0"] for r in rs if r.get(key) is not None]
                    ys = [r[key] for r in rs if r.get(key) is not None]
                    ax.scatter(xs, ys, s=8, c=colors[method], label=method)
                    ax.set_xscale("log")
                    continue
                xs, ys = [], []
                for v in values[sweep]:
                    m = _median([r.get(key) for r in rs if r["value"] == v])
                    if m is not None:
                        xs.append(v)
                        ys.append(m)
                ax.plot(xs, ys, "o-", ms=3, c=colors[method], label=method)
        axes[0, j].set_title(sweep, fontsize=8)
        axes[1, j].set_xlabel(SWEEPS[sweep][2], fontsize=7)
        for i in range(2):
            axes[i, j].set_yscale("log")
            axes[i, j].tick_params(labelsize=6)
        axes[0, j].axhline(CHAMFER_FAIL, color="k", lw=0.6, ls="--")
        axes[1, j].axhline(Q_FAIL, color="k", lw=0.6, ls="--")
    axes[0, 0].set_ylabel("Chamfer distance, m", fontsize=7)
    axes[1, 0].set_ylabel("Q (smaller is clearer)", fontsize=7)
    axes[0, 0].legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=60)
    plt.close(fig)
