"""``groundstation bench pareto``: wall time against accuracy of every mapping method.

Scenes: the paper's 2D shapes (``bench.shapes2d``, n ~ 590, seed 0 of each shape; the 2D rows
average the three shapes), the paper-like 3D set (``bench.scenes3d.paper3d``, n ~ 2,700, grid
0.05 m over 8 x 4 x 2 m), and the 40-minute session (``scenes3d.session40``) for the refit line.

Methods (one point each, :func:`method_specs`): GPIS; exact robust GPIS (the reference of the
ratios); robust GPIS on merged observations at several voxel sizes; sparse robust GPIS at several
numbers of inducing points; the default mapper (``SurfaceModel`` with default settings, marked
"default"); dense vs narrow-band evaluation at several grid spacings (re-using one fit of the
exact and of the default model); scikit-learn's ``GaussianProcessRegressor`` (plain GPIS, C x RBF
+ White, one L-BFGS start) as an outside baseline, predicted in chunks.

Every point is timed as fit (+ merge) + field + mesh in this one process with BLAS limited to one
thread (threadpoolctl), with its peak RSS above the process baseline (sampled every 10 ms), and
measured by Chamfer distance between the extracted surface (3D mesh / 2D contour) and the true
surface, the paper's shape error e where a field is available, and false-positive clarity Q over
the raw observations. Outputs in ``--out``: ``pareto.png``, ``pareto.md`` (every point, the
default marked, ratios vs the exact robust model), ``refit_vs_session.png`` and ``results.json``.
Methods whose module is missing (the speed core) are listed as skipped, never faked.
"""

from __future__ import annotations

import dataclasses
import math
import os
import threading
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.bench import scenes3d, shapes2d
from groundstation.mapping.grid import Grid, evaluate_field
from groundstation.mapping.metrics import (
    chamfer_distance,
    false_positive_clarity,
    sample_mesh_surface,
    sample_polylines,
    shape_error,
)
from groundstation.mapping.surface import extract_contours, extract_surface

DEFAULT = "default"
REFERENCE = "robust_exact"
N_SURFACE_SAMPLES = 20000  # mesh samples for the 3D Chamfer distance
CONTOUR_STEP = 0.005  # 2D contour / boundary sampling for the Chamfer distance, metres
FOCUS_MARGIN = 0.5  # metres around the contacts' bounding box for the "near data" metrics


# --------------------------------------------------------------------------- scenes


@dataclasses.dataclass(frozen=True)
class BenchScene:
    """Observations with ground truth, 2D or 3D, in the form every method consumes.

    Attributes
    ----------
    name : str
    X : (n, d) float64 metres; y : (n,) labels; kind : (n,) int8 (``shapes2d`` codes)
    ids : (n,) int64; t_ns : (n,) int64
    sdf : callable (m, d) -> (m,) signed distance, metres
    truth : (k, d) float64, dense samples of the true surface
    region_min, region_max : tuple of float, metres
    """

    name: str
    X: np.ndarray
    y: np.ndarray
    kind: np.ndarray
    ids: np.ndarray
    t_ns: np.ndarray
    sdf: Callable[[np.ndarray], np.ndarray]
    truth: np.ndarray
    region_min: tuple[float, ...]
    region_max: tuple[float, ...]

    @property
    def ndim(self) -> int:
        return int(self.X.shape[1])

    @property
    def outlier(self) -> np.ndarray:
        return self.kind == shapes2d.FALSE_CONTACT

    @property
    def normal(self) -> np.ndarray:
        return self.kind <= shapes2d.EXTERNAL

    def grid(self, spacing: float) -> Grid:
        return Grid.from_bounds(self.region_min, self.region_max, spacing)

    @property
    def focus(self) -> tuple[np.ndarray, np.ndarray]:
        """The explored box: contacts' bounding box + FOCUS_MARGIN, within the region (metres).

        Far from every observation the GP mean reverts to the prior mean 0, the surface level,
        so any method draws phantom surface there; "near data" metrics look only inside this
        box (the same box the default mapper meshes).
        """
        c = self.X[self.y == 0]
        lo = np.maximum(np.asarray(self.region_min), c.min(axis=0) - FOCUS_MARGIN)
        hi = np.minimum(np.asarray(self.region_max), c.max(axis=0) + FOCUS_MARGIN)
        return lo, hi

    def in_focus(self, pts: np.ndarray) -> np.ndarray:
        lo, hi = self.focus
        return np.all((pts >= lo) & (pts <= hi), axis=1)


def scene_2d(shape_name: str, seed: int = 0, **kw: Any) -> BenchScene:
    """A paper 2D data set (``shapes2d.make_dataset``) as a :class:`BenchScene`."""
    shape = shapes2d.make_shape(shape_name)
    rng = np.random.default_rng(np.random.SeedSequence([seed, shapes2d.SHAPES.index(shape_name)]))
    d = shapes2d.make_dataset(shape, rng, **kw)
    n = len(d.y)
    half = kw.get("region_half", shapes2d.REGION_HALF)
    return BenchScene(
        name=f"2d-{shape_name}",
        X=d.X,
        y=d.y,
        kind=d.kind,
        ids=np.arange(n, dtype=np.int64),
        t_ns=np.arange(n, dtype=np.int64) * 40_000_000,
        sdf=shape.sdf,
        truth=shape.boundary(CONTOUR_STEP),
        region_min=(-half, -half),
        region_max=(half, half),
    )


def scene_3d(obs: scenes3d.ObservationSet3D) -> BenchScene:
    """A 3D observation set as a :class:`BenchScene`."""
    sc = obs.scene
    return BenchScene(
        name=obs.name,
        X=obs.X,
        y=obs.y,
        kind=obs.kind,
        ids=obs.ids,
        t_ns=obs.t_ns,
        sdf=obs.sdf,
        truth=obs.truth_samples,
        region_min=tuple(sc.region_min),
        region_max=tuple(sc.region_max),
    )


# --------------------------------------------------------------------------- measuring


class PeakRSS:
    """Context manager sampling this process's resident set every 10 ms; ``peak_mb`` above start."""

    def __init__(self, period_s: float = 0.01) -> None:
        self.period_s = period_s
        self.peak_mb = float("nan")

    @staticmethod
    def _rss() -> int:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    def __enter__(self) -> PeakRSS:
        try:
            self._base = self._peak = self._rss()
        except OSError:  # not Linux: no memory column
            self._base = None
            return self
        self._stop = threading.Event()

        def loop() -> None:
            while not self._stop.wait(self.period_s):
                self._peak = max(self._peak, self._rss())

        self._thread = threading.Thread(target=loop, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._base is None:
            return
        self._stop.set()
        self._thread.join()
        self._peak = max(self._peak, self._rss())
        self.peak_mb = (self._peak - self._base) / 2**20


def _f(x: Any) -> float | None:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


@dataclasses.dataclass
class Fitted:
    """A fitted method, reduced to what the bench measures."""

    predict: Callable[..., Any]  # predict(Xq, return_std=False) -> mean
    u_raw: np.ndarray | None  # per raw observation, for Q
    model: Any
    merge_s: float
    fit_s: float
    n_train: int
    info: dict


def surface_of(mean: np.ndarray, grid: Grid) -> Any:
    """Zero set of a grid field: a SurfaceMesh (3D) or a list of contours (2D)."""
    if grid.ndim == 3:
        return extract_surface(mean, grid)
    return extract_contours(mean, grid)


def chamfer_of(surface: Any, scene: BenchScene, *, near: bool = False) -> float | None:
    """Chamfer distance (m) between an extracted surface and the true one; None if empty.

    ``near``: only surface samples inside the explored box (``BenchScene.focus``) count.
    """
    if scene.ndim == 3:
        if surface is None or surface.is_empty:
            return None
        pts = sample_mesh_surface(surface.vertices, surface.faces, N_SURFACE_SAMPLES, seed=0)
    else:
        pts = sample_polylines(surface or [], CONTOUR_STEP)
    truth = scene.truth
    if near:
        pts, truth = pts[scene.in_focus(pts)], truth[scene.in_focus(truth)]
    return _f(chamfer_distance(pts, truth))


def clarity_of(u: np.ndarray | None, scene: BenchScene) -> float | None:
    """Mean false-positive clarity Q over the planted false contacts (None without u)."""
    if u is None or not np.any(scene.outlier):
        return None
    u = np.maximum(np.asarray(u, dtype=np.float64), 1e-300)
    return _f(false_positive_clarity(scene.X, u, scene.outlier, normal=scene.normal).mean)


def error_of(
    mean: np.ndarray | None, grid: Grid, scene: BenchScene, *, near: bool = False
) -> float | None:
    """The paper's shape error e over a grid field (None without one; ``near``: focus box)."""
    if mean is None:
        return None
    flat = np.asarray(mean).reshape(-1)
    pts = grid.points()
    ok = np.isfinite(flat)
    if near:
        ok &= scene.in_focus(pts)
    return _f(shape_error(flat[ok], pts[ok], scene.sdf))


# --------------------------------------------------------------------------- methods


def _core() -> dict[str, Any] | None:
    """The speed core's modules, or None when they are not installed yet."""
    import importlib

    try:
        return {
            name: importlib.import_module(f"groundstation.mapping.{name}")
            for name in ("merge", "sparse", "field", "model")
        }
    except ImportError:
        return None


def _uncertainty(model: Any) -> np.ndarray | None:
    u = getattr(model, "uncertainty_", None)
    return None if u is None else np.asarray(u, dtype=np.float64)


def fit_exact(kind: str, scene: BenchScene, **kw: Any) -> Fitted:
    """GPIS or exact RobustGPIS on the raw observations."""
    from groundstation.mapping import GPIS, RobustGPIS

    model = GPIS(**kw) if kind == "gpis" else RobustGPIS(**kw)
    t0 = time.perf_counter()
    model.fit(scene.X, scene.y)
    fit_s = time.perf_counter() - t0
    return Fitted(
        model.predict, _uncertainty(model), model, 0.0, fit_s, len(scene.y), _hyper(model)
    )


def _hyper(model: Any) -> dict:
    keys = ("lengthscale_", "signal_var_", "noise_var_", "alpha_", "beta_", "n_iter_")
    out = {k.rstrip("_"): _f(getattr(model, k, None)) for k in keys if hasattr(model, k)}
    if hasattr(model, "converged_"):
        out["converged"] = bool(model.converged_)
    return out


def _training_members(ts: Any, n_train: int) -> list[np.ndarray] | None:
    """Raw-row indices merged into each training row, if the TrainingSet exposes them."""
    for name in ("members", "groups", "source_rows"):
        mem = getattr(ts, name, None)
        if mem is not None and len(mem) == n_train:
            return [np.asarray(m, dtype=np.int64) for m in mem]
    return None


def fit_merged(scene: BenchScene, voxel_m: float, core: dict) -> Fitted:
    """Exact RobustGPIS on observations merged at ``voxel_m`` (``merge_observations``)."""
    from groundstation.mapping import RobustGPIS

    t0 = time.perf_counter()
    ts = core["merge"].merge_observations(scene.X, scene.y, scene.ids, scene.t_ns, voxel_m)
    t1 = time.perf_counter()
    model = RobustGPIS().fit(ts.X, ts.y)
    t2 = time.perf_counter()
    u_raw = _raw_u_from_merge(ts, model.uncertainty_, scene, model)
    info = _hyper(model) | {"n_train": len(ts.y)}
    return Fitted(model.predict, u_raw, model, t1 - t0, t2 - t1, len(ts.y), info)


def _raw_u_from_merge(ts: Any, u: np.ndarray, scene: BenchScene, model: Any) -> np.ndarray:
    """u of each raw observation: that of its merged row, else the model's predictive u."""
    members = _training_members(ts, len(u))
    if members is not None:
        out = np.full(len(scene.y), np.nan)
        for row, mem in enumerate(members):
            out[mem] = u[row]
        if np.all(np.isfinite(out)):
            return out
    # Fallback: nearest training row of the same label (merging never mixes labels).
    from scipy.spatial import cKDTree

    out = np.empty(len(scene.y))
    for lab in np.unique(scene.y):
        sel, tsel = scene.y == lab, np.asarray(ts.y) == lab
        if not np.any(tsel):
            out[sel] = float(np.median(u))
            continue
        _, idx = cKDTree(np.asarray(ts.X)[tsel]).query(scene.X[sel])
        out[sel] = u[np.flatnonzero(tsel)[idx]]
    return out


def fit_sparse(scene: BenchScene, n_inducing: int, core: dict) -> Fitted:
    """SparseRobustGPIS with ``n_inducing`` inducing points on the raw observations."""
    model = core["sparse"].SparseRobustGPIS(n_inducing=n_inducing)
    t0 = time.perf_counter()
    model.fit(scene.X, scene.y)
    fit_s = time.perf_counter() - t0
    info = _hyper(model) | {"n_inducing": n_inducing}
    return Fitted(model.predict, _uncertainty(model), model, 0.0, fit_s, len(scene.y), info)


def fit_sklearn(scene: BenchScene) -> Fitted:
    """scikit-learn GaussianProcessRegressor (plain GPIS): C x RBF + White, one L-BFGS start."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    kernel = ConstantKernel(1.0, (1e-3, 1e3)) * RBF(0.25, (1e-2, 1e2)) + WhiteKernel(
        0.01, (1e-6, 1e1)
    )
    gpr = GaussianProcessRegressor(kernel=kernel, n_restarts_optimizer=0, random_state=0)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        gpr.fit(scene.X, scene.y)
    fit_s = time.perf_counter() - t0
    _, std = gpr.predict(scene.X, return_std=True)

    def predict(Xq: np.ndarray, return_std: bool = False) -> Any:
        return gpr.predict(Xq, return_std=return_std)

    return Fitted(predict, std**2, gpr, 0.0, fit_s, len(scene.y), {"kernel": str(gpr.kernel_)})


def default_mapping(ndim: int):
    """The default mapper's settings for a scene. The drone-geometry settings (length-scale
    floor 0.35 m, signal variance cap, internal value -d_in/r) describe 3D flights; the 2D
    paper shapes are a tenth of that scale (a 0.3 m square), so there they are the paper's."""
    from groundstation.mapping.settings import MappingSettings

    if ndim == 3:
        return MappingSettings()
    return MappingSettings(lengthscale_min=0.01, signal_var_max=1000.0, inside_value=-1.0)


def fit_default(scene: BenchScene, spacing: float, core: dict, **surface_kw: Any) -> Any:
    """An unfitted default mapper (``SurfaceModel``) for the scene's region at ``spacing``."""
    from groundstation.mapping.settings import SurfaceSettings

    surface = SurfaceSettings(
        region_min=scene.region_min, region_max=scene.region_max, spacing=spacing, **surface_kw
    )
    return core["model"].SurfaceModel(default_mapping(scene.ndim), surface)


def fit_default_model(scene: BenchScene, core: dict) -> Fitted:
    """The default mapper fitted on the raw stream (merge + exact/sparse as it decides)."""
    model = fit_default(scene, 0.05 if scene.ndim == 3 else 0.02, core)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(scene.X, scene.y, scene.ids, scene.t_ns)
    wall = time.perf_counter() - t0
    tm = dict(model.timings_)
    merge_s = float(tm.get("merge_s", 0.0))
    fit_s = float(tm.get("fit_s", wall - merge_s))
    byid = model.uncertainty_by_id()
    u = np.full(len(scene.y), np.nan)
    u[np.searchsorted(scene.ids, byid.ids)] = byid.u
    info = _hyper(model.fit_) | {"mode": model.mode_, "n_train": int(model.n_train_)}
    return Fitted(model.predict, u, model, merge_s, fit_s, int(model.n_train_), info)


# --------------------------------------------------------------------------- points


@dataclasses.dataclass(frozen=True)
class PointSpec:
    """One point of the chart.

    ``fit`` names the fit (points with the same ``fit`` share it); ``field`` is "dense",
    "band" (``narrow_band_field`` over the scene's grid at ``spacing``) or "model" (the default
    mapper's own ``mesh()``: its grid follows the length scale and the contacts' box).
    """

    label: str
    fit: str
    field: str
    spacing: float
    param: float | None = None


def method_specs(ndim: int, quick: bool) -> list[PointSpec]:
    """Every configuration of the issue, for 2D or 3D (see the module docstring)."""
    if ndim == 3:
        base, spacings = (0.1, (0.2, 0.1)) if quick else (0.05, (0.1, 0.05, 0.025))
        voxels = (0.1, 0.2) if quick else (0.05, 0.1, 0.2)
        inducing = (100, 300) if quick else (150, 300, 600, 1000)
    else:
        base, spacings = (0.05, (0.1, 0.05)) if quick else (0.02, (0.04, 0.02, 0.01))
        voxels, inducing = (0.01, 0.02, 0.04), ((50, 200) if quick else (50, 100, 200))
    specs = [
        PointSpec("gpis", "gpis", "dense", base),
        PointSpec(REFERENCE, REFERENCE, "dense", base),
        PointSpec(f"{REFERENCE} + band", REFERENCE, "band", base),
    ]
    specs += [PointSpec(f"merge {v:g} m + robust", f"merge{v:g}", "dense", base, v) for v in voxels]
    specs += [PointSpec(f"sparse M={m}", f"sparse{m}", "dense", base, m) for m in inducing]
    specs.append(PointSpec(DEFAULT, DEFAULT, "model" if ndim == 3 else "band", base))
    for sp in spacings:
        specs.append(PointSpec(f"default fit + dense {sp:g} m", DEFAULT, "dense", sp))
        specs.append(PointSpec(f"default fit + band {sp:g} m", DEFAULT, "band", sp))
    specs.append(PointSpec("sklearn GPR", "sklearn", "dense", base))
    return specs


def _do_fit(spec: PointSpec, scene: BenchScene, core: dict | None) -> Fitted:
    if spec.fit == "gpis":
        return fit_exact("gpis", scene)
    if spec.fit == REFERENCE:
        return fit_exact("robust", scene)
    if spec.fit == "sklearn":
        return fit_sklearn(scene)
    if core is None:
        raise ImportError("the speed core (groundstation.mapping.merge/sparse/field/model)")
    if spec.fit.startswith("merge"):
        return fit_merged(scene, float(spec.param), core)
    if spec.fit.startswith("sparse"):
        return fit_sparse(scene, int(spec.param), core)
    return fit_default_model(scene, core)


def measure(spec: PointSpec, fitted: Fitted, scene: BenchScene, core: dict | None) -> dict:
    """Field + surface of one point, timed, with Chamfer, e and Q."""
    rec: dict[str, Any] = {}
    mean, grid = None, None
    with PeakRSS() as mem:
        t0 = time.perf_counter()
        if spec.field == "model":
            surface = fitted.model.mesh()
            t1 = time.perf_counter()
            band = fitted.model.last_field_
            tm = fitted.model.timings_
            field_s, mesh_s = float(tm["field_s"]), float(tm["mesh_s"])
            rec["grid_spacing"] = band.grid.spacing
            rec["grid_points"] = band.grid.size
            rec["fraction_evaluated"] = band.fraction_evaluated
            mean, grid = band.values, band.grid
        else:
            grid = scene.grid(spec.spacing)
            if spec.field == "dense":
                mean = evaluate_field(fitted.predict, grid, n_train=fitted.n_train).mean
                rec["fraction_evaluated"] = 1.0
            else:
                if core is None:
                    raise ImportError("groundstation.mapping.field (narrow_band_field)")
                band = core["field"].narrow_band_field(fitted.predict, grid)
                mean = band.values
                rec["fraction_evaluated"] = band.fraction_evaluated
            t1 = time.perf_counter()
            surface = surface_of(mean, grid)
            field_s, mesh_s = t1 - t0, time.perf_counter() - t1
            rec["grid_spacing"], rec["grid_points"] = grid.spacing, grid.size
    rec.update(
        merge_s=fitted.merge_s,
        fit_s=fitted.fit_s,
        field_s=field_s,
        mesh_s=mesh_s,
        total_s=fitted.merge_s + fitted.fit_s + field_s + mesh_s,
        field_peak_mb=_f(mem.peak_mb),
        chamfer=chamfer_of(surface, scene),
        chamfer_near=chamfer_of(surface, scene, near=True),
        e=error_of(mean, grid, scene),
        e_near=error_of(mean, grid, scene, near=True),
        Q=clarity_of(fitted.u_raw, scene),
        n_train=fitted.n_train,
    )
    return rec


def run_scene(scene: BenchScene, specs: list[PointSpec], core: dict | None, bar: Any) -> list[dict]:
    """Every spec on one scene, in one process; each fit is made once and shared."""
    out: list[dict] = []
    cache: dict[str, tuple[Fitted, float] | str] = {}
    for i, spec in enumerate(specs):
        base = {
            "scene": scene.name,
            "label": spec.label,
            "fit": spec.fit,
            "field": spec.field,
            "spacing": spec.spacing,
            "n_raw": int(len(scene.y)),
        }
        bar.set_postfix_str(f"{scene.name}: {spec.label}")
        if spec.fit not in cache:
            try:
                with PeakRSS() as mem:
                    fitted = _do_fit(spec, scene, core)
                cache[spec.fit] = (fitted, mem.peak_mb)
            except ImportError as exc:
                cache[spec.fit] = f"skipped: {exc}"
            except Exception as exc:  # a failing method is a result of the bench
                cache[spec.fit] = f"error: {type(exc).__name__}: {exc}"
        entry = cache[spec.fit]
        if isinstance(entry, str):
            out.append(base | {"status": entry})
        else:
            fitted, fit_mb = entry
            try:
                rec = measure(spec, fitted, scene, core)
                peak = max(x for x in (fit_mb, rec.pop("field_peak_mb")) if x is not None)
                out.append(base | rec | {"status": "ok", "peak_mb": _f(peak), "info": fitted.info})
            except ImportError as exc:
                out.append(base | {"status": f"skipped: {exc}"})
            except Exception as exc:
                out.append(base | {"status": f"error: {type(exc).__name__}: {exc}"})
        if not any(s.fit == spec.fit for s in specs[i + 1 :]):
            cache.pop(spec.fit, None)  # free the fit's memory
        bar.update()
    return out


# --------------------------------------------------------------------------- session refits


def refit_session(
    obs: scenes3d.ObservationSet3D, every_s: float, core: dict | None, bar: Any
) -> list[dict]:
    """Refit the default mapper on the growing session every ``every_s`` seconds (one model)."""
    if core is None:
        return []
    scene = scene_3d(obs)
    model = fit_default(scene, 0.05, core)
    out = []
    end = obs.t_ns[-1] * 1e-9
    for t in np.arange(every_s, end + every_s, every_s):
        part = obs.upto(min(float(t), end))
        bar.set_postfix_str(f"session40: t = {t:.0f} s")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model.fit(part.X, part.y, part.ids, part.t_ns)
            mesh = model.mesh()
        tm = model.timings_
        total = sum(float(tm[k]) for k in ("merge_s", "fit_s", "field_s", "mesh_s"))
        out.append(
            {
                "t_s": float(t),
                "n_raw": int(len(part.y)),
                "n_train": int(model.n_train_),
                "mode": model.mode_,
                **{k: float(v) for k, v in tm.items()},
                "total_s": total,
                "chamfer": chamfer_of(mesh, scene),
                "chamfer_near": chamfer_of(mesh, scene, near=True),
                "covered": bool(t >= obs.covered_s),
            }
        )
        bar.update()
    return out


# --------------------------------------------------------------------------- summary


_NUMERIC = (
    "merge_s",
    "fit_s",
    "field_s",
    "mesh_s",
    "total_s",
    "chamfer",
    "chamfer_near",
    "e",
    "e_near",
    "Q",
    "peak_mb",
    "n_train",
    "grid_spacing",
    "fraction_evaluated",
)


def aggregate(points: list[dict], group: str) -> list[dict]:
    """One row per label: means over the group's scenes (the 2D shapes; 3D has one scene)."""
    rows: dict[str, dict] = {}
    for p in points:
        rows.setdefault(
            p["label"],
            {
                "group": group,
                "label": p["label"],
                "field": p["field"],
                "spacing": p["spacing"],
                "items": [],
            },
        )["items"].append(p)
    out = []
    for row in rows.values():
        ok = [p for p in row["items"] if p.get("status") == "ok"]
        row["status"] = "ok" if ok else row["items"][0].get("status", "?")
        row["scenes"] = len(ok)
        for key in _NUMERIC:
            vals = [p[key] for p in ok if p.get(key) is not None]
            row[key] = float(np.mean(vals)) if vals else None
        row["field_mesh_s"] = (
            row["field_s"] + row["mesh_s"] if ok and row["field_s"] is not None else None
        )
        del row["items"]
        out.append(row)
    front = pareto_front([(r["total_s"], r["chamfer_near"]) for r in out])
    for r, f in zip(out, front, strict=True):
        r["pareto"] = f
    return out


def pareto_front(points: list[tuple[float | None, float | None]]) -> list[bool]:
    """Non-dominated flags for (time, error) pairs (both smaller-is-better; None never wins)."""
    flags = []
    for i, (t, c) in enumerate(points):
        if t is None or c is None:
            flags.append(False)
            continue
        dominated = any(
            j != i
            and t2 is not None
            and c2 is not None
            and t2 <= t
            and c2 <= c
            and (t2 < t or c2 < c)
            for j, (t2, c2) in enumerate(points)
        )
        flags.append(not dominated)
    return flags


def ratios(rows: list[dict]) -> dict[str, float | None]:
    """Default vs exact robust GPIS in the same run (the issue's Done-when ratios)."""
    by = {r["label"]: r for r in rows}
    ref, dft = by.get(REFERENCE), by.get(DEFAULT)
    if not ref or not dft or ref["status"] != "ok" or dft["status"] != "ok":
        return {"fit_speedup": None, "field_mesh_speedup": None, "chamfer_ratio": None}

    def div(a: float | None, b: float | None) -> float | None:
        return None if a is None or b is None or b <= 0 else a / b

    return {
        "fit_speedup": div(ref["merge_s"] + ref["fit_s"], dft["merge_s"] + dft["fit_s"]),
        "field_mesh_speedup": div(ref["field_mesh_s"], dft["field_mesh_s"]),
        "chamfer_ratio": div(dft["chamfer_near"], ref["chamfer_near"]),
        "chamfer_full_ratio": div(dft["chamfer"], ref["chamfer"]),
    }


def refit_ratio(refits: list[dict]) -> dict[str, float | None]:
    """Refit time at the end vs right after the structure was first covered."""
    covered = [r for r in refits if r["covered"]]
    if len(covered) < 2:
        return {"covered_total_s": None, "end_total_s": None, "ratio": None}
    a, b = covered[0], refits[-1]
    return {
        "covered_t_s": a["t_s"],
        "covered_total_s": a["total_s"],
        "end_t_s": b["t_s"],
        "end_total_s": b["total_s"],
        "ratio": b["total_s"] / a["total_s"],
        "covered_n_raw": a["n_raw"],
        "end_n_raw": b["n_raw"],
    }


def _g(x: float | None, fmt: str) -> str:
    return "-" if x is None else format(x, fmt)


def render(groups: dict[str, list[dict]], rat: dict, refit: dict, meta: dict) -> str:
    """Markdown: every point per group, the default marked, ratios and the refit line."""
    lines = ["# pareto: wall time against accuracy", "", meta["note"], ""]
    for group, rows in groups.items():
        lines += [
            f"## {group}",
            "",
            "| method | field | grid m | n train | merge+fit s | field s | mesh s | total s "
            "| Chamfer near data mm | Chamfer whole grid mm | e near data mm | Q | peak MB "
            "| Pareto |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in rows:
            name = f"**{r['label']}** ★" if r["label"] == DEFAULT else r["label"]
            if r["status"] != "ok":
                lines.append(
                    f"| {name} | {r['field']} | {r['spacing']:g} | "
                    + " | ".join(["-"] * 10)
                    + f" | {r['status']} |"
                )
                continue
            fit = (r["merge_s"] or 0.0) + (r["fit_s"] or 0.0)
            ch = None if r["chamfer"] is None else 1e3 * r["chamfer"]
            chn = None if r["chamfer_near"] is None else 1e3 * r["chamfer_near"]
            e = None if r["e_near"] is None else 1e3 * r["e_near"]
            lines.append(
                f"| {name} | {r['field']} | {_g(r['grid_spacing'], '.3g')} | "
                f"{_g(r['n_train'], '.0f')} | {fit:.2f} | {_g(r['field_s'], '.2f')} | "
                f"{_g(r['mesh_s'], '.2f')} | {_g(r['total_s'], '.2f')} | {_g(chn, '.1f')} | "
                f"{_g(ch, '.1f')} | "
                f"{_g(e, '.1f')} | {_g(r['Q'], '.3g')} | {_g(r['peak_mb'], '.0f')} | "
                f"{'yes' if r['pareto'] else ''} |"
            )
        q = rat.get(group, {})
        lines += [
            "",
            f"Default vs {REFERENCE} in this run: fit speed-up "
            f"{_g(q.get('fit_speedup'), '.1f')}x, field+mesh speed-up "
            f"{_g(q.get('field_mesh_speedup'), '.1f')}x, Chamfer (near data) ratio "
            f"{_g(q.get('chamfer_ratio'), '.3f')} (whole grid "
            f"{_g(q.get('chamfer_full_ratio'), '.3f')}).",
            "",
        ]
    if refit.get("ratio") is not None:
        lines += [
            "## Refit time over the 40-minute session (default mapper)",
            "",
            f"Structure first covered at t = {refit['covered_t_s']:.0f} s "
            f"({refit['covered_n_raw']} raw observations): refit "
            f"{refit['covered_total_s']:.2f} s; at the end (t = {refit['end_t_s']:.0f} s, "
            f"{refit['end_n_raw']} raw): {refit['end_total_s']:.2f} s; ratio "
            f"{refit['ratio']:.2f} (goal <= 2).",
            "",
        ]
    return "\n".join(lines) + "\n"


def plot_pareto(groups: dict[str, list[dict]], path: Path) -> None:
    """Total wall time vs Chamfer and vs Q, one row per group; front joined, default starred."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(groups), 2, figsize=(11, 4.2 * len(groups)), squeeze=False)
    for i, (group, rows) in enumerate(groups.items()):
        ok = [r for r in rows if r["status"] == "ok" and r["total_s"]]
        for j, key in enumerate(("chamfer_near", "Q")):
            ax = axes[i, j]
            for r in ok:
                if r[key] is None:
                    continue
                dft, ref = r["label"] == DEFAULT, r["label"] == REFERENCE
                style = (
                    dict(marker="*", s=220, c="gold", edgecolors="k", zorder=5)
                    if dft
                    else (
                        dict(marker="s", s=50, c="tab:blue", zorder=4)
                        if ref
                        else dict(marker="o", s=25, c="tab:gray", zorder=3)
                    )
                )
                ax.scatter(r["total_s"], r[key], **style)
                ax.annotate(
                    r["label"],
                    (r["total_s"], r[key]),
                    fontsize=6,
                    xytext=(3, 3),
                    textcoords="offset points",
                )
            if key == "chamfer_near":
                fr = sorted((r["total_s"], r["chamfer_near"]) for r in ok if r["pareto"])
                if fr:
                    ax.plot(*zip(*fr, strict=True), "g--", lw=1, label="Pareto front")
                    ax.legend(fontsize=7)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("wall time: merge + fit + field + mesh, s (1 BLAS thread)", fontsize=8)
            ax.set_ylabel(
                "Chamfer near data, m" if key != "Q" else "Q (smaller: clearer)", fontsize=8
            )
            ax.set_title(f"{group}", fontsize=9)
            ax.grid(True, which="both", lw=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=70)
    plt.close(fig)


def plot_refits(refits: list[dict], covered_n: int | None, path: Path) -> None:
    """Refit time (stacked parts) against observations received for the default mapper."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    n = [r["n_raw"] for r in refits]
    bottom = np.zeros(len(refits))
    for key, col in (
        ("merge_s", "tab:gray"),
        ("fit_s", "tab:blue"),
        ("field_s", "tab:orange"),
        ("mesh_s", "tab:green"),
    ):
        vals = np.array([r.get(key, 0.0) for r in refits])
        ax.bar(
            n,
            vals,
            bottom=bottom,
            width=0.6 * (n[1] - n[0] if len(n) > 1 else 1.0),
            color=col,
            label=key[:-2],
        )
        bottom += vals
    if covered_n is not None:
        ax.axvline(covered_n, color="k", ls="--", lw=1, label="structure first covered")
    ax2 = ax.twinx()
    ax2.plot(n, [r["n_train"] for r in refits], "r.-", lw=1, label="training points (merged)")
    ax2.set_ylabel("merged training points", fontsize=8, color="r")
    ax.set_xlabel("raw observations received", fontsize=8)
    ax.set_ylabel("refit wall time, s", fontsize=8)
    ax.set_title("default mapper: refit time over a 40-minute session", fontsize=9)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=70)
    plt.close(fig)


# --------------------------------------------------------------------------- command


def json_default(x: Any) -> Any:
    if isinstance(x, np.integer | np.floating | np.bool_):
        return x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return str(x)
