"""``groundstation bench inject``: one false contact planted in each real contact-free flight.

The real flights of ``../shared/external_data/aggressive_flight`` (a DJI quadrotor, RTK ground
truth as the pose) hold no contact at all: the detector finds none on them, so the map has only
free space, one row per 0.1 m of path. That is the case a false contact is hardest on for speed:
when one arrives, the live mapper must refit a region dense with free-space rows at once. This
bench detects each flight once (:func:`~groundstation.pipeline.offline.detect_offline`), plants
one contact event where a gust would put it (on the vehicle's rim, ``radius`` from a path point
at ``at`` of the flight, facing a seeded horizontal direction, with its internal point behind),
then replays the flight through the whole pipeline on the live refit cadence with that contact
handed to the mapper at its data time (``run_offline(inject=)``). It reports every refit's time,
the refit that took the contact in (the issue's line: <= 1 s), and whether the final map flags
the contact. Pure functions; ``groundstation bench inject`` (``cli/bench.py``) loops over the
files and writes the table.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from groundstation.config import Config
from groundstation.contact.detector import LABEL_INSIDE, LABEL_SURFACE, Observation

#: event id of the planted contact (far above any a detector numbers in one flight)
PLANTED_EVENT = 1_000_000_000


@dataclasses.dataclass(frozen=True)
class Planted:
    """The planted contact: its data time, place and observations."""

    t_ns: int
    contact: np.ndarray
    observations: tuple[Observation, ...]


def plant(
    observations: Sequence[Observation],
    *,
    at: float,
    radius_m: float,
    internal_depth_m: float,
    seed: int = 0,
    samples: int = 3,
    period_ns: int = 40_000_000,
) -> Planted:
    """A false contact on the vehicle's rim at the free-space point nearest ``at`` (a fraction
    of the flight's free-space time span), facing a horizontal direction drawn from ``seed``:
    where a gust's 'contact' lies. Like a short gust event it has ``samples`` contact /
    internal pairs ``period_ns`` apart (the detector's 25 Hz). Raises ValueError when there is
    no free-space point."""
    free = [o for o in observations if o.label > 0]
    if not free:
        raise ValueError("no free-space observation to plant a contact beside")
    if not 0.0 <= at <= 1.0:
        raise ValueError(f"at must be in [0, 1], got {at!r}")
    t0, t1 = free[0].t_ns, free[-1].t_ns
    target = t0 + at * (t1 - t0)
    o = min(free, key=lambda f: abs(f.t_ns - target))
    phi = np.random.default_rng(seed).uniform(0.0, 2.0 * math.pi)
    d = np.array([math.cos(phi), math.sin(phi), 0.0])
    contact = np.asarray(o.position, dtype=np.float64) + radius_m * d
    normal = -d  # the 'structure' would lie beyond the rim: its outward normal faces the vehicle
    first = max((x.id for x in observations), default=-1) + 1
    common = dict(event_id=PLANTED_EVENT, accel_g=2.0)
    inside = contact - internal_depth_m * normal
    obs: list[Observation] = []
    for k in range(samples):
        t = o.t_ns + k * period_ns
        obs.append(Observation(first + 2 * k, t, contact, LABEL_SURFACE, normal, **common))
        obs.append(Observation(first + 2 * k + 1, t, inside, LABEL_INSIDE, normal, **common))
    return Planted(o.t_ns, contact, tuple(obs))


def summarize(name: str, duration_s: float, planted: Planted, result: Any) -> dict[str, Any]:
    """One flight's row: refit times, the refit that took the contact in, its final flag."""
    fits = result.fits
    times = np.array([f.timings.get("total_s", math.nan) for f in fits], dtype=np.float64)
    took = next((f for f in fits if f.data_ns >= planted.t_ns), None)
    final = result.final
    ids = {o.id for o in planted.observations}
    p_map = math.nan
    if final is not None and final.p_false is not None:
        sel = np.isin(final.ids, list(ids))
        if sel.any():
            p_map = float(np.mean(final.p_false[sel]))
    free = sum(o.label > 0 for o in result.observations)
    return {
        "flight": name,
        "duration_s": round(duration_s, 1),
        "free_space_points": int(free),
        "contacts_detected": sum(1 for e in result.events if e.payload.get("state") == "begin"),
        "rows_final": None if final is None else int(len(final.ids)),
        "refits": len(fits),
        "refit_median_s": _q(times, 50),
        "refit_p95_s": _q(times, 95),
        "refit_max_s": _q(times, 100),
        "contact_refit_s": None if took is None else took.timings.get("total_s"),
        "flagged": final is not None and PLANTED_EVENT in final.flagged_events,
        "p_false_map": None if math.isnan(p_map) else round(p_map, 3),
        "contact": [round(float(v), 3) for v in planted.contact],
    }


def _q(x: np.ndarray, q: float) -> float | None:
    x = x[np.isfinite(x)]
    return round(float(np.percentile(x, q)), 3) if x.size else None


def measure(log: str, name: str, config: Config, *, at: float, seed: int) -> dict[str, Any]:
    """Detect, plant, replay on the live cadence, summarise (one flight)."""
    from groundstation.mapping.model import training_policy
    from groundstation.pipeline.offline import detect_offline, run_offline

    det = detect_offline(log, config)
    pol = training_policy(config.mapping, config.vehicle, config.contact.internal_depth_m)
    planted = plant(
        det.observations,
        at=at,
        radius_m=pol.body_radius_m,
        internal_depth_m=config.contact.internal_depth_m,
        seed=seed,
    )
    res = run_offline(log, config, map_mode="live", inject=planted.observations)
    return summarize(name, det.duration_s, planted, res)


COLUMNS = (
    ("flight", "flight"),
    ("duration_s", "s"),
    ("free_space_points", "free-space points"),
    ("contacts_detected", "contacts detected"),
    ("refits", "refits"),
    ("refit_median_s", "refit median s"),
    ("refit_p95_s", "refit p95 s"),
    ("refit_max_s", "refit max s"),
    ("contact_refit_s", "refit taking the contact in, s"),
    ("flagged", "planted contact flagged"),
    ("p_false_map", "its P(false)"),
)


def markdown(rows: Sequence[dict[str, Any]]) -> str:
    """The table of ``inject.md``, with the pooled line."""
    head = "| " + " | ".join(h for _, h in COLUMNS) + " |"
    lines = [head, "|" + "---|" * len(COLUMNS)]
    for r in rows:
        lines.append("| " + " | ".join(_cell(r.get(k)) for k, _ in COLUMNS) + " |")
    took = [r["contact_refit_s"] for r in rows if r["contact_refit_s"] is not None]
    flagged = sum(bool(r["flagged"]) for r in rows)
    lines.append("")
    lines.append(
        f"Planted contacts flagged: {flagged} of {len(rows)}. Refit taking the contact in: "
        f"worst {_cell(max(took) if took else None)} s (target <= 1 s)."
    )
    return "\n".join(lines) + "\n"


def _cell(v: Any) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "**no**"
    if isinstance(v, float):
        return f"{v:.3f}" if abs(v) < 10 else f"{v:.1f}"
    return str(v)


def real_logs(paths: Sequence[str], files: Sequence[str], cache: Path) -> list[tuple[str, str]]:
    """(log, name) of each real flight, imported into ``cache`` once."""
    from groundstation.bench.detector import external_data_root, import_real_flight

    root = external_data_root()
    out = []
    for p in paths:
        for f in files:
            log = import_real_flight(root, p, f, cache)
            out.append((str(log), f"{p}/{Path(f).stem}"))
    return out
