"""``report.html``: one self-contained page per replay (no network, no script; opens offline).

Sections, top to bottom:

1. **Summary**: the log, window, duration, contacts (events, as the status line counts them)
   and how many the map flags, refits, and the truth scores when the log carries ground truth.
2. **Detector signal**: the impulse detector's trigger score (or, with the threshold detector,
   the filtered |a| in G) against its trigger and release levels, over log time; every contact
   event shaded from begin to end in its state's colour (green trusted, magenta flagged, amber
   awaiting a second touch, grey pending) and numbered; true contacts (``truth.json``) ticked
   along the bottom by kind.
3. **Map**: the final mesh, contact points by state and the flown path from three sides (top,
   front, side) with metre axes, the true structure outlined in dashed red when the log has
   ground truth (the same renderer as every snapshot, ``viewer.headless.render_matplotlib``).
4. **Contact events**: one row per event: id, begin and end time, place (the mean contact point
   of its observations, else the vehicle position), peak |a|, ``p_false`` when the detector gave
   one, the map's verdict (trusted / flagged / awaiting: flagged only because no other touch
   corroborates it / pending) and the truth label when known.
5. **Settings**: the command and every setting of the run (``groundstation config show``).

Images are PNGs inlined as ``data:`` URIs; the page is plain HTML and CSS.
"""

from __future__ import annotations

import base64
import dataclasses
import datetime
import html
import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.contact.stage import UPSET_TILT_DEG
from groundstation.viewer.scene import STATE_COLORS, STATE_NAMES

_TRUTH_COLORS = {"touch": "#1f77b4", "slow_touch": "#17becf", "gust": "#d62728"}


@dataclasses.dataclass(frozen=True)
class EventRow:
    """One row of the event table (times in seconds from the log start, place in metres)."""

    id: int
    t_begin_s: float
    t_end_s: float | None
    place: tuple[float, float, float] | None
    peak_g: float
    p_false: float | None
    state: str  # trusted | flagged | awaiting | pending
    truth: str | None  # touch | gust | ... | "unmatched" | None (no truth)
    p_false_impulse: float | None = None  # the detector's value on the impulse alone


def event_rows(result, truth: Mapping[str, Any] | None) -> list[EventRow]:
    """The event table of a ``PipelineResult`` (module docstring, section 4)."""
    from groundstation.pipeline.outputs import detected_events
    from groundstation.pipeline.scoring import match_events

    final = result.final
    flagged = set(final.flagged_events) if final is not None else set()
    awaiting = set(final.awaiting_events) if final is not None else set()
    in_fit = set(final.ids.tolist()) if final is not None else set()
    points: dict[int, list[np.ndarray]] = {}
    fitted_events: set[int] = set()
    obs_p: dict[int, list[float]] = {}
    for o in result.observations:
        if int(o.label) == 0 and o.event_id >= 0:
            points.setdefault(o.event_id, []).append(np.asarray(o.position, dtype=float))
            if o.id in in_fit:
                fitted_events.add(o.event_id)
            p = getattr(o, "p_false", None)
            if p is not None and math.isfinite(float(p)):
                obs_p.setdefault(o.event_id, []).append(float(p))
    labels = {}
    if truth and truth.get("contacts") is not None:
        labels = match_events(detected_events(result), dict(truth))
    begins: dict[int, Any] = {}
    ends: dict[int, Any] = {}
    for e in result.events:
        (begins if e.payload["state"] == "begin" else ends)[int(e.payload["id"])] = e
    rows = []
    t0 = result.start_ns
    for ev_id, b in sorted(begins.items()):
        e = ends.get(ev_id)
        last = e if e is not None else b
        p = last.payload.get("p_false", b.payload.get("p_false"))
        p_alone = last.payload.get("p_false_impulse", b.payload.get("p_false_impulse"))
        if p is None and obs_p.get(ev_id):
            p = float(np.mean(obs_p[ev_id]))
        if ev_id in points:
            place = tuple(float(v) for v in np.mean(points[ev_id], axis=0))
        else:
            pos = np.asarray(last.arrays["position_m"], dtype=float)
            place = tuple(float(v) for v in pos) if np.all(np.isfinite(pos)) else None
        state = "pending"
        if ev_id in flagged:
            state = "awaiting" if ev_id in awaiting else "flagged"
        elif ev_id in fitted_events:
            state = "trusted"
        label = None
        if labels:
            m = labels.get(ev_id)
            label = "unmatched" if m is None else m[1]
        rows.append(
            EventRow(
                id=ev_id,
                t_begin_s=(b.header.source_ns - t0) / 1e9,
                t_end_s=None if e is None else (e.header.source_ns - t0) / 1e9,
                place=place,  # type: ignore[arg-type]
                peak_g=float(last.payload["peak_g"]),
                p_false=None if p is None else float(p),
                state=state,
                truth=label,
                p_false_impulse=None if p_alone is None else float(p_alone),
            )
        )
    return rows


def p_false_cell(r: EventRow) -> str:
    """The event table's ``p_false``: with the impulse's own value when a gust burst raised it
    (``contact.burst_odds``), so a doubted touch says why."""
    text = _fmt(r.p_false, 2)
    if r.p_false is not None and r.p_false_impulse is not None:
        if r.p_false - r.p_false_impulse > 0.005:
            text += (
                f" ({r.p_false_impulse:.2f} on its own; a dropped impulse pushed the same way"
                " just before)"
            )
    return text


def _png(fig: Any) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _envelope(t: np.ndarray, g: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Min/max per bin (keeps every peak visible at any length), as one polyline."""
    if t.size <= 2 * bins:
        return t, g
    edges = np.linspace(t[0], t[-1], bins + 1)
    idx = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, bins - 1)
    order = np.argsort(idx, kind="stable")
    starts = np.searchsorted(idx[order], np.arange(bins))
    lo = np.minimum.reduceat(g[order], starts)
    hi = np.maximum.reduceat(g[order], starts)
    mid = 0.5 * (edges[:-1] + edges[1:])
    return np.repeat(mid, 2), np.column_stack([lo, hi]).reshape(-1)


def signal_figure(
    t_s: np.ndarray,
    g: np.ndarray,
    threshold_g: float,
    release_g: float,
    rows: Sequence[EventRow],
    truth: Mapping[str, Any] | None,
    t0_ns: int,
    width: int = 1100,
    height: int = 340,
    score: bool = False,
) -> Any:
    """The signal plot (module docstring, section 2) as a matplotlib figure."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Patch

    fig = Figure(figsize=(width / 100, height / 100), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.06, 0.16, 0.92, 0.74))
    state_color = dict(zip(STATE_NAMES, STATE_COLORS, strict=True))
    for r in rows:
        end = r.t_end_s if r.t_end_s is not None else r.t_begin_s + 0.05
        ax.axvspan(r.t_begin_s, max(end, r.t_begin_s + 0.02), color=state_color[r.state],
                   alpha=0.35, lw=0)  # fmt: skip
    if t_s.size:
        x, y = _envelope(t_s, g, 3000)
        ax.plot(x, y, color="k", lw=0.6, label="trigger score" if score else "filtered |a|")
    unit = "" if score else " G"
    ax.axhline(threshold_g, color="#d62728", ls="--", lw=1,
               label=f"{'trigger' if score else 'threshold'} {threshold_g:g}{unit}")  # fmt: skip
    ax.axhline(release_g, color="#ff7f0e", ls=":", lw=1, label=f"release {release_g:.3g}{unit}")
    top = max([threshold_g * 1.3] + ([float(np.max(g))] if g.size else []))
    ax.set_ylim(0, top * 1.12)
    for r in rows:
        ax.text(r.t_begin_s, top * 1.04, str(r.id), fontsize=6, ha="center", va="bottom",
                color=state_color[r.state])  # fmt: skip
    kinds = set()
    if truth:
        offset = int(truth.get("clock", {}).get("station_offset_ns", 0))
        for c in truth.get("contacts", []):
            ts = (c["start"] * 1e9 + offset - t0_ns) / 1e9
            color = _TRUTH_COLORS.get(c["kind"], "0.3")
            ax.plot([ts, ts], [0, top * 0.06], color=color, lw=2)
            kinds.add(c["kind"])
    ax.set_xlabel("log time (s from the start of the recording)", fontsize=8)
    ax.set_ylabel("trigger score" if score else "|a| (G)", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.grid(True, color="0.9", lw=0.5)
    if t_s.size:
        ax.set_xlim(float(t_s[0]), float(t_s[-1]))
    handles, _ = ax.get_legend_handles_labels()
    handles += [Patch(color=c, alpha=0.35, label=f"event {n}") for n, c in state_color.items()]
    handles += [Patch(color=_TRUTH_COLORS.get(k, "0.3"), label=f"true {k}") for k in sorted(kinds)]
    fig.legend(handles=handles, loc="upper center", ncol=min(len(handles), 8), fontsize=7,
               frameon=False, bbox_to_anchor=(0.5, 1.0))  # fmt: skip
    return fig


def map_scene(result, trajectory: np.ndarray):
    """The final map as a viewer Scene: mesh, contact points with the final fit's states,
    events counted as the status line counts them, and the whole flown path."""
    from groundstation.viewer.scene import ViewModel, ViewSettings

    n = max(len(trajectory), 2)
    vm = ViewModel(
        ViewSettings(trajectory_window_s=1e9, trajectory_max_points=n, max_observations=max(
            2, len(result.observations)))
    )  # fmt: skip
    fit = result.final
    if fit is not None and fit.mesh is not None and not fit.mesh.is_empty:
        m = fit.mesh
        std = m.std if m.std is not None else np.zeros(len(m.vertices))
        vm.ingest_mesh(m.vertices, m.faces, std, fit.mesh_fit_index)
    for e in result.events:
        vm.ingest_event(int(e.payload["id"]), e.payload["state"])
    for o in result.observations:
        vm.ingest_observation(o.id, int(o.label), o.position, o.event_id)
    if fit is not None:
        vm.ingest_fit(fit.ids, fit.u, fit.flags, fit.fit_index, fit.flagged_events)
    for k, p in enumerate(trajectory):
        vm.ingest_pose(k, p, [1.0, 0.0, 0.0, 0.0])
    return vm.scene()


def rejected_text(events) -> str:
    """How many candidates the detector rejected, and how many of them because they began with
    the body at the floor (``contact.floor_z_m``) or upset (``contact.reject_tilt_deg``)."""
    rejected = [e for e in events if e.payload.get("state") == "rejected"]
    floor = sum(bool(e.payload.get("at_floor")) for e in rejected)
    upset = sum(bool(e.payload.get("upset")) for e in rejected)
    why = [f"{floor} begun with the body at the floor"] if floor else []
    why += [f"{upset} begun with the body upset"] if upset else []
    return f"{len(rejected)} ({', '.join(why)})" if why else str(len(rejected))


def observations_text(result) -> str:
    """How many observations the detector made, and how many free-space samples it skipped
    because the body was tilted past ``contact.external_max_tilt_deg`` (a flip, a crash)."""
    tilted = int(((result.stats or {}).get("detector") or {}).get("tilted") or 0)
    n = str(len(result.observations))
    return f"{n} ({tilted} free-space samples skipped: body tilted)" if tilted else n


def upset_text(result) -> str:
    """How long the body was tilted past ``contact.stage.UPSET_TILT_DEG`` (a flip, or down
    after a crash), and from when: ``"tilted past 60 deg for 470.2 s, first at 124.0 s (a flip
    or a crash)"``; ``no`` when never, or for a report from before the stage counted it."""
    det = (result.stats or {}).get("detector") or {}
    first = det.get("upset_first_ns")
    ms, first = int(det.get("upset_ms") or 0), -1 if first is None else int(first)
    if first < 0:
        return "no"
    at = (first - result.start_ns) / 1e9
    return (
        f"tilted past {UPSET_TILT_DEG:g} deg for {ms / 1e3:.1f} s, first at {at:.1f} s"
        " (a flip or a crash)"
    )


def truth_rows(report: Mapping[str, Any]) -> list[tuple[str, str]]:
    """The report's truth scores as (label, text) summary rows (none without truth): the
    accuracy next to what it costs (surface missing, surface invented, and where the largest
    invented patches lie), the flags per event, and what a stricter confidence mask would
    trade (``mask_curve``)."""
    rows = []
    for key, label in (
        ("mesh_to_truth_median_m", "mesh -> truth, median (m)"),
        ("chamfer_m", "Chamfer where touched (m)"),
        ("missing_share", "touched surface missing (within 0.5 m of a touch)"),
        ("missing_share_near", "touched surface missing (within 0.2 m)"),
        ("touched_area_near_m2", "touched surface within 0.2 m of a touch (m^2)"),
        ("missing_share_near_detected", "... missing, near the touches the detector reported"),
        ("phantom_area_m2", "phantom surface (m^2)"),
        ("shape_error_m", "shape error (m)"),
        ("gust_events_flagged", "gust events flagged"),
        ("touch_events_flagged", "touch events flagged"),
        ("touch_events_flagged_on_surface", "touch events flagged, of those placed on the surface"),
        ("events_touch_mislocated", "touch events placed > 0.1 m off the surface"),
        ("mislocated_touches_flagged", "touch events flagged, of those placed off it"),
        ("slow_touch_events_flagged", "slow touch events (< 0.2 m/s) flagged"),
        ("events_echo", "echoes of touches (the vehicle's reaction, not a contact)"),
        ("echo_events_flagged", "echoes of touches flagged"),
        ("fp_precision", "flag precision"),
        ("fp_recall", "flag recall"),
        ("detection_recall", "touches detected"),
    ):
        if key in report:
            rows.append((label, _fmt(report[key])))
    for k, p in enumerate(report.get("phantom_patches") or [], start=1):
        centre = ", ".join(f"{x:.2f}" for x in p["centre"])
        drawn = ""
        if p.get("cause"):
            ids = ", ".join(str(e["id"]) for e in p.get("events", []) if not e["flagged"])
            drawn = f"; drawn by {p['cause']}" + (f" (events {ids})" if ids else "")
        rows.append((f"phantom patch {k}",
                     f"{_fmt(p['area_m2'])} m^2 at ({centre}), up to {_fmt(p['farthest_m'])} m "
                     f"from the truth{drawn}"))  # fmt: skip
    for r in report.get("mask_curve") or []:
        rows.append((
            f"at a stricter mask, {r['max_std_fraction']:.2f} of the prior std",
            f"largest phantom patch {_fmt(r['phantom_max_patch_m2'])} m^2, phantom surface "
            f"{_fmt(r['phantom_area_m2'])} m^2; touched surface missing "
            f"{_fmt(r['missing_share_near'])} within 0.2 m, {_fmt(r['missing_share'])} within "
            f"0.5 m",
        ))  # fmt: skip
    return rows


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return "–" if not math.isfinite(v) else f"{v:.{digits}g}"
    return html.escape(str(v))


_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:24px auto;
max-width:1140px;color:#222;line-height:1.4}
h1{font-size:22px;margin-bottom:4px} h2{font-size:17px;margin-top:28px;border-bottom:1px solid #ddd}
table{border-collapse:collapse;font-size:13px} td,th{padding:3px 8px;border-bottom:1px solid #eee;
text-align:right} th{background:#f5f5f5} td.l,th.l{text-align:left}
.summary td{text-align:left} .muted{color:#777;font-size:12px}
.trusted{color:#1a9933} .flagged{color:#d9198f;font-weight:600} .pending{color:#888}
.awaiting{color:#d98c00;font-weight:600}
.gust{color:#d62728;font-weight:600} pre{background:#f7f7f7;padding:8px;font-size:12px;
overflow-x:auto} img{max-width:100%;border:1px solid #eee}
"""


def render_html(
    *,
    title: str,
    summary: Sequence[tuple[str, str]],
    signal_png: str,
    map_png: str,
    rows: Sequence[EventRow],
    settings_toml: str,
    command: str,
    has_truth: bool,
    has_p_false: bool,
    score: bool = False,
) -> str:
    """The page (module docstring); images are ``data:`` URIs."""
    esc = html.escape
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{esc(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{esc(title)}</h1>",
        f'<p class="muted">written {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC '
        "by groundstation; self-contained, opens offline</p>",
        '<h2 id="summary">Summary</h2><table class="summary">',
    ]
    parts += [f"<tr><th class='l'>{esc(k)}</th><td>{esc(v)}</td></tr>" for k, v in summary]
    parts.append("</table>")
    parts += [
        '<h2 id="signal">Detector signal</h2>',
        (
            "<p>The impulse detector's trigger score (the impulse residual over its trigger "
            "levels: an event opens above 1)"
            if score
            else "<p>Filtered |a| (gravity removed, world frame) that the detector compares with "
            "the threshold"
        )
        + "; each contact event is shaded from begin to end in the map's verdict "
        "(green trusted, magenta flagged, amber awaiting a second touch, grey pending) and "
        "numbered"
        + ("; true contacts are ticked along the bottom by kind" if has_truth else "")
        + ".</p>",
        f'<img id="signal-plot" alt="detector signal against the threshold" src="{signal_png}">',
        '<h2 id="map">Map</h2>',
        "<p>Final mesh (colour = predictive std), contact points by state and the flown path, "
        "from the top, the front and the side, in metres"
        + ("; the true structure is outlined in dashed red" if has_truth else "")
        + ".</p>",
        f'<img id="map-views" alt="map from three views" src="{map_png}">',
        f'<h2 id="events">Contact events ({len(rows)})</h2>',
        "<table><tr><th>id</th><th>begin (s)</th><th>end (s)</th>"
        "<th class='l'>place x, y, z (m)</th><th>peak (G)</th>"
        + ("<th>p_false</th>" if has_p_false else "")
        + "<th class='l'>map</th>"
        + ("<th class='l'>truth</th>" if has_truth else "")
        + "</tr>",
    ]
    for r in rows:
        place = "–" if r.place is None else ", ".join(f"{v:.2f}" for v in r.place)
        cells = [
            f"<td>{r.id}</td><td>{r.t_begin_s:.2f}</td><td>{_fmt(r.t_end_s, 4)}</td>",
            f"<td class='l'>{place}</td><td>{r.peak_g:.2f}</td>",
        ]
        if has_p_false:
            cells.append(f"<td>{html.escape(p_false_cell(r))}</td>")
        cells.append(f"<td class='l {r.state}'>{r.state}</td>")
        if has_truth:
            cells.append(f"<td class='l {esc(r.truth or '')}'>{esc(r.truth or '–')}</td>")
        parts.append("<tr>" + "".join(cells) + "</tr>")
    parts.append("</table>")
    if not has_p_false:
        parts.append(
            '<p class="muted">p_false: the detector of this run gave none for these events.</p>'
        )
    parts += [
        '<h2 id="settings">Settings</h2>',
        f"<p>Command: <code>{esc(command)}</code></p>",
        f"<pre>{esc(settings_toml)}</pre>",
        "</body></html>",
    ]
    return "\n".join(parts) + "\n"


def write_report_html(
    path: str | Path,
    *,
    result,
    report: Mapping[str, Any],
    signal: tuple[np.ndarray, np.ndarray],
    threshold_g: float,
    release_g: float,
    trajectory: np.ndarray,
    settings_toml: str,
    command: str,
    window_s: tuple[float | None, float | None] = (None, None),
    score: bool = False,
) -> Path:
    """Write ``report.html`` for one pipeline run (module docstring).

    Parameters
    ----------
    path : output file
    result : PipelineResult
    report : the ``report.json`` dictionary (summary numbers)
    signal : (t_ns (n,) int64, filtered |a| (n,) G)
    threshold_g, release_g : detector threshold and release level, G
    trajectory : (m, 3) flown path, metres
    settings_toml : every setting of the run (``config.to_toml``)
    command : the command line
    window_s : the replayed window, seconds from the log start
    score : the signal is the impulse detector's trigger score (unitless, trigger at 1)
    """
    from groundstation.viewer.headless import render_matplotlib

    truth = result.truth
    rows = event_rows(result, truth)
    t_ns, g = signal
    t_s = (np.asarray(t_ns, dtype=np.int64) - result.start_ns) / 1e9
    sig_fig = signal_figure(t_s, np.asarray(g, float), threshold_g, release_g, rows, truth,
                            result.start_ns, score=score)  # fmt: skip
    buf = io.BytesIO()
    outline = (truth or {}).get("scene", {}).get("objects", []) if truth else []
    render_matplotlib(map_scene(result, trajectory), buf, 1100, 825, outline)
    map_png = "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")
    n_flag = sum(r.state in ("flagged", "awaiting") for r in rows)
    n_wait = sum(r.state == "awaiting" for r in rows)
    start, end = window_s
    window = "whole log" if start is None and end is None else (
        f"{start or 0:g} s to {'end' if end is None else f'{end:g} s'}")  # fmt: skip
    summary = [
        ("log", str(report.get("log", result.log_path))),
        ("window", window),
        ("mode", str(report.get("mode", result.mode))),
        ("duration", f"{result.duration_s:.1f} s"),
        (
            "contacts",
            f"{len(rows)} ({n_flag} flagged"
            + (f", {n_wait} awaiting a second touch)" if n_wait else ")"),
        ),
        ("candidates rejected", rejected_text(result.events)),
        ("observations", observations_text(result)),
        ("vehicle upset", upset_text(result)),
        ("refits", f"{len(result.fits)} (median {_fmt(report.get('refit_s_median'))} s)"),
    ]
    spent = refit_time_text(report.get("refit_time_s") or {})
    if spent:
        summary.append(("refit time", spent))
    summary += truth_rows(report)
    page = render_html(
        title=f"Flight report: {Path(result.log_path).name}",
        summary=summary,
        signal_png=_png(sig_fig),
        map_png=map_png,
        rows=rows,
        settings_toml=settings_toml,
        command=command,
        has_truth=bool(truth and truth.get("contacts") is not None),
        has_p_false=any(r.p_false is not None for r in rows),
        score=score,
    )
    path = Path(path)
    path.write_text(page, encoding="utf-8")
    return path


def refit_time_text(parts: dict) -> str:
    """Where the refits' time went, as the report's summary shows it (``refit_time_s``):
    ``"12.3 s: rows 29 %, fits 29 %, mesh 41 % (GP means 6 %, open-space offset 9 %)"``."""
    total = (parts.get("total") or {}).get("sum_s")
    if not total:
        return ""
    names = (("rows", "rows"), ("fit", "fits"), ("mesh", "mesh"))
    inner = (("mesh_gp", "GP means"), ("mesh_offset", "open-space offset"))

    def share(key: str) -> float | None:
        v = (parts.get(key) or {}).get("share")
        return v if isinstance(v, (int, float)) and math.isfinite(v) else None

    text = f"{total:.1f} s: " + ", ".join(
        f"{label} {100 * share(k):.0f} %" for k, label in names if share(k) is not None
    )
    within = [f"{label} {100 * share(k):.0f} %" for k, label in inner if share(k) is not None]
    return text + (f" ({', '.join(within)})" if within else "")
