"""``groundstation bench speed``: fit and prediction times of the estimators and the mapper.

One process, BLAS limited to one thread (threadpoolctl), on the paper's scales:

- **2D, n ~ 590**: the paper's circle (``shapes2d``, seed 0): ``GPIS`` and ``RobustGPIS`` cold fits.
- **3D, n ~ 2,300**: the paper-like set (``scenes3d.paper3d``, seed 0): exact ``RobustGPIS``
  cold fit; the default mapper (``SurfaceModel``, event mixture in tiles) cold on all of it, and
  a warm refit after the last 2 % of the observations arrive (what the mapper does every few
  seconds in a session: only the tiles they touch are refitted); the previous default (legacy
  engine: merge + exact/sparse robust GPIS) cold, for comparison.
- **Prediction on the paper's grid** (8 x 4 x 2 m at 0.05 m, 161 x 81 x 41 = 534,681 points):
  mean, and mean + std, of the exact model and of the default mapper, in chunks of
  ``chunk_mb`` (the peak RSS above the process baseline is reported: chunking keeps it at a
  few hundred MB), and the default mapper's own narrow-band mesh.

- **Replay throughput** (``--replay LOG``, repeatable): the decode + detect path of ``replay``
  (everything before the mapper: MCAP reading, MAVLink/NatNet decoding, alignment, the contact
  stage; :func:`groundstation.pipeline.offline.detect_offline`) on each log, as wall and CPU
  seconds per minute of log and times real time. ``--replay-only`` skips the estimator rows.

Results: a markdown table (stdout and ``--out``/speed.md) and ``speed.json``. ``--quick`` skips
the exact 3D fit and the exact std prediction (minutes each) and shrinks the 3D set.
"""

from __future__ import annotations

import time
import warnings
from typing import Any

import numpy as np

from groundstation.bench import scenes3d, shapes2d
from groundstation.bench.pareto import PeakRSS
from groundstation.errors import ConvergenceWarning
from groundstation.mapping import GPIS, RobustGPIS
from groundstation.mapping.grid import Grid
from groundstation.mapping.legacy import LegacySurfaceModel
from groundstation.mapping.model import SurfaceModel
from groundstation.mapping.settings import MappingSettings, SurfaceSettings

PAPER_GRID = ((0.0, 0.0, 0.0), (8.0, 4.0, 2.0), 0.05)


def _timed(fn, *args, **kw) -> tuple[Any, float, float]:
    """(result, wall seconds, peak MB above the start) of ``fn(*args, **kw)``."""
    with PeakRSS() as rss, warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        t0 = time.perf_counter()
        out = fn(*args, **kw)
        wall = time.perf_counter() - t0
    return out, wall, rss.peak_mb


def _row(rows: list[dict], what: str, n: int, seconds: float, mb: float, note: str = "") -> None:
    rows.append({"what": what, "n": n, "seconds": seconds, "peak_mb": mb, "note": note})
    print(f"bench speed: {what}: {seconds:.2f} s ({note})", flush=True)


def measure(quick: bool = False, chunk_mb: float = 64.0) -> list[dict]:
    """Every row of the table (module docstring)."""
    rows: list[dict] = []
    circle = shapes2d.make_dataset(shapes2d.make_shape("circle"), np.random.default_rng(0))
    for cls in (GPIS, RobustGPIS):
        m, s, mb = _timed(cls().fit, circle.X, circle.y)
        _row(rows, f"2D {cls.__name__} cold fit", len(circle.y), s, mb,
             f"{m.n_iter_} iterations")  # fmt: skip

    n_contacts = 300 if quick else 1100
    obs = scenes3d.paper3d(0, n_contacts=n_contacts, n_external=int(n_contacts * 450 / 1100))
    X, y, ids, t = obs.X, obs.y, obs.ids, obs.t_ns
    lo, hi, spacing = PAPER_GRID
    grid = Grid.from_bounds(np.array(lo), np.array(hi), spacing)
    pts = grid.points()
    exact = None
    if not quick:
        exact, s, mb = _timed(RobustGPIS(chunk_mb=chunk_mb).fit, X, y)
        note = f"{exact.n_iter_} iterations, start {exact.init_used_}, alpha {exact.alpha_:.3g}"
        _row(rows, "3D exact RobustGPIS cold fit", len(y), s, mb, note)

    surface = SurfaceSettings(spacing=spacing, chunk_mb=chunk_mb)
    observations = obs.observations()
    k = int(0.98 * len(observations))
    model = SurfaceModel(MappingSettings(), surface)
    _, s, mb = _timed(model.fit, observations)
    _row(rows, "3D default mapper cold fit", len(y), s, mb,
         f"{model.summary_.n_train} rows in {int(model.timings_['tiles'])} tiles")  # fmt: skip
    warm = SurfaceModel(MappingSettings(), surface)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        warm.fit(observations[:k])
    _, s, mb = _timed(warm.fit, observations)
    tiles = f"{int(warm.timings_['tiles_refit'])} of {int(warm.timings_['tiles'])} tiles refitted"
    _row(rows, "3D default mapper warm refit (+2 % observations)", len(y), s, mb, tiles)
    legacy_settings = MappingSettings(engine="legacy", lengthscale_min=0.35, prior_mean=0.0)
    legacy = LegacySurfaceModel(legacy_settings, surface)
    _, s, mb = _timed(legacy.fit, X, y, ids, t)
    _row(rows, "3D previous default (legacy engine) cold fit", len(y), s, mb,
         f"{legacy.mode_}, {legacy.n_train_} merged rows")  # fmt: skip

    if exact is not None:
        _, s, mb = _timed(exact.predict, pts)
        _row(rows, "exact model: mean on the paper grid", len(pts), s, mb, f"n = {len(y)}")
        _, s, mb = _timed(exact.predict, pts, return_std=True)
        _row(rows, "exact model: mean + std on the paper grid", len(pts), s, mb, f"n = {len(y)}")
    n_rows = model.summary_.n_train
    _, s, mb = _timed(model.predict, pts)
    _row(rows, "default mapper: mean on the paper grid", len(pts), s, mb, f"{n_rows} rows")
    _, s, mb = _timed(model.predict, pts, return_std=True)
    _row(rows, "default mapper: mean + std on the paper grid", len(pts), s, mb, f"{n_rows} rows")
    mesh, s, mb = _timed(model.mesh)
    _row(rows, "default mapper: narrow-band field + mesh + vertex std (every tile)",
         len(mesh.vertices), s, mb, f"{len(mesh.faces)} triangles")  # fmt: skip
    return rows


def replay_throughput(paths: list[str]) -> list[dict]:
    """Decode + detect seconds of each log in ``paths`` (module docstring), one row per log."""
    from pathlib import Path

    from groundstation.pipeline.offline import detect_offline

    rows: list[dict] = []
    for path in paths:
        c0 = time.process_time()
        run, wall, mb = _timed(detect_offline, str(path))
        cpu = time.process_time() - c0
        minutes = run.duration_s / 60.0
        note = (
            f"{run.duration_s:.0f} s of log: {wall / minutes:.2f} s wall, {cpu / minutes:.2f} s "
            f"CPU per log-minute, {run.duration_s / wall:.1f}x real time; "
            f"{run.stats.get('imu', 0):,} IMU samples, {len(run.observations):,} observations"
        )
        _row(rows, f"replay decode + detect: {Path(path).name}", run.stats.get("imu", 0), wall,
             mb, note)  # fmt: skip
    return rows


def table(rows: list[dict]) -> str:
    lines = ["| measurement | n / points | seconds | peak MB | note |", "|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['what']} | {r['n']:,} | {r['seconds']:.2f} | {r['peak_mb']:.0f} | {r['note']} |"
        )
    return "\n".join(lines) + "\n"
