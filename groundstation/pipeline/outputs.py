"""Files of a pipeline run: ``mesh.ply``, ``observations.csv``, ``report.json``, ``snapshots/``,
``report.html`` and ``replay.mcap``.

- ``mesh.ply``: the last good mesh, vertex colours = predictive std (``mapping.surface``).
- ``observations.csv``: ``id, x, y, z, label, t_s, event_id, u, flag, p_false, dv_mps, rebound,
  sigma_m, p_false_map, awaiting`` per observation; ``t_s`` is the observation's data (source)
  time in seconds from the log start; ``u``/``flag`` (1: flagged false) from the final fit (empty
  when the observation was not in a fit); ``p_false``, ``dv_mps``, ``rebound``, ``sigma_m``: the
  detector's evidence for its event (empty when none); ``p_false_map``: the map's posterior that
  its event is false; ``awaiting`` 1: flagged only because no other touch corroborates it (a
  second touch beside it would keep it; ``mapper.lone_flag_p``).
- ``report.json``: :func:`build_report` (NaN written as ``null``).
- ``snapshots/snapshot_<fit>.png``: the meshes of the last few fits with the observations
  coloured by flag state (``viewer.headless.render_snapshot``: the three-view renderer with
  metre axes that live headless views use too; the true structure outlined when the log has
  ground truth).
- ``report.html``: the flight report (``pipeline.report``), self-contained.
- ``replay.mcap``: the replay's output recording with Foxglove channels
  (``openformats.replay_output``), when the caller filled a :class:`ReplayOutput`.
"""

from __future__ import annotations

import csv
import json
import math
import statistics
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from groundstation.contact.detector import LABEL_SURFACE
from groundstation.mapping.mapper import (
    FLAG_AWAITING,
    FLAG_FALSE_POSITIVE,
    REFIT_STAGES,
    FitResult,
)
from groundstation.mapping.settings import SurfaceSettings
from groundstation.pipeline.offline import PipelineResult
from groundstation.pipeline.scoring import MASK_CURVE, DetectedEvent, mask_curve, score


def detected_events(result: PipelineResult) -> list[DetectedEvent]:
    """Begin messages of the run with the final fit's flag and their contact points."""
    flagged = set(result.final.flagged_events) if result.final is not None else set()
    points: dict[int, list[tuple[float, float, float]]] = {}
    for o in result.observations:
        if o.label == LABEL_SURFACE:
            points.setdefault(int(o.event_id), []).append(tuple(map(float, o.position)))
    return [
        DetectedEvent(
            int(e.payload["id"]),
            int(e.header.source_ns),
            e.payload["id"] in flagged,
            tuple(points.get(int(e.payload["id"]), ())),
        )
        for e in result.events
        if e.payload["state"] == "begin"
    ]


#: Meshes a replay with outputs keeps for replay.mcap (every fit's mesh up to this many; older
#: ones are dropped): ``replay --out`` and every batch task, so both write the same file.
KEEP_MESHES = 200

#: report.json keys that measure wall-clock time: they differ between two runs of the same log
#: (everything else in a report is a function of the log and the settings).
TIMING_KEYS = frozenset({"wall_s", "refit_s_median", "refit_s_p95", "refit_s_max", "refit_time_s"})


def refit_time(fits: Sequence[FitResult]) -> dict:
    """Where the refits' time went (issue 13, Build point 7): per part of a refit
    (:data:`~groundstation.mapping.mapper.REFIT_STAGES`) the seconds summed over every refit
    that reports it, their share of the summed ``total_s`` and the part's p95 over refits."""
    total = sum(f.timings.get("total_s", 0.0) for f in fits)
    out = {}
    for stage in REFIT_STAGES:
        values = [float(f.timings[stage]) for f in fits if stage in f.timings]
        if values:
            out[stage.removesuffix("_s")] = {
                "sum_s": float(sum(values)),
                "share": float(sum(values) / total) if total > 0 else math.nan,
                "p95_s": float(np.percentile(values, 95)),
            }
    return out


def build_report(
    result: PipelineResult, *, scored: bool = True, mask_fractions: Sequence[float] = ()
) -> dict:
    """Every report key of ``groundstation replay`` (truth metrics when the log has truth).

    ``mask_fractions``: the stricter confidence masks the final mesh is also scored at
    (``mask_curve``, :func:`~groundstation.pipeline.scoring.mask_curve`; :func:`stricter_masks`
    of the run's settings), when the mesh is the final fit's own (its kernel's prior std)."""
    fits = result.fits
    refit_s = [f.timings["total_s"] for f in fits if "total_s" in f.timings]
    minutes = result.duration_s / 60.0
    rep: dict = {
        "log": result.log_path,
        "mode": result.mode,
        "duration_s": result.duration_s,
        "contacts": result.contacts,
        "contacts_per_min": result.contacts / minutes if minutes > 0 else math.nan,
        "observations": len(result.observations),
        "refits": len(fits),
        "refit_s_median": statistics.median(f.timings.get("total_s", math.nan) for f in fits)
        if fits
        else math.nan,
        "refit_s_p95": float(np.percentile(refit_s, 95)) if refit_s else math.nan,
        "refit_s_max": max(refit_s) if refit_s else math.nan,
        "refit_time_s": refit_time(fits),
        "refits_unreliable": sum(not f.reliable for f in fits),
        "flagged_events": list(result.final.flagged_events) if result.final else [],
        "awaiting_events": list(result.final.awaiting_events) if result.final else [],
        "final_fit": None
        if result.final is None
        else {
            "fit_index": result.final.fit_index,
            "reliable": result.final.reliable,
            "reasons": list(result.final.reasons),
            "mesh_fit_index": result.final.mesh_fit_index,
            "hyperparameters": result.final.hyperparameters,
        },
        "wall_s": result.wall_s,
        "gaps": result.gaps,
        "stats": result.stats,
    }
    if scored and result.truth:
        mesh = result.final.mesh if result.final is not None else None
        rep.update(score(mesh, detected_events(result), result.truth))
        final = result.final
        sf2 = None if final is None else final.hyperparameters.get("signal_var")
        own = final is not None and final.mesh_fit_index == final.fit_index
        if mask_fractions and own and sf2 is not None and math.isfinite(float(sf2)):
            rep["mask_curve"] = mask_curve(
                mesh, result.truth, math.sqrt(float(sf2)), mask_fractions
            )
    return rep


def stricter_masks(surface: SurfaceSettings) -> tuple[float, ...]:
    """The fractions of :data:`~groundstation.pipeline.scoring.MASK_CURVE` stricter than the
    configured ``surface.max_std_fraction`` (the mesh holds no face a looser one would add)."""
    return tuple(f for f in MASK_CURVE if f < surface.max_std_fraction - 1e-9)


def _clean(obj):
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    if isinstance(obj, np.generic):
        return _clean(obj.item())
    return obj


def write_report(report: dict, path: str | Path) -> Path:
    """``report.json`` with NaN/inf as null."""
    path = Path(path)
    path.write_text(json.dumps(_clean(report), indent=2, sort_keys=True) + "\n")
    return path


def write_observations_csv(result: PipelineResult, path: str | Path) -> Path:
    """``observations.csv`` (columns in the module docstring)."""
    fit = result.final
    lookup: dict[int, tuple[float, int, float]] = {}
    if fit is not None:
        post = fit.p_false if fit.p_false is not None else np.full(len(fit.ids), np.nan)
        for i, u, f, p in zip(
            fit.ids.tolist(), fit.u.tolist(), fit.flags.tolist(), post.tolist(), strict=True
        ):
            lookup[i] = (u, f, p)
    path = Path(path)

    def num(v, spec: str) -> str:
        return "" if v is None or not math.isfinite(v) else format(v, spec)

    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow([
            "id", "x", "y", "z", "label", "t_s", "event_id", "u", "flag",
            "p_false", "dv_mps", "rebound", "sigma_m", "p_false_map", "awaiting",
        ])  # fmt: skip
        for o in sorted(result.observations, key=lambda o: o.id):
            u, f, p = lookup.get(o.id, (None, None, None))
            x, y, z = (float(v) for v in o.position)
            evidence = o.label != 1 and math.isfinite(o.p_false)
            w.writerow([
                o.id, f"{x:.4f}", f"{y:.4f}", f"{z:.4f}", int(o.label),
                f"{(o.t_ns - result.start_ns) / 1e9:.4f}", o.event_id,
                num(u, ".6g"), "" if f is None else int(f) & FLAG_FALSE_POSITIVE,
                num(o.p_false, ".4f"), num(o.dv_mps, ".4f"),
                int(o.rebound) if evidence else "", num(o.sigma_m, ".4f"), num(p, ".4f"),
                "" if f is None else int(bool(int(f) & FLAG_AWAITING)),
            ])  # fmt: skip
    return path


def write_snapshots(result: PipelineResult, folder: str | Path, last: int = 3) -> list[Path]:
    """PNG snapshots of the last ``last`` fits that still hold a mesh (captions count contacts
    as the status line does: events begun by then and the events that fit flags)."""
    from groundstation.viewer.headless import render_snapshot
    from groundstation.viewer.scene import ViewModel

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    outline = ((result.truth or {}).get("scene") or {}).get("objects", [])
    out: list[Path] = []
    with_mesh = [f for f in result.fits if f.mesh is not None and not f.mesh.is_empty]
    for fit in with_mesh[-last:] if last > 0 else []:
        vm = ViewModel()
        m = fit.mesh
        std = m.std if m.std is not None else np.zeros(len(m.vertices))
        vm.ingest_mesh(m.vertices, m.faces, std, fit.mesh_fit_index)
        for e in result.events:
            if e.header.source_ns <= fit.data_ns:
                vm.ingest_event(int(e.payload["id"]), e.payload["state"])
        for o in result.observations:
            if o.t_ns <= fit.data_ns:
                vm.ingest_observation(o.id, int(o.label), o.position, o.event_id)
        vm.ingest_fit(fit.ids, fit.u, fit.flags, fit.fit_index, fit.flagged_events or None)
        path = folder / f"snapshot_{fit.fit_index:04d}.png"
        render_snapshot(vm.scene(), path, backend="matplotlib", outline=outline)
        out.append(path)
    return out


def write_outputs(
    result: PipelineResult,
    out_dir: str | Path,
    *,
    snapshots: int = 3,
    replay_output=None,
    config=None,
    command: str = "",
    window_s: tuple[float | None, float | None] = (None, None),
) -> dict:
    """Write every output file into ``out_dir`` (created); returns the report.

    Parameters
    ----------
    replay_output : ReplayOutput, optional
        Filled while the pipeline ran: gets the results, is closed into ``replay.mcap``, and
        gives ``report.html`` the detector signal and the flown path. Without it, the samples
        are decoded here from the log.
    config : Config, optional
        The run's settings (report.html prints them); defaults when None.
    command : str
        The command line, for report.html.
    window_s : (start, end)
        The replayed window, seconds from the log start.
    """
    from groundstation.config import Config, to_toml
    from groundstation.openformats.replay_output import ReplayOutput
    from groundstation.pipeline.report import write_report_html

    config = config or Config()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    report = build_report(result, mask_fractions=stricter_masks(config.surface))
    final = result.final
    if final is not None and final.mesh is not None and not final.mesh.is_empty:
        from groundstation.mapping.surface import write_ply

        write_ply(final.mesh, out / "mesh.ply")
        report["mesh"] = "mesh.ply"
    else:
        report["mesh"] = None
    write_observations_csv(result, out / "observations.csv")
    report["snapshots"] = [p.name for p in write_snapshots(result, out / "snapshots", snapshots)]
    if replay_output is None:
        replay_output = ReplayOutput(out / "replay.mcap", result.log_path, config,
                                     _window_ns(result, window_s), command)  # fmt: skip
        replay_output.samples_from_log(config.acquisition)
    replay_output.results(result)
    recording = replay_output.close()
    report["replay_mcap"] = {"file": replay_output.path.name, **recording}
    write_report_html(
        out / "report.html",
        result=result,
        report=report,
        signal=replay_output.signal(),
        threshold_g=replay_output.translator.signal.threshold_g,
        release_g=replay_output.translator.signal.release_g,
        trajectory=replay_output.trajectory(),
        settings_toml=to_toml(config),
        command=command,
        window_s=window_s,
        score=replay_output.translator.signal.is_score,
    )
    report["report_html"] = "report.html"
    write_report(report, out / "report.json")
    return report


def _window_ns(result: PipelineResult, window_s) -> tuple[int | None, int | None]:
    start, end = window_s
    return (
        None if start is None else result.start_ns + int(round(start * 1e9)),
        None if end is None else result.start_ns + int(round(end * 1e9)),
    )
