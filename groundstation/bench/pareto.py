"""``groundstation bench pareto``: speed against accuracy of the mapping engines, and refit time
over a session.

**The paper-like 3D set** (``scenes3d.paper3d``: ~2,300 observations in time order on the SITL
``paper`` scene; strokes of contacts with their internal points and normals, free space along the
paths flown, isolated gusts and three gust clusters) and its **clean control** (the same set
without false contacts). Methods, each timed as fit + field + mesh in this one process with BLAS
limited to one thread:

- ``gpis``: the paper's plain GPIS, exact, on every row; dense field on the scene's grid.
- ``sklearn``: an independent plain GP (scikit-learn ``GaussianProcessRegressor``, C x RBF +
  White, one L-BFGS start), same rows and grid: a check on our own GP code.
- ``robust_exact``: the paper's robust GPIS (Student-t, variational EM), exact, every row; dense
  field; a contact is flagged when its u exceeds the fit's noise floor by 0.3 (the legacy rule).
- ``legacy``: the previous default mapper (``mapping.engine = legacy`` with its measured settings:
  length-scale floor 0.35 m), through :class:`~groundstation.mapping.mapper.Mapper`.
- ``default``: the map engine v2 (event mixture, tiles), through the same ``Mapper``.

Metrics (metres, against the scene's true surface): Chamfer distance near the touched surface
(mesh and truth within 0.5 m of a true touch), the share of the touched surface (within 0.3 m of a
true touch) farther than 0.1 m from the mesh (missing), the share and area of the mesh farther
than 0.15 m from the truth (phantom) and its largest patch, and the shares of cluster gusts,
isolated gusts and touches whose event is flagged false. A method whose accuracy is as good with
false contacts as without is robust; one whose clean control is no better is smoothing.

**The 40-minute session** (``scenes3d.session40``): the legacy and the default mapper refitted
every ``refit_every`` seconds of the growing stream (warm, as live): wall time of each refit
(fit + mesh) against the raw observations so far, and the metrics above of the map each ends
the session with (a fast refit of a wrong map is no result).

Outputs in ``--out``: ``pareto.md``, ``pareto.png`` (total time against Chamfer near the touched
surface, full set and clean control), ``refit_vs_session.png`` and ``results.json``.
"""

from __future__ import annotations

import math
import os
import threading
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.bench import scenes3d
from groundstation.mapping.metrics import chamfer_distance, phantom_patches, sample_mesh_surface
from groundstation.mapping.surface import SurfaceMesh

DEFAULT = "default"
LEGACY = "legacy"
REFERENCE = "robust_exact"
SKLEARN = "sklearn"
EXACT = ("gpis", SKLEARN, REFERENCE)
METHODS = ("gpis", SKLEARN, REFERENCE, LEGACY, DEFAULT)
N_SAMPLES = 20000
TOUCHED_M = 0.3  # true surface within this of a true touch is "touched"
NEAR_M = 0.5  # Chamfer looks at mesh and truth within this of a true touch
MISSING_M = 0.1
PHANTOM_M = 0.15
#: The previous default mapper's settings (what the legacy engine was measured with).
LEGACY_SETTINGS = (
    "mapping.engine=legacy",
    "mapping.lengthscale_min=0.35",
    "mapping.prior_mean=0.0",
    "surface.max_std_fraction=0.7",
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


def surface_metrics(mesh: SurfaceMesh | None, data: scenes3d.ObservationSet3D) -> dict:
    """Chamfer near the touched surface, missing, phantom (module docstring)."""
    from scipy.spatial import cKDTree

    out: dict[str, float | None] = dict.fromkeys(
        ("chamfer_near", "missing", "phantom_share", "phantom_m2", "phantom_max_patch_m2",
         "mesh_to_truth_median", "truth_to_mesh_median"),
    )  # fmt: skip
    if mesh is None or mesh.is_empty:
        out["missing"] = 1.0
        return out
    truth = data.truth_samples
    touched = cKDTree(data.touched)
    pts = sample_mesh_surface(mesh.vertices, mesh.faces, N_SAMPLES, seed=0)
    t_near = truth[touched.query(truth)[0] <= TOUCHED_M]
    d, _ = cKDTree(pts).query(t_near)
    m2t = np.abs(data.sdf(pts))
    pts_n = pts[touched.query(pts)[0] <= NEAR_M]
    t_n = truth[touched.query(truth)[0] <= NEAR_M]
    v, f = mesh.vertices, mesh.faces
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    patches = phantom_patches(v, f, data.sdf, threshold=PHANTOM_M)
    phantom = float(sum(p.area_m2 for p in patches))
    out.update(
        chamfer_near=_f(chamfer_distance(pts_n, t_n)) if len(pts_n) and len(t_n) else None,
        missing=float(np.mean(d > MISSING_M)),
        phantom_share=phantom / max(float(area.sum()), 1e-12),
        phantom_m2=phantom,
        phantom_max_patch_m2=patches[0].area_m2 if patches else 0.0,
        mesh_to_truth_median=float(np.median(m2t)),
        truth_to_mesh_median=float(np.median(d)),
    )
    return out


def flag_metrics(flagged_events: set[int], data: scenes3d.ObservationSet3D) -> dict:
    """Shares of cluster gusts, isolated gusts and touches whose event is flagged."""
    ev, kind = data.event, data.kind
    clu = np.zeros(kind.shape, dtype=bool) if data.cluster is None else data.cluster

    def share(sel: np.ndarray) -> float | None:
        evs = set(ev[sel].tolist())
        return float(np.mean([e in flagged_events for e in evs])) if evs else None

    return {
        "cluster_flagged": share(clu & (kind == scenes3d.FALSE_CONTACT)),
        "isolated_flagged": share(~clu & (kind == scenes3d.FALSE_CONTACT)),
        "touch_flagged": share(kind == scenes3d.CONTACT),
    }


# --------------------------------------------------------------------------- methods


def _settings(overrides: tuple[str, ...]):
    from groundstation.config import load_config

    return load_config(None, list(overrides))


def run_mapper(data: scenes3d.ObservationSet3D, overrides: tuple[str, ...] = ()) -> dict:
    """The production mapper on the whole set: one fit and its mesh, timed."""
    from groundstation.mapping.mapper import Mapper

    cfg = _settings(overrides)
    mapper = Mapper.from_config(cfg)
    mapper.add(data.observations())
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = mapper.refit()
    wall = time.perf_counter() - t0
    rec = {"total_s": wall, "fit_s": _f(fit.timings.get("fit_s")),
           "mesh_s": _f(fit.timings.get("mesh_s")), "reliable": fit.reliable,
           "lengthscale": _f(fit.hyperparameters.get("lengthscale"))}  # fmt: skip
    rec |= surface_metrics(fit.mesh, data)
    rec |= flag_metrics(set(fit.flagged_events), data)
    return rec


def _sklearn_gpr() -> Any:
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    kernel = ConstantKernel(1.0, (1e-3, 1e3)) * RBF(0.25, (1e-2, 1e2)) + WhiteKernel(
        0.01, (1e-6, 1e1)
    )
    return GaussianProcessRegressor(kernel=kernel, n_restarts_optimizer=0, random_state=0)


def run_exact(kind: str, data: scenes3d.ObservationSet3D, spacing: float) -> dict:
    """Plain GPIS (ours or scikit-learn's) or exact robust GPIS on every row, dense field on the
    scene's grid, mesh."""
    from groundstation.mapping import GPIS, RobustGPIS
    from groundstation.mapping.grid import Grid, evaluate_field
    from groundstation.mapping.surface import extract_surface

    sc = data.scene
    model = {"gpis": GPIS, SKLEARN: _sklearn_gpr, REFERENCE: RobustGPIS}[kind]()
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        model.fit(data.X, data.y)
    t1 = time.perf_counter()
    grid = Grid.from_bounds(sc.region_min, sc.region_max, spacing)
    field = evaluate_field(model.predict, grid, n_train=len(data.y))
    mesh = extract_surface(field.mean, grid)
    t2 = time.perf_counter()
    ell = getattr(model, "lengthscale_", None)
    if kind == SKLEARN:
        ell = model.kernel_.k1.k2.length_scale
    rec = {"total_s": t2 - t0, "fit_s": t1 - t0, "mesh_s": t2 - t1, "reliable": True,
           "lengthscale": _f(ell)}  # fmt: skip
    rec |= surface_metrics(mesh, data)
    flagged: set[int] = set()
    if kind == REFERENCE:
        u = np.asarray(model.uncertainty_)
        floor = model.beta_ / (model.alpha_ + 0.5)
        sus = (data.y == 0) & (u > floor + 0.3)
        for e in set(data.event[data.y == 0].tolist()):
            rows = (data.event == e) & (data.y == 0)
            if np.mean(sus[rows]) >= 0.5:
                flagged.add(e)
    rec |= flag_metrics(flagged, data)
    return rec


def count_points(methods: tuple[str, ...] | list[str]) -> int:
    """How many fits :func:`run_paper3d` makes: mappers also run on the clean control."""
    return sum(1 if m in EXACT else 2 for m in methods)


def run_paper3d(data: scenes3d.ObservationSet3D, methods: tuple[str, ...], spacing: float,
                bar: Any) -> list[dict]:  # fmt: skip
    """Every method on the set and (mappers) on its clean control."""
    rows = []
    clean = data.clean()
    for m in methods:
        for which, d in (("full", data), ("clean", clean)):
            if which == "clean" and m in EXACT:
                continue
            bar.set_postfix_str(f"paper3d {m} {which}")
            try:
                with PeakRSS() as mem:
                    if m == DEFAULT:
                        rec = run_mapper(d)
                    elif m == LEGACY:
                        rec = run_mapper(d, LEGACY_SETTINGS)
                    else:
                        rec = run_exact(m, d, spacing)
                rec["peak_mb"] = _f(mem.peak_mb)
                rec["status"] = "ok"
            except Exception as exc:  # a failing method is a result of the bench
                rec = {"status": f"error: {type(exc).__name__}: {exc}"}
            rows.append({"method": m, "set": which, "n_raw": len(d.y)} | rec)
            bar.update()
    return rows


def refit_session(session: scenes3d.ObservationSet3D, every_s: float, bar: Any) -> list[dict]:
    """The legacy and the default mapper refitted (warm) on the growing session."""
    from groundstation.mapping.mapper import Mapper

    out = []
    end = session.t_ns[-1] * 1e-9
    obs = session.observations()
    t_obs = np.array([o.t_ns for o in obs])
    for name, overrides in ((DEFAULT, ()), (LEGACY, LEGACY_SETTINGS)):
        mapper = Mapper.from_config(_settings(overrides))
        k0 = 0
        for t in np.arange(every_s, end + every_s, every_s):
            k1 = int(np.searchsorted(t_obs, int(min(t, end) * 1e9), side="right"))
            mapper.add(obs[k0:k1])
            k0 = k1
            bar.set_postfix_str(f"session40 {name}: t = {t:.0f} s")
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                fit = mapper.refit()
            wall = time.perf_counter() - t0
            out.append({
                "method": name, "t_s": float(t), "n_raw": k1, "total_s": wall,
                "fit_s": _f(fit.timings.get("fit_s")), "mesh_s": _f(fit.timings.get("mesh_s")),
                "n_train": fit.hyperparameters.get("n_train"),
                "covered": bool(t >= session.covered_s),
            })  # fmt: skip
            bar.update()
        # the map the session ends with, scored like the 3D set's (its clean control is not run)
        out[-1]["final"] = surface_metrics(fit.mesh, session) | flag_metrics(
            set(fit.flagged_events), session
        )
    return out


def refit_summary(refits: list[dict]) -> dict:
    """Median and p95 refit time per method, and after the structure was first covered."""
    out = {}
    for m in {r["method"] for r in refits}:
        t = np.array([r["total_s"] for r in refits if r["method"] == m])
        tc = np.array([r["total_s"] for r in refits if r["method"] == m and r["covered"]])
        out[m] = {
            "refits": int(t.size),
            "median_s": _f(np.median(t)) if t.size else None,
            "p95_s": _f(np.percentile(t, 95)) if t.size else None,
            "max_s": _f(t.max()) if t.size else None,
            "covered_median_s": _f(np.median(tc)) if tc.size else None,
            "final": next((r["final"] for r in refits if r["method"] == m and "final" in r), None),
        }
    return out


def pareto_front(points: list[tuple[float | None, float | None]]) -> list[bool]:
    """Which (cost, error) points no other point beats in both (None: never on the front)."""
    out = []
    for i, (c, e) in enumerate(points):
        if c is None or e is None:
            out.append(False)
            continue
        dominated = any(
            j != i and c2 is not None and e2 is not None and c2 <= c and e2 <= e
            and (c2 < c or e2 < e)
            for j, (c2, e2) in enumerate(points)
        )  # fmt: skip
        out.append(not dominated)
    return out


# --------------------------------------------------------------------------- outputs


def _g(x: Any, fmt: str) -> str:
    return "-" if x is None or (isinstance(x, float) and not math.isfinite(x)) else format(x, fmt)


def render(rows: list[dict], refits: dict, note: str) -> str:
    """The markdown tables."""
    lines = [
        "# Speed against accuracy of the mapping engines", "", note, "",
        "## Paper-like 3D set (and its clean control)", "",
        "| method | set | total s | Chamfer near (mm) | missing | phantom share | phantom max "
        "patch m^2 | cluster flagged | isolated flagged | touches flagged | l (m) | status |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]  # fmt: skip
    for r in rows:
        ch = r.get("chamfer_near")
        lines.append(
            f"| {r['method']} | {r['set']} | {_g(r.get('total_s'), '.1f')} | "
            f"{_g(None if ch is None else 1e3 * ch, '.1f')} | {_g(r.get('missing'), '.3f')} | "
            f"{_g(r.get('phantom_share'), '.3f')} | {_g(r.get('phantom_max_patch_m2'), '.3f')} | "
            f"{_g(r.get('cluster_flagged'), '.2f')} | {_g(r.get('isolated_flagged'), '.2f')} | "
            f"{_g(r.get('touch_flagged'), '.3f')} | {_g(r.get('lengthscale'), '.3f')} | "
            f"{r.get('status', '')} |"
        )
    if refits:
        lines += ["", "## Refits over the session (warm, as live)", "",
                  "| method | refits | median s | p95 s | max s | median s once covered |",
                  "|---|---|---|---|---|---|"]  # fmt: skip
        for m, s in sorted(refits.items()):
            lines.append(
                f"| {m} | {s['refits']} | {_g(s['median_s'], '.2f')} | {_g(s['p95_s'], '.2f')} | "
                f"{_g(s['max_s'], '.2f')} | {_g(s['covered_median_s'], '.2f')} |"
            )
        lines += ["", "The map each ends the session with (metrics as for the 3D set):", "",
                  "| method | Chamfer near (mm) | missing | phantom share | phantom max patch m^2 "
                  "| gusts flagged | touches flagged |",
                  "|---|---|---|---|---|---|---|"]  # fmt: skip
        for m, s in sorted(refits.items()):
            f = s.get("final") or {}
            ch = f.get("chamfer_near")
            lines.append(
                f"| {m} | {_g(None if ch is None else 1e3 * ch, '.1f')} | "
                f"{_g(f.get('missing'), '.3f')} | {_g(f.get('phantom_share'), '.3f')} | "
                f"{_g(f.get('phantom_max_patch_m2'), '.2f')} | "
                f"{_g(f.get('isolated_flagged'), '.2f')} | {_g(f.get('touch_flagged'), '.3f')} |"
            )
    return "\n".join(lines) + "\n"


def plot_pareto(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    ok = [r for r in rows if r.get("status") == "ok" and r.get("chamfer_near") is not None]
    front = pareto_front([(r["total_s"], r["chamfer_near"]) for r in ok if r["set"] == "full"])
    k = 0
    for r in ok:
        marker = "o" if r["set"] == "full" else "s"
        color = {"gpis": "tab:gray", SKLEARN: "tab:purple", REFERENCE: "tab:blue",
                 LEGACY: "tab:orange", DEFAULT: "tab:green"}[r["method"]]  # fmt: skip
        edge = "black" if r["set"] == "full" and front[k] else "none"
        k += r["set"] == "full"
        ax.scatter(r["total_s"], 1e3 * r["chamfer_near"], marker=marker, c=color, edgecolors=edge,
                   s=70, label=f"{r['method']} ({r['set']})")  # fmt: skip
    ax.set_xscale("log")
    ax.set_xlabel("fit + field + mesh, s (one BLAS thread)")
    ax.set_ylabel("Chamfer near the touched surface, mm")
    ax.set_title("paper-like 3D set: circles with false contacts, squares clean control")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_refits(refits: list[dict], covered_s: float | None, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for m, color in ((DEFAULT, "tab:green"), (LEGACY, "tab:orange")):
        r = [x for x in refits if x["method"] == m]
        if r:
            ax.plot([x["t_s"] / 60 for x in r], [x["total_s"] for x in r], "o-", ms=3,
                    color=color, label=m)  # fmt: skip
    if covered_s:
        ax.axvline(covered_s / 60, color="gray", ls=":", label="structure first covered")
    ax.set_xlabel("session time, min")
    ax.set_ylabel("refit (fit + mesh), s")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def json_default(x: Any) -> Any:
    if isinstance(x, np.integer | np.floating | np.bool_):
        return x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return str(x)


__all__ = [
    "DEFAULT", "EXACT", "LEGACY", "METHODS", "REFERENCE", "SKLEARN", "PeakRSS", "count_points",
    "flag_metrics", "json_default", "pareto_front", "plot_pareto", "plot_refits",
    "refit_session", "refit_summary", "render", "run_exact", "run_mapper", "run_paper3d",
    "surface_metrics",
]  # fmt: skip
