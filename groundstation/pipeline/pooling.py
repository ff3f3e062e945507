"""Pooled metrics of a batch's task reports and the summary text (pure).

Pooled metrics (per variant, over its finished tasks)
-----------------------------------------------------
``metrics``: for every truth metric of ``report.json`` (:data:`TRUTH_METRICS`), the number of
tasks that have it, its mean, median and worst (largest for errors, smallest for rates to
maximise). ``shares``: event counts pooled over tasks (gust / touch events flagged, touch
events flagged among those whose contacts lie on the surface and among the mislocated ones
(``pipeline.scoring``), slow touch events flagged, flag precision, touches detected) and
``missing_near_by_area``: the touched surface missing within 0.2 m of a touch, pooled by area
over the tasks (``missing_area_near_m2`` over ``touched_area_near_m2``, m²: the share of all
the touched surface the maps lack, where the mean of ``missing_share_near`` weighs every
flight alike); ``missing_near_detected_by_area``: the same near the touches the detector
reported (``missing_area_near_detected_m2`` over ``touched_area_near_detected_m2``).
``large_patches``: the tasks whose largest phantom patch is over ``PATCH_LINE_M2`` (issue 13's
line), of those that have one measured, and how many of them each cause drew
(``phantom_max_patch_cause``, ``pipeline.scoring.patch_sources``; ``not recorded`` for reports
written before it existed).
``upset``: the tasks whose body was tilted past 60 deg (``contact.stage.UPSET_TILT_DEG``) for
over ``UPSET_LINE_S`` (flipped or crashed), of those that recorded it.
``mask_curve``: the reports' ``mask_curve`` rows (the final mesh at stricter confidence masks,
``pipeline.scoring.mask_curve``) pooled per mask (:func:`pool_mask_curve`): what the phantom
line would cost in missing surface if the mask alone were tightened.
``u_auc``: probability that a gust event's median contact u exceeds a touch event's.
``refit_s_median``: median over every refit of every task. ``task_wall_s``: mean / median /
max wall time of one task (replay + outputs).

A task record is ``{"status": "done" | "failed" | "missing", "report": report.json,
"done": done.json, "error": text}`` (``pipeline.batch_outputs.read_record``).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

from groundstation.contact.stage import UPSET_TILT_DEG
from groundstation.pipeline.batch import LogInput, Plan

#: Truth metrics of ``report.json`` pooled by a batch, and which way is better.
TRUTH_METRICS: dict[str, str] = {
    "mesh_to_truth_median_m": "low",
    "truth_to_mesh_median_m": "low",
    "missing_share": "low",
    "missing_share_near": "low",
    "missing_share_near_detected": "low",
    "phantom_area_m2": "low",
    "phantom_max_patch_m2": "low",
    "gust_events_flagged": "high",
    "touch_events_flagged": "low",
    "chamfer_m": "low",
    "chamfer_full_m": "low",
    "shape_error_m": "low",
    "fp_precision": "high",
    "fp_recall": "high",
    "detection_recall": "high",
}


def event_u(result: Any) -> list[tuple[str, float]]:
    """(truth kind, median contact u) of every detected event matched to the truth.

    Parameters
    ----------
    result : pipeline.offline.PipelineResult
        A finished run whose log carries truth; [] otherwise.
    """
    from groundstation.pipeline.outputs import detected_events
    from groundstation.pipeline.scoring import match_events

    fit = result.final
    if fit is None or not result.truth:
        return []
    u = dict(zip(fit.ids.tolist(), fit.u.tolist(), strict=True))
    by_event: dict[int, list[float]] = {}
    for o in result.observations:
        if o.label == 0 and o.id in u:
            by_event.setdefault(o.event_id, []).append(u[o.id])
    out = []
    for eid, m in match_events(detected_events(result), result.truth).items():
        if m is not None and eid in by_event:
            out.append((m[1], float(statistics.median(by_event[eid]))))
    return out


# --- pooling ------------------------------------------------------------------------------------


def _finite(values: Iterable[Any]) -> list[float]:
    out = []
    for v in values:
        if isinstance(v, bool) or v is None:
            continue
        try:
            f = float(v)
        except (TypeError, ValueError):
            continue
        if math.isfinite(f):
            out.append(f)
    return out


def metric_stats(values: Iterable[Any], better: str = "low") -> dict[str, float]:
    """n, mean, median and worst of the finite values (NaN when there are none)."""
    xs = _finite(values)
    if not xs:
        return {"n": 0, "mean": math.nan, "median": math.nan, "worst": math.nan}
    return {
        "n": len(xs),
        "mean": statistics.fmean(xs),
        "median": statistics.median(xs),
        "worst": max(xs) if better == "low" else min(xs),
    }


def u_auc(gust_u: Sequence[float], touch_u: Sequence[float]) -> float:
    """P(u of a gust event > u of a touch event), ties counted half; NaN if either is empty."""
    g, t = _finite(gust_u), _finite(touch_u)
    if not g or not t:
        return math.nan
    greater = sum(a > b for a in g for b in t)
    ties = sum(a == b for a in g for b in t)
    return (greater + 0.5 * ties) / (len(g) * len(t))


def _share(num: float, den: float) -> dict[str, float]:
    return {"num": num, "den": den, "share": num / den if den else math.nan}


def pool(records: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Pooled metrics of a group of task records (module docstring).

    Parameters
    ----------
    records : sequence of dict
        ``{"status": "done" | "failed" | ..., "report": report.json, "done": done.json}``.
    """
    done = [r for r in records if r.get("status") == "done"]
    reports = [r.get("report") or {} for r in done]
    extras = [r.get("done") or {} for r in done]
    metrics = {
        k: metric_stats([rep.get(k) for rep in reports], better)
        for k, better in TRUTH_METRICS.items()
    }

    def total(key: str, weight: str | None = None) -> float:
        s = 0.0
        for rep in reports:
            v = rep.get(key)
            if weight is not None:
                w = rep.get(weight)
                if v is None or w is None or not math.isfinite(float(v)):
                    continue
                s += round(float(v) * float(w))
            elif v is not None and math.isfinite(float(v)):
                s += float(v)
        return s

    def counted(key: str, count: Any) -> dict[str, float]:
        """A share pooled over the reports that have it, each weighted by ``count(report)``."""
        num = den = 0.0
        for rep in reports:
            v, w = rep.get(key), count(rep)
            if v is None or w is None or not math.isfinite(float(v)):
                continue
            num += round(float(v) * float(w))
            den += float(w)
        return _share(num, den)

    def by_area(part: str, whole: str) -> dict[str, float]:
        """Sum of ``part`` over sum of ``whole``, over the reports that have both."""
        pairs = [_finite([rep.get(part), rep.get(whole)]) for rep in reports]
        return _share(
            sum(p[0] for p in pairs if len(p) == 2), sum(p[1] for p in pairs if len(p) == 2)
        )

    def on_surface(rep: Mapping[str, Any]) -> float | None:
        n, off = rep.get("events_touch"), rep.get("events_touch_mislocated")
        return None if n is None or off is None else float(n) - float(off)

    shares = {
        "gust_events_flagged": _share(total("events_flagged_false"), total("events_false")),
        "touch_events_flagged": _share(
            total("touch_events_flagged", "events_touch"), total("events_touch")
        ),
        "touch_events_flagged_on_surface": counted("touch_events_flagged_on_surface", on_surface),
        "mislocated_touches_flagged": counted(
            "mislocated_touches_flagged", lambda rep: rep.get("events_touch_mislocated")
        ),
        "slow_touch_events_flagged": counted(
            "slow_touch_events_flagged", lambda rep: rep.get("events_slow_touch")
        ),
        "echo_events_flagged": counted("echo_events_flagged", lambda rep: rep.get("events_echo")),
        "fp_precision": _share(total("events_flagged_false"), total("events_flagged")),
        "detection_recall": _share(
            total("detection_recall", "truth_touches"), total("truth_touches")
        ),
        "missing_near_by_area": by_area("missing_area_near_m2", "touched_area_near_m2"),
        "missing_near_detected_by_area": by_area(
            "missing_area_near_detected_m2", "touched_area_near_detected_m2"
        ),
    }
    events = [tuple(e) for x in extras for e in x.get("event_u", [])]
    refits = _finite(t for x in extras for t in x.get("refit_s", []))
    walls = _finite(x.get("task_wall_s") for x in extras)
    return {
        "tasks": len(records),
        "done": len(done),
        "failed": sum(r.get("status") == "failed" for r in records),
        "metrics": metrics,
        "shares": shares,
        "large_patches": large_patches(reports),
        "upset": upset_flights(reports),
        "mask_curve": pool_mask_curve(reports),
        "u_auc": u_auc(
            [u for k, u in events if k == "gust"], [u for k, u in events if k != "gust"]
        ),
        "refits": len(refits),
        "refit_s_median": statistics.median(refits) if refits else math.nan,
        "task_wall_s": {
            "mean": statistics.fmean(walls) if walls else math.nan,
            "median": statistics.median(walls) if walls else math.nan,
            "max": max(walls) if walls else math.nan,
        },
        "contacts": total("contacts"),
        "observations": total("observations"),
    }


#: The largest phantom patch a flight may leave (m², issue 13's line).
PATCH_LINE_M2 = 0.1


def large_patches(reports: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Reports whose largest phantom patch is over :data:`PATCH_LINE_M2`, by what drew it."""
    measured = [r for r in reports if _finite([r.get("phantom_max_patch_m2")])]
    over = [r for r in measured if float(r["phantom_max_patch_m2"]) > PATCH_LINE_M2]
    by_cause: dict[str, int] = {}
    for r in over:
        cause = r.get("phantom_max_patch_cause") or "not recorded"
        by_cause[cause] = by_cause.get(cause, 0) + 1
    return {"line_m2": PATCH_LINE_M2, "flights": len(measured), "over": len(over),
            "by_cause": by_cause}  # fmt: skip


#: A flight whose body was tilted past ``contact.stage.UPSET_TILT_DEG`` for longer than this
#: (s) flipped or crashed: the summaries count such flights beside the figures they weigh on.
UPSET_LINE_S = 1.0


def upset_flights(reports: Sequence[Mapping[str, Any]]) -> dict[str, int]:
    """How many reports say the body was upset (tilted past ``UPSET_TILT_DEG``) for over
    :data:`UPSET_LINE_S`, of those that recorded it (``stats.detector.upset_ms``)."""
    known = [((r.get("stats") or {}).get("detector") or {}).get("upset_ms") for r in reports]
    known = [float(v) for v in known if v is not None]
    return {"over": sum(v > 1e3 * UPSET_LINE_S for v in known), "flights": len(known)}


def upset_text(p: Mapping[str, Any]) -> str:
    """``2/36``: the pooled :func:`upset_flights` in a cell (``-`` when none recorded it)."""
    u = p.get("upset") or {}
    return f"{u['over']}/{u['flights']}" if u.get("flights") else "-"


def pool_mask_curve(reports: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """The reports' ``mask_curve`` rows pooled per mask, strictest last: flights scored, those
    whose largest phantom patch is over :data:`PATCH_LINE_M2`, the mean largest patch and
    phantom area, the touched surface missing within 0.2 m by area (as ``missing_near_by_area``),
    and the means of ``missing_share`` (within 0.5 m) and ``mesh_to_truth_median_m``."""
    rows: dict[float, list[Mapping[str, Any]]] = {}
    for rep in reports:
        for row in rep.get("mask_curve") or []:
            rows.setdefault(float(row["max_std_fraction"]), []).append(row)
    out = []
    for frac in sorted(rows, reverse=True):
        rs = rows[frac]
        big = _finite(r.get("phantom_max_patch_m2") for r in rs)
        pairs = [_finite([r.get("missing_area_near_m2"), r.get("touched_area_near_m2")])
                 for r in rs]  # fmt: skip
        out.append({
            "max_std_fraction": frac,
            "flights": len(big),
            "over": sum(b > PATCH_LINE_M2 for b in big),
            "phantom_max_patch_m2": metric_stats(big),
            "phantom_area_m2": metric_stats(r.get("phantom_area_m2") for r in rs),
            "missing_near_by_area": _share(
                sum(p[0] for p in pairs if len(p) == 2), sum(p[1] for p in pairs if len(p) == 2)
            ),
            "missing_share": metric_stats(r.get("missing_share") for r in rs),
            "mesh_to_truth_median_m": metric_stats(r.get("mesh_to_truth_median_m") for r in rs),
        })  # fmt: skip
    return out


def large_patches_text(p: Mapping[str, Any]) -> str:
    """``4/36 (touches 3, false contact 1)``: the pooled :func:`large_patches` in a cell."""
    causes = ", ".join(f"{c} {n}" for c, n in sorted(p["by_cause"].items(), key=lambda x: -x[1]))
    return f"{p['over']}/{p['flights']}" + (f" ({causes})" if causes else "")


def log_names(logs: Sequence[LogInput]) -> dict[str, str]:
    """Path -> the log's name in the summary: its stem, or ``stem-<sha256[:8]>`` when two
    different logs share a stem."""
    by_stem: dict[str, set[str]] = {}
    for log in logs:
        by_stem.setdefault(log.name, set()).add(log.path)
    return {
        log.path: log.name if len(by_stem[log.name]) == 1 else f"{log.name}-{log.sha256[:8]}"
        for log in logs
    }


def summarize(plan: Plan, records: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """The batch summary: pooled per variant, per log, and every failure.

    Parameters
    ----------
    plan : Plan
    records : dict
        Task folder -> record (``status``, ``report``, ``done``, ``error``).
    """
    per_variant: dict[str, Any] = {}
    per_log: dict[str, dict[str, Any]] = {}
    names = log_names([c.log for c in plan.cells])
    for v in plan.variants:
        cells = [c for c in plan.cells if c.variant == v.name]
        recs = [records.get(c.task.folder, {"status": "missing"}) for c in cells]
        per_variant[v.name] = {
            "overrides": [*plan.base_overrides, *v.overrides],
            "pooled": pool(recs),
        }
        for c, r in zip(cells, recs, strict=True):
            rep = r.get("report") or {}
            per_log.setdefault(names[c.log.path], {})[v.name] = {
                "folder": c.task.folder,
                "status": r.get("status", "missing"),
                **{k: rep.get(k) for k in (*TRUTH_METRICS, "contacts", "refits")},
                "phantom_at": ((rep.get("phantom_patches") or [{}])[0]).get("centre"),
                "task_wall_s": (r.get("done") or {}).get("task_wall_s"),
            }
    failed = [
        {"folder": t.folder, "log": t.log, "error": records.get(t.folder, {}).get("error", "")}
        for t in plan.tasks
        if records.get(t.folder, {}).get("status") != "done"
    ]
    return {"variants": per_variant, "logs": per_log, "failed": failed}


# --- text ---------------------------------------------------------------------------------------


def fmt(v: Any, spec: str = ".3f") -> str:
    """A number for a table; ``-`` for missing / NaN."""
    if v is None or isinstance(v, bool):
        return "-"
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    return "-" if not math.isfinite(f) else format(f, spec)


def summary_markdown(summary: Mapping[str, Any], title: str = "groundstation batch") -> str:
    """``summary.md``: pooled metrics per variant, flag shares, timing, per log, failures."""
    variants = summary["variants"]
    names = list(variants)
    lines = [f"# {title}", ""]
    for name, v in variants.items():
        p = v["pooled"]
        lines.append(
            f"- **{name}**: {' '.join(v['overrides']) or '(defaults)'} - {p['done']}/{p['tasks']}"
            f" tasks done, {p['failed']} failed"
        )
    lines += ["", "## Truth metrics (mean / median / worst over logs)", ""]
    lines += ["| metric | better | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for key, better in TRUTH_METRICS.items():
        cells = []
        for name in names:
            s = variants[name]["pooled"]["metrics"][key]
            cells.append(
                "-" if not s["n"] else f"{fmt(s['mean'])} / {fmt(s['median'])} / {fmt(s['worst'])}"
            )
        lines.append(f"| {key} | {better} | " + " | ".join(cells) + " |")
    lines += ["", "## Pooled over events, and time", ""]
    lines += ["| | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    pooled_keys = (
        "gust_events_flagged", "touch_events_flagged", "touch_events_flagged_on_surface",
        "mislocated_touches_flagged", "slow_touch_events_flagged", "fp_precision",
        "detection_recall",
    )  # fmt: skip
    for key in pooled_keys:
        row = []
        for name in names:
            s = variants[name]["pooled"]["shares"][key]
            row.append(f"{fmt(s['share'], '.2f')} ({fmt(s['num'], '.0f')}/{fmt(s['den'], '.0f')})")
        lines.append(f"| {key} | " + " | ".join(row) + " |")
    rows = {
        f"flights with a phantom patch over {PATCH_LINE_M2} m² (by cause)": lambda p: (
            large_patches_text(p["large_patches"])
        ),
        f"flights upset (tilted past {UPSET_TILT_DEG:g} deg for over {UPSET_LINE_S:g} s: "
        "flipped or crashed)": upset_text,
        "u-AUC gust vs touch": lambda p: fmt(p["u_auc"], ".2f"),
        "refit median (s)": lambda p: f"{fmt(p['refit_s_median'], '.2f')} ({p['refits']} refits)",
        "task wall mean / median / max (s)": lambda p: " / ".join(
            fmt(p["task_wall_s"][k], ".1f") for k in ("mean", "median", "max")
        ),
    }
    for label, f in rows.items():
        lines.append(f"| {label} | " + " | ".join(f(variants[n]["pooled"]) for n in names) + " |")
    cols = ("mesh_to_truth_median_m", "missing_share", "phantom_max_patch_m2",
            "gust_events_flagged", "touch_events_flagged", "chamfer_m")  # fmt: skip
    lines += ["", "## Per log", ""]
    lines += ["| log | variant | status | " + " | ".join(cols)
              + " | largest phantom patch at | contacts | task wall (s) |"]  # fmt: skip
    lines += ["|---|---|---|" + "---|" * (len(cols) + 3)]
    for log, per in summary["logs"].items():
        for name, r in per.items():
            at = r.get("phantom_at")
            where = "(" + ", ".join(fmt(x, ".2f") for x in at) + ")" if at else "-"
            lines.append(
                f"| {log} | {name} | {r['status']} | "
                + " | ".join(fmt(r.get(k)) for k in cols)
                + f" | {where} | {fmt(r.get('contacts'), '.0f')}"
                + f" | {fmt(r.get('task_wall_s'), '.1f')} |"
            )
    if summary.get("failed"):
        lines += ["", "## Failed or missing tasks", ""]
        for f in summary["failed"]:
            err = (f.get("error") or "not run").strip().splitlines()
            lines.append(f"- `{f['folder']}`: {err[-1] if err else 'not run'}")
    return "\n".join(lines) + "\n"
