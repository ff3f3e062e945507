"""``groundstation bench sessions``: the production pipeline on many flights, over batch.

The bench only builds a task list; ``groundstation batch`` (``pipeline.batch``,
``runtime.batch``) runs it on Dask, one task per (flight, variant), exactly as ``groundstation
replay --map final`` would, and keeps every task's outputs. The flights:

- the three bundled ``replay_logs/`` (simple physics, gusty air; no clean control);
- for every engine and seed, the evaluation flights of ``bench detector``
  (``bench.detector.flight_suite``: ``script:varied`` surveys of scenes around and away from the
  mocap origin and contact-free flights, in gusty air), generated once into ``--cache``;
- for each of those its **clean control** (:func:`control_of`): the same flight with the gust
  options replaced by ``--gust-rate 0`` (same seed, no false contacts).

A flight of engine E is replayed with the ``[vehicle]`` settings a user gives for that airframe
(``bench.detector.VEHICLE[E]``) before ``--set`` and the variant's overrides; they replace the
simulator's exact airframe that the recording stores (which ``--logs`` recordings start from, as
``replay`` does), so the map is judged on a user's description of the body, not the model's.

Summary (per variant and per group: each engine, all engines pooled, the bundled logs)
--------------------------------------------------------------------------------------
For every truth metric (``pipeline.pooling.TRUTH_METRICS``) the mean, median and worst over the
gusty flights, the same over their controls, and the ratio of the means (gusty / control).
Accuracy that comes from smoothing rather than from rejecting false contacts shows up as *no*
gap to the control; a robust map is as good in gusty air as in calm air (ratio ~1 for errors).
Event shares are pooled over flights (``pipeline.pooling.pool``), and so is the touched
surface missing within 0.2 m of a touch, by area (``missing_near_by_area``): the mean of
``missing_share_near`` weighs a flight with one touch as much as one with fifty. Next to it,
the same near the touches the detector reported (``missing_near_detected_by_area``): the rest
was never given to the map.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from groundstation.bench.detector import FlightSpec, flight_suite
from groundstation.contact.stage import UPSET_TILT_DEG
from groundstation.pipeline.batch import Plan, Variant
from groundstation.pipeline.pooling import (
    PATCH_LINE_M2,
    TRUTH_METRICS,
    UPSET_LINE_S,
    fmt,
    large_patches_text,
    pool,
    u_auc,
    upset_text,
)

__all__ = ["BUNDLED", "ROOT", "Flight", "Variant", "control_of", "flights", "u_auc"]

ROOT = Path(__file__).resolve().parents[2]
BUNDLED = ("wall_survey", "pillar_survey", "wall_slow_touch_gusts")
#: Engine of the bundled logs (``replay_logs/regenerate.sh`` runs the simple SITL).
BUNDLED_ENGINE = "simple"


@dataclasses.dataclass(frozen=True)
class Flight:
    """A generated flight of the bench: its spec, ``gusty`` or ``control``, and the name of the
    gusty flight it belongs to."""

    spec: FlightSpec
    role: str
    pair: str


def control_of(spec: FlightSpec) -> FlightSpec:
    """The same flight in calm air: every ``--gust-*`` option dropped, ``--gust-rate 0`` added."""
    args: list[str] = []
    skip = False
    for a in spec.sitl_args:
        if skip:
            skip = False
            if not a.startswith("--"):
                continue
        if a.startswith("--gust"):
            skip = "=" not in a
            continue
        args.append(a)
    return dataclasses.replace(spec, sitl_args=(*args, "--gust-rate", "0"))


def flights(engines: Sequence[str], seeds: Sequence[int]) -> list[Flight]:
    """Every evaluation flight of ``engines`` x ``seeds`` followed by its clean control."""
    out = []
    for spec in flight_suite(engines, seeds):
        out.append(Flight(spec, "gusty", spec.name))
        out.append(Flight(control_of(spec), "control", spec.name))
    return out


def groups(plan: Plan, variant: str) -> dict[str, dict[str, list[str]]]:
    """Task folders per group and role for ``variant``: ``{group: {"gusty": [...], "control":
    [...]}}`` with a group per engine, ``pooled`` (every generated flight) and ``bundled``."""
    out: dict[str, dict[str, list[str]]] = {}
    for c in plan.cells:
        if c.variant != variant:
            continue
        role, engine = c.log.label("role"), c.log.label("engine")
        if role == "bundled" or role == "log":
            out.setdefault(role, {"gusty": [], "control": []})["gusty"].append(c.task.folder)
        elif role in ("gusty", "control"):
            for g in (engine, "pooled"):
                out.setdefault(g, {"gusty": [], "control": []})[role].append(c.task.folder)
    order = [g for g in out if g not in ("pooled", "bundled", "log")]
    order += [g for g in ("pooled", "bundled", "log") if g in out]
    return {g: out[g] for g in order}


def ratio(a: float, b: float) -> float:
    """a / b, NaN when either is missing or b is 0."""
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)) or b == 0:
        return math.nan
    return a / b


def compare(plan: Plan, records: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """Per variant and group: pooled gusty flights, pooled controls and the ratio of means."""
    out: dict[str, Any] = {}
    for v in plan.variants:
        out[v.name] = {}
        for g, roles in groups(plan, v.name).items():
            gusty = pool([records.get(f, {"status": "missing"}) for f in roles["gusty"]])
            control = pool([records.get(f, {"status": "missing"}) for f in roles["control"]])
            out[v.name][g] = {
                "gusty": gusty,
                "control": control if roles["control"] else None,
                "ratio": {
                    k: ratio(gusty["metrics"][k]["mean"], control["metrics"][k]["mean"])
                    for k in TRUTH_METRICS
                }
                if roles["control"]
                else None,
            }
    return out


def _triple(s: Mapping[str, Any]) -> str:
    return "-" if not s["n"] else f"{fmt(s['mean'])} / {fmt(s['median'])} / {fmt(s['worst'])}"


def markdown(comparison: Mapping[str, Any], overrides: Mapping[str, Sequence[str]]) -> str:
    """The bench's own section of ``summary.md``: per variant and group, gusty vs control."""
    lines = ["# bench sessions", ""]
    lines.append(
        "Per group: gusty flights (mean / median / worst over flights), their clean controls "
        "(the same flights with `--gust-rate 0`), and the ratio of the means (gusty / control). "
        "No gap to the control means the accuracy does not depend on rejecting false contacts."
    )
    for name, per_group in comparison.items():
        lines += ["", f"## variant {name}: {' '.join(overrides.get(name, ())) or '(defaults)'}"]
        for g, c in per_group.items():
            gp, cp = c["gusty"], c["control"]
            head = f"{gp['done']}/{gp['tasks']} flights"
            if cp is not None:
                head += f", controls {cp['done']}/{cp['tasks']}"
            lines += ["", f"### {g} ({head})", ""]
            if cp is None:
                lines += ["| metric | mean / median / worst |", "|---|---|"]
            else:
                lines += ["| metric | gusty | control | ratio |", "|---|---|---|---|"]
            for k in TRUTH_METRICS:
                row = f"| {k} | {_triple(gp['metrics'][k])} |"
                if cp is not None:
                    row += f" {_triple(cp['metrics'][k])} | {fmt(c['ratio'][k], '.2f')} |"
                lines.append(row)
            extra = {
                "events: gusts flagged": lambda p: _share(p, "gust_events_flagged"),
                "events: touches flagged": lambda p: _share(p, "touch_events_flagged"),
                "events: touches placed on the surface flagged": lambda p: _share(
                    p, "touch_events_flagged_on_surface"
                ),
                "events: touches placed > 0.1 m off it flagged": lambda p: _share(
                    p, "mislocated_touches_flagged"
                ),
                "events: slow touches flagged": lambda p: _share(p, "slow_touch_events_flagged"),
                "events: touches' echoes flagged": lambda p: _share(p, "echo_events_flagged"),
                "events: flag precision": lambda p: _share(p, "fp_precision"),
                "events: touches detected": lambda p: _share(p, "detection_recall"),
                "touched surface missing within 0.2 m, by area (m²)": lambda p: _share(
                    p, "missing_near_by_area", ".3f", ".2f"
                ),
                "... near the touches the detector reported (m²)": lambda p: _share(
                    p, "missing_near_detected_by_area", ".3f", ".2f"
                ),
                f"flights with a phantom patch over {PATCH_LINE_M2} m² (by cause)": lambda p: (
                    large_patches_text(p["large_patches"])
                ),
                f"flights upset (tilted past {UPSET_TILT_DEG:g} deg for over {UPSET_LINE_S:g} s: "
                "flipped or crashed)": upset_text,
                "u-AUC gust vs touch": lambda p: fmt(p["u_auc"], ".2f"),
                "refit median (s)": lambda p: fmt(p["refit_s_median"], ".2f"),
                "task wall median (s)": lambda p: fmt(p["task_wall_s"]["median"], ".1f"),
            }
            for label, f in extra.items():
                row = f"| {label} | {f(gp)} |"
                if cp is not None:
                    row += f" {f(cp)} | |"
                lines.append(row)
            lines += mask_curve_lines(gp, cp)
    return "\n".join(lines) + "\n"


def _curve_cells(
    over: str, big: Any, area: Any, near: Mapping[str, Any], missing: Any, m2t: Any
) -> list[str]:
    near_cell = f"{fmt(near['share'])} of {fmt(near['den'], '.2f')}"
    return [over, fmt(big), fmt(area), near_cell, fmt(missing), fmt(m2t)]


def mask_curve_lines(gp: Mapping[str, Any], cp: Mapping[str, Any] | None) -> list[str]:
    """The group's mask curve (``pipeline.pooling.pool_mask_curve``) as a table: the configured
    mask's row from the group's own figures, then each stricter mask; gusty flights, controls
    in brackets. Nothing when no report has a curve."""
    if not gp.get("mask_curve"):
        return []

    def configured(p: Mapping[str, Any]) -> list[str]:
        lp, m = p["large_patches"], p["metrics"]
        return _curve_cells(
            f"{lp['over']}/{lp['flights']}",
            m["phantom_max_patch_m2"]["mean"],
            m["phantom_area_m2"]["mean"],
            p["shares"]["missing_near_by_area"],
            m["missing_share"]["mean"],
            m["mesh_to_truth_median_m"]["mean"],
        )

    def stricter(row: Mapping[str, Any]) -> list[str]:
        return _curve_cells(
            f"{row['over']}/{row['flights']}",
            row["phantom_max_patch_m2"]["mean"],
            row["phantom_area_m2"]["mean"],
            row["missing_near_by_area"],
            row["missing_share"]["mean"],
            row["mesh_to_truth_median_m"]["mean"],
        )

    rows = [("configured", configured(gp), configured(cp) if cp is not None else None)]
    by_frac = {r["max_std_fraction"]: r for r in (cp or {}).get("mask_curve") or []}
    for r in gp["mask_curve"]:
        c = by_frac.get(r["max_std_fraction"])
        rows.append((f"{r['max_std_fraction']:.2f}", stricter(r), stricter(c) if c else None))
    out = [
        "",
        "The same final meshes kept at stricter confidence masks (`surface.max_std_fraction`, "
        "a fraction of the prior std): the phantom surface a stricter mask removes and the "
        "touched surface it costs" + (" (controls in brackets)." if cp is not None else "."),
        "",
        f"| mask | flights over {PATCH_LINE_M2} m² | largest phantom patch, mean (m²) | "
        "phantom area, mean (m²) | touched surface missing within 0.2 m, share of the area (m²) | "
        "missing within 0.5 m, mean | mesh -> truth median, mean (m) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, g, c in rows:
        cells = g if c is None else [f"{a} ({b})" for a, b in zip(g, c, strict=True)]
        out.append(f"| {name} | " + " | ".join(cells) + " |")
    return out


def _share(p: Mapping[str, Any], key: str, share: str = ".2f", counts: str = ".0f") -> str:
    s = p["shares"][key]
    return f"{fmt(s['share'], share)} ({fmt(s['num'], counts)}/{fmt(s['den'], counts)})"


def control_chart(comparison: Mapping[str, Any], path: Path) -> Path:
    """Bars of every error metric's mean, gusty vs control, per group (one row per variant)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    keys = [k for k, b in TRUTH_METRICS.items() if b == "low"]
    names = list(comparison)
    fig, axes = plt.subplots(
        len(names), len(keys), figsize=(2.4 * len(keys), 2.6 * len(names)), squeeze=False
    )
    for row, name in zip(axes, names, strict=True):
        per_group = {g: c for g, c in comparison[name].items() if c["control"] is not None}
        x = np.arange(len(per_group))
        for ax, k in zip(row, keys, strict=True):
            gusty = [c["gusty"]["metrics"][k]["mean"] for c in per_group.values()]
            calm = [c["control"]["metrics"][k]["mean"] for c in per_group.values()]
            ax.bar(x - 0.2, np.nan_to_num(gusty), 0.4, label="gusty")
            ax.bar(x + 0.2, np.nan_to_num(calm), 0.4, label="control")
            ax.set_xticks(x, list(per_group), fontsize=7)
            ax.set_title(f"{name}: {k}", fontsize=7)
            ax.tick_params(axis="y", labelsize=7)
        row[0].legend(fontsize=7)
    fig.suptitle("bench sessions: mean per group, gusty flights vs clean controls", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
