"""``groundstation bench paper2d``: the paper's 2D simulation, GPIS vs robust GPIS.

For each shape (square, circle, cross) and seed, draw a data set (``bench.shapes2d``, protocol and
size choices in its docstring), fit GPIS and RobustGPIS with the paper's initial values, predict
the mean on a grid over [-3, 3]^2 and measure (``mapping.metrics``): shape error e, Chamfer
distance between the extracted zero contour and the true boundary, false-positive clarity Q,
phantom contour length, fit/predict times, EM iterations, convergence. Prints per-shape
mean +- sd with Welch t-test p-values (the paper's Tables II and III) and writes ``summary.md``,
``results.json`` and one Fig.-6-like PNG per shape into ``--out``.

Seeds run in a process pool (``--jobs``) whose workers use 1 BLAS thread; ``--jobs 1`` runs in
this process, also with 1 BLAS thread, so both give identical numbers.
"""

from __future__ import annotations

import dataclasses
import math
import platform
import sys
import time
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.bench import shapes2d
from groundstation.mapping.grid import Grid, evaluate_field
from groundstation.mapping.metrics import (
    chamfer_distance,
    false_positive_clarity,
    phantom_length,
    polyline_length,
    sample_polylines,
    shape_error,
)
from groundstation.mapping.surface import extract_contours

MODELS = ("gpis", "robust")


@dataclasses.dataclass(frozen=True)
class BenchSettings:
    """Settings of one bench run (defaults: the paper's protocol, module docstrings)."""

    spacing: float = 0.02  # test grid spacing, metres
    region_half: float = shapes2d.REGION_HALF
    n_free: int = shapes2d.N_FREE
    outlier_prob: float = shapes2d.OUTLIER_PROB
    prior_mean: float = 0.0
    lengthscale: float = 0.25
    signal_var: float = 1.0
    noise_var: float = 0.01  # GPIS initial noise variance (MappingSettings default)
    alpha: float = 2.0
    beta: float = 4.0
    band: float = 0.01  # |mu| band of the shape error, label units
    clarity_radius: float = 0.5  # metres
    # A "false" contact closer to the true boundary than the structure's minimum thickness d_in
    # (paper: 0.1 m) is geometrically a true contact with a small error: nothing can tell it apart.
    # Q is scored on the others; Q_all keeps every outlier (both are reported).
    min_outlier_distance: float = 0.1  # metres
    phantom_threshold: float = 0.1  # metres
    sample_step: float = 0.005  # contour / boundary sampling for Chamfer, metres


def make_models(s: BenchSettings) -> dict[str, Any]:
    """Unfitted GPIS and RobustGPIS with the bench's settings (paper's initial values)."""
    from groundstation.mapping import GPIS, RobustGPIS

    common = dict(lengthscale=s.lengthscale, signal_var=s.signal_var, prior_mean=s.prior_mean)
    return {
        "gpis": GPIS(noise_var=s.noise_var, **common),
        "robust": RobustGPIS(alpha=s.alpha, beta=s.beta, **common),
    }


def _rng(shape: str, seed: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([seed, shapes2d.SHAPES.index(shape)]))


def _f(x: float) -> float | None:
    return None if x is None or not math.isfinite(x) else float(x)


def run_one(shape_name: str, seed: int, s: BenchSettings, keep_fields: bool = False) -> dict:
    """Fit both models on one data set and measure them.

    Returns a JSON-ready dict (NaN as None); with ``keep_fields`` also the arrays the figure
    needs under ``"fields"`` (removed before writing results.json).
    """
    shape = shapes2d.make_shape(shape_name)
    data = shapes2d.make_dataset(
        shape, _rng(shape_name, seed), n_free=s.n_free, outlier_prob=s.outlier_prob,
        region_half=s.region_half,
    )  # fmt: skip
    grid = Grid.from_bounds((-s.region_half,) * 2, (s.region_half,) * 2, s.spacing)
    points = grid.points()
    truth_samples = shape.boundary(s.sample_step)
    out: dict[str, Any] = {"shape": shape_name, "seed": seed, "n": int(len(data.y)),
                           "counts": data.counts()}  # fmt: skip
    fields: dict[str, Any] = {"X": data.X, "y": data.y, "kind": data.kind, "grid": grid}
    for name, model in make_models(s).items():
        rec: dict[str, Any] = {}
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                t0 = time.perf_counter()
                model.fit(data.X, data.y)
                t1 = time.perf_counter()
                field = evaluate_field(model.predict, grid, n_train=len(data.y))
                t2 = time.perf_counter()
        except Exception as exc:  # a failed fit is a result of the bench, not a crash
            out[name] = {"error": f"{type(exc).__name__}: {exc}"}
            continue
        contours = extract_contours(field.mean, grid)
        u = np.asarray(model.uncertainty_, dtype=np.float64)
        far = np.abs(shape.sdf(data.X)) >= s.min_outlier_distance
        clarity = false_positive_clarity(
            data.X, u, data.outlier & far, normal=data.normal, radius=s.clarity_radius
        )
        clarity_all = false_positive_clarity(
            data.X, u, data.outlier, normal=data.normal, radius=s.clarity_radius
        )
        rec.update(
            e=_f(shape_error(field.mean.reshape(-1), points, shape.sdf, band=s.band)),
            chamfer=_f(chamfer_distance(sample_polylines(contours, s.sample_step), truth_samples)),
            Q=_f(clarity.mean),
            Q_per_outlier=[_f(q) for q in clarity.per_outlier],
            Q_skipped=clarity.n_skipped,
            Q_all=_f(clarity_all.mean),
            Q_all_per_outlier=[_f(q) for q in clarity_all.per_outlier],
            near_surface_outliers=int(np.sum(data.outlier & ~far)),
            phantom_length=phantom_length(contours, shape.sdf, threshold=s.phantom_threshold),
            contour_length=polyline_length(contours),
            fit_s=t1 - t0,
            predict_s=t2 - t1,
            n_iter=int(getattr(model, "n_iter_", -1)),
            converged=bool(getattr(model, "converged_", False)),
            lengthscale=_f(float(getattr(model, "lengthscale_", float("nan")))),
            signal_var=_f(float(getattr(model, "signal_var_", float("nan")))),
            alpha=_f(float(getattr(model, "alpha_", float("nan")))),
            beta=_f(float(getattr(model, "beta_", float("nan")))),
            warnings=sorted({f"{w.category.__name__}: {w.message}" for w in caught}),
        )
        out[name] = rec
        fields[name] = {"mean": field.mean, "u": u, "contours": contours}
    if keep_fields:
        out["fields"] = fields
    return out


#: Environment that makes every BLAS/OpenMP pool single-threaded in processes started after it.
_ONE_THREAD_ENV = {k: "1" for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}


def _one_blas_thread() -> Any:
    """Load every BLAS the fits use, then limit them all to 1 thread (returns the limiter).

    threadpoolctl only limits libraries already loaded, so the estimators (and scipy.linalg)
    are imported first. One thread makes the numbers independent of --jobs: the robust EM
    follows slightly different paths when BLAS sums in a different order.
    """
    import scipy.linalg  # noqa: F401
    from threadpoolctl import threadpool_limits

    import groundstation.mapping.gpis  # noqa: F401
    import groundstation.mapping.robust  # noqa: F401

    return threadpool_limits(limits=1)


def _worker_init() -> None:
    _one_blas_thread()  # process-wide in a worker


def _run_all(tasks: list[tuple[str, int, bool]], s: BenchSettings, jobs: int) -> list[dict]:
    import os

    from tqdm import tqdm

    results: list[dict] = []
    bar = tqdm(total=len(tasks), file=sys.stderr, desc="paper2d", unit="run")
    if jobs <= 1:
        with _one_blas_thread():
            for shape, seed, keep in tasks:
                results.append(run_one(shape, seed, s, keep))
                bar.update()
    else:
        saved = {k: os.environ.get(k) for k in _ONE_THREAD_ENV}
        os.environ.update(_ONE_THREAD_ENV)  # inherited by the spawned workers
        try:
            ctx = get_context("spawn")
            with ProcessPoolExecutor(jobs, mp_context=ctx, initializer=_worker_init) as pool:
                futures = [pool.submit(run_one, sh, seed, s, keep) for sh, seed, keep in tasks]
                for fut in as_completed(futures):
                    results.append(fut.result())
                    bar.update()
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
    bar.close()
    return sorted(results, key=lambda r: (shapes2d.SHAPES.index(r["shape"]), r["seed"]))


def _values(runs: list[dict], model: str, key: str) -> np.ndarray:
    vals = [r[model].get(key) for r in runs if "error" not in r[model]]
    return np.array([np.nan if v is None else v for v in vals], dtype=np.float64)


def _pooled_q(runs: list[dict], model: str) -> np.ndarray:
    q = [v for r in runs if "error" not in r[model] for v in r[model]["Q_per_outlier"]]
    return np.array([np.nan if v is None else v for v in q], dtype=np.float64)


def _welch(a: np.ndarray, b: np.ndarray) -> float | None:
    from scipy import stats

    a, b = a[np.isfinite(a)], b[np.isfinite(b)]
    if a.size < 2 or b.size < 2:
        return None
    return _f(float(stats.ttest_ind(a, b, equal_var=False).pvalue))


def _mannwhitney(a: np.ndarray, b: np.ndarray) -> float | None:
    from scipy import stats

    a, b = a[np.isfinite(a)], b[np.isfinite(b)]
    if a.size < 2 or b.size < 2:
        return None
    return _f(float(stats.mannwhitneyu(a, b, alternative="two-sided").pvalue))


def _ms(x: np.ndarray) -> dict[str, float | int | None]:
    x = x[np.isfinite(x)]
    return {"mean": _f(float(x.mean())) if x.size else None,
            "sd": _f(float(x.std(ddof=1))) if x.size > 1 else None,
            "median": _f(float(np.median(x))) if x.size else None, "n": int(x.size)}  # fmt: skip


def summarize(runs: list[dict]) -> dict[str, Any]:
    """Per shape: mean/sd of every measure per model and Welch p-values (GPIS vs robust)."""
    table: dict[str, Any] = {}
    for shape in shapes2d.SHAPES:
        rs = [r for r in runs if r["shape"] == shape]
        if not rs:
            continue
        row: dict[str, Any] = {"runs": len(rs)}
        for key in ("e", "chamfer", "Q", "Q_all", "phantom_length", "fit_s", "predict_s", "n_iter"):
            g, r = _values(rs, "gpis", key), _values(rs, "robust", key)
            row[key] = {"gpis": _ms(g), "robust": _ms(r), "p": _welch(g, r),
                        "p_mannwhitney": _mannwhitney(g, r)}  # fmt: skip
        g, r = _pooled_q(rs, "gpis"), _pooled_q(rs, "robust")
        row["Q_pooled"] = {"gpis": _ms(g), "robust": _ms(r), "p": _welch(g, r),
                           "p_mannwhitney": _mannwhitney(g, r)}  # fmt: skip
        row["near_surface"] = sum(
            x["robust"].get("near_surface_outliers", 0) for x in rs if "error" not in x["robust"]
        )
        for m in MODELS:
            ok = [x[m] for x in rs if "error" not in x[m]]
            row.setdefault("converged", {})[m] = sum(bool(x.get("converged")) for x in ok)
            row.setdefault("failed", {})[m] = len(rs) - len(ok)
            # No grid point in the |mu| < band: no estimated surface, e undefined (NaN).
            row.setdefault("no_surface", {})[m] = sum(x.get("e") is None for x in ok)
            # alpha at the Gaussian limit: the robust fit interpolates everything (no robustness).
            row.setdefault("alpha_at_limit", {})[m] = sum((x.get("alpha") or 0) >= 1e5 for x in ok)
        table[shape] = row
    return table


def _fmt(d: dict, digits: int = 4) -> str:
    if d["mean"] is None:
        return "n/a"
    sd = "" if d["sd"] is None else f" ± {d['sd']:.{digits}f}"
    return f"{d['mean']:.{digits}f}{sd}"


def _p(p: float | None) -> str:
    if p is None:
        return "n/a"
    return "< 1e-300" if p == 0.0 else f"{p:.2e}"  # 0.0: below double precision


def render_summary(table: dict[str, Any], s: BenchSettings, seeds: int) -> str:
    """Markdown tables like the paper's Tables II (shape error) and III (clarity), plus times."""
    lines = [
        "# paper2d: GPIS vs robust GPIS on the paper's 2D simulation",
        "",
        f"{seeds} seeds per shape; grid spacing {s.spacing} m over [-{s.region_half}, "
        f"{s.region_half}]^2; prior mean {s.prior_mean}; initial lengthscale {s.lengthscale}, "
        f"signal_var {s.signal_var}, alpha {s.alpha}, beta {s.beta}, GPIS noise_var {s.noise_var}.",
        "",
        "Protocol: 120 contacts per shape (0.01 m spacing; circle every 3 deg), square side 0.3 m, "
        "circle radius 0.191 m, cross extent 0.3 m with 0.1 m arms (all perimeters 1.2 m); "
        f"{s.n_free} free-space points uniform in the region, labelled by inside/outside; each "
        f"external point replaced with probability {s.outlier_prob} by an outlier pair (false "
        "contact + internal point 0.1 m away); n ~ 590. Sizes are our choice (see "
        "groundstation/bench/shapes2d.py).",
        "",
        f"e: mean distance to the true boundary of grid points with |mu| < {s.band} (m). Chamfer: "
        "symmetric mean distance between the extracted zero contour and the true boundary (m). "
        f"Q: mean over outliers of (mean u of genuine data within {s.clarity_radius} m) / u_o "
        "(smaller is clearer); 'per run' averages Q within each run then tests the run means, "
        "'pooled' tests all outliers of all runs. Q scores the false contacts at least "
        f"{s.min_outlier_distance} m (d_in) from the true boundary: a closer one is a true "
        "contact with a small error that nothing can tell apart; Q_all scores every false "
        "contact. p: Welch t-test.",
        "",
        "## Shape error (Table II)",
        "",
        "| shape | GPIS e | robust e | p | GPIS Chamfer | robust Chamfer | p |",
        "|---|---|---|---|---|---|---|",
    ]
    for shape, row in table.items():
        e, c = row["e"], row["chamfer"]
        lines.append(f"| {shape} | {_fmt(e['gpis'])} | {_fmt(e['robust'])} | {_p(e['p'])} | "
                     f"{_fmt(c['gpis'])} | {_fmt(c['robust'])} | {_p(c['p'])} |")  # fmt: skip
    lines += ["", "## False-positive clarity (Table III)", "",
              "| shape | GPIS Q (per run) | robust Q (per run) | p | GPIS Q (pooled) | "
              "robust Q (pooled) | outliers | p | GPIS Q_all | robust Q_all | p | "
              "near-surface |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for shape, row in table.items():
        q, qp, qa = row["Q"], row["Q_pooled"], row["Q_all"]
        lines.append(f"| {shape} | {_fmt(q['gpis'])} | {_fmt(q['robust'])} | {_p(q['p'])} | "
                     f"{_fmt(qp['gpis'])} | {_fmt(qp['robust'])} | {qp['gpis']['n']} | "
                     f"{_p(qp['p'])} | {_fmt(qa['gpis'])} | {_fmt(qa['robust'])} | "
                     f"{_p(qa['p'])} | {row['near_surface']} |")  # fmt: skip
    lines += [
        "",
        "## Medians and Mann-Whitney U p-values (robust to the heavy tails)",
        "",
        "| shape | measure | GPIS median | robust median | p |",
        "|---|---|---|---|---|",
    ]
    for shape, row in table.items():
        for key in ("e", "chamfer", "Q", "Q_all", "Q_pooled"):
            d = row[key]
            g, r = d["gpis"]["median"], d["robust"]["median"]
            lines.append(
                f"| {shape} | {key} | {'n/a' if g is None else f'{g:.3g}'} | "
                f"{'n/a' if r is None else f'{r:.3g}'} | {_p(d['p_mannwhitney'])} |"
            )
    lines += ["", f"## Phantom contour (farther than {s.phantom_threshold} m from the boundary, m)",
              "", "| shape | GPIS | robust | p |", "|---|---|---|---|"]  # fmt: skip
    for shape, row in table.items():
        ph = row["phantom_length"]
        lines.append(
            f"| {shape} | {_fmt(ph['gpis'], 3)} | {_fmt(ph['robust'], 3)} | {_p(ph['p'])} |"
        )
    lines += ["", "## Cost and failures", "",
              "no surface: runs without any grid point in the band (e undefined, left out of the "
              "means); alpha at limit: robust fits that ended at alpha >= 1e5 (Gaussian limit).",
              "",
              "| shape | model | fit s | predict s | EM/opt iterations | converged | failed | "
              "no surface | alpha at limit |", "|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for shape, row in table.items():
        for m in MODELS:
            lines.append(f"| {shape} | {m} | {_fmt(row['fit_s'][m], 2)} | "
                         f"{_fmt(row['predict_s'][m], 2)} | {_fmt(row['n_iter'][m], 1)} | "
                         f"{row['converged'][m]}/{row['runs']} | {row['failed'][m]} | "
                         f"{row['no_surface'][m]} | {row['alpha_at_limit'][m]} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def plot_shape(run: dict, path: Path, s: BenchSettings) -> None:
    """Fig.-6-like PNG: estimated shape, predicted mean, data uncertainty; GPIS over robust."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f = run["fields"]
    X, y, kind, grid = f["X"], f["y"], f["kind"], f["grid"]
    outline = shapes2d.make_shape(run["shape"]).outline()
    ext = [grid.origin[0], grid.region_max[0], grid.origin[1], grid.region_max[1]]
    fig, axes = plt.subplots(2, 4, figsize=(13, 6.4), constrained_layout=True)
    for row, model in enumerate(MODELS):
        if model not in f:
            continue
        mean, u, contours = f[model]["mean"], f[model]["u"], f[model]["contours"]
        for col, zoom in ((0, s.region_half), (1, 0.45)):
            ax = axes[row, col]
            for lab, colr in ((-1, "tab:blue"), (0, "tab:green"), (1, "tab:red")):
                sel = (y == lab) & (kind != shapes2d.FALSE_CONTACT)
                ax.scatter(X[sel, 0], X[sel, 1], s=4, c=colr, label=f"y={lab:+d}", lw=0)
            out = kind == shapes2d.FALSE_CONTACT
            ax.scatter(X[out, 0], X[out, 1], s=30, marker="x", c="k", label="false contact")
            ax.plot(outline[:, 0], outline[:, 1], "k--", lw=1, label="true")
            for i, c in enumerate(contours):
                ax.plot(c[:, 0], c[:, 1], "m-", lw=1.2, label="mu=0" if i == 0 else None)
            ax.set(xlim=(-zoom, zoom), ylim=(-zoom, zoom), aspect="equal")
            ax.set_title(f"{model}: estimated shape" + (" (zoom)" if col else ""), fontsize=9)
        axes[row, 0].legend(fontsize=6, loc="lower left")
        im = axes[row, 2].imshow(mean.T, origin="lower", extent=ext, cmap="RdBu_r", vmin=-1.5,
                                 vmax=1.5)  # fmt: skip
        axes[row, 2].set_title(f"{model}: predicted mean", fontsize=9)
        fig.colorbar(im, ax=axes[row, 2], shrink=0.8)
        sc = axes[row, 3].scatter(X[:, 0], X[:, 1], c=np.log10(u), s=6, cmap="viridis", lw=0)
        axes[row, 3].scatter(X[out, 0], X[out, 1], s=40, facecolors="none", edgecolors="r", lw=0.8)
        axes[row, 3].set(xlim=ext[:2], ylim=ext[2:], aspect="equal")
        axes[row, 3].set_title(f"{model}: log10 u (red: false contacts)", fontsize=9)
        fig.colorbar(sc, ax=axes[row, 3], shrink=0.8)
    fig.suptitle(f"{run['shape']}, seed {run['seed']}, n = {run['n']}", fontsize=10)
    fig.savefig(path, dpi=72)
    plt.close(fig)


def _versions() -> dict[str, str]:
    import scipy
    import skimage

    import groundstation

    return {"python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "scikit-image": skimage.__version__,
            "groundstation": getattr(groundstation, "__version__", "0.1.0")}  # fmt: skip
