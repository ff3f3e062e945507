"""``groundstation batch``, the pure part: task keys, config hashing, pooling and the summary text.

A batch replays every (log, variant) pair with ``pipeline.offline.run_offline`` and writes the
outputs of ``groundstation replay --out`` per pair. This module holds what needs no cluster,
files or clock, so it is tested without Dask: the Dask shell is ``groundstation.runtime.batch``.

Task keys
---------
A task is identified by the log's content (sha256 of its bytes) and the *resolved* settings:
:func:`config_hash` hashes ``groundstation config show``'s TOML of the effective
:class:`~groundstation.config.Config` plus the replay mode (``--map``, checkpoints). Two variants
that resolve to the same settings are one task; a renamed or copied log is the same task; a
changed default changes the key. The task folder :attr:`Task.folder` carries both hashes.

Pooled metrics (per variant, over its finished tasks)
-----------------------------------------------------
``metrics``: for every truth metric of ``report.json`` (:data:`TRUTH_METRICS`), the number of
tasks that have it, its mean, median and worst (largest for errors, smallest for rates to
maximise). ``shares``: event counts pooled over tasks (gust / touch events flagged, flag
precision, touches detected). ``u_auc``: probability that a gust event's median contact u
exceeds a touch event's. ``refit_s_median``: median over every refit of every task.
``task_wall_s``: mean / median / max wall time of one task (replay + outputs).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import statistics
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from groundstation.config import Config, to_toml
from groundstation.errors import ConfigError

#: Truth metrics of ``report.json`` pooled by a batch, and which way is better.
TRUTH_METRICS: dict[str, str] = {
    "mesh_to_truth_median_m": "low",
    "truth_to_mesh_median_m": "low",
    "missing_share": "low",
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

#: Name of the marker a finished task writes last (atomically) into its folder.
DONE = "done.json"
#: Written instead when the task failed (its error; the task reruns next time).
FAILED = "failed.json"

MAP_MODES = ("live", "final")


@dataclasses.dataclass(frozen=True)
class Variant:
    """A named list of ``--set`` overrides: ``NAME`` or ``NAME:key=value,key=value``.

    A value may itself hold commas (``surface.region_min=0,0,0``): a piece without ``=``
    continues the previous item.
    """

    name: str
    overrides: tuple[str, ...] = ()

    @classmethod
    def parse(cls, text: str) -> Variant:
        name, _, rest = text.partition(":")
        name = name.strip()
        if not name:
            raise ConfigError(
                f"--variant {text!r}: give a name", hint="e.g. --variant low:contact.threshold_g=1"
            )
        items: list[str] = []
        for piece in rest.split(","):
            if "=" in piece or not items:
                items.append(piece.strip())
            else:
                items[-1] += "," + piece.strip()
        items = [s for s in items if s]
        for item in items:
            key, sep, _ = item.partition("=")
            if not sep or not key.strip():
                raise ConfigError(f"--variant {text!r}: {item!r} is not key=value")
        return cls(name, tuple(items))


@dataclasses.dataclass(frozen=True)
class LogInput:
    """One recording of a batch.

    Attributes
    ----------
    path : str
        Absolute path (workers of a remote cluster must see the same path).
    sha256 : str
        Hex digest of the file's bytes.
    overrides : tuple of str
        Settings this log needs before the batch's own (e.g. its airframe's ``[vehicle]``).
    labels : tuple of (str, str)
        Free tags carried into the summary (``engine``, ``role``, ``pair``...).
    """

    path: str
    sha256: str
    overrides: tuple[str, ...] = ()
    labels: tuple[tuple[str, str], ...] = ()

    @property
    def name(self) -> str:
        return Path(self.path).stem

    def label(self, key: str, default: str = "") -> str:
        return dict(self.labels).get(key, default)


@dataclasses.dataclass(frozen=True)
class Task:
    """One replay: a log under resolved settings (what a worker runs)."""

    log: str
    log_sha256: str
    config: Config
    config_hash: str
    map_mode: str = "live"
    checkpoints: int = 0

    @property
    def key(self) -> str:
        """``<log sha256>-<config hash>`` (hex): the identity of the result."""
        return f"{self.log_sha256}-{self.config_hash}"

    @property
    def folder(self) -> str:
        """``<log stem>-<log sha256[:12]>-<config hash[:12]>``."""
        stem = "".join(c if c.isalnum() or c in "-_." else "_" for c in Path(self.log).stem)
        return f"{stem[:60]}-{self.log_sha256[:12]}-{self.config_hash[:12]}"


@dataclasses.dataclass(frozen=True)
class Cell:
    """One (variant, log) pair of the plan and the task that answers it."""

    variant: str
    log: LogInput
    task: Task


@dataclasses.dataclass(frozen=True)
class Plan:
    """Every cell of a batch and its distinct tasks (in first-use order)."""

    cells: tuple[Cell, ...]
    variants: tuple[Variant, ...]
    base_overrides: tuple[str, ...] = ()

    @property
    def tasks(self) -> tuple[Task, ...]:
        seen: dict[str, Task] = {}
        for c in self.cells:
            seen.setdefault(c.task.folder, c.task)
        return tuple(seen.values())


def replay_settings_text(config: Config, map_mode: str, checkpoints: int) -> str:
    """The resolved settings of a task as TOML: the config and the replay mode."""
    return to_toml(config) + f"\n[replay]\nmap = {map_mode!r}\ncheckpoints = {int(checkpoints)}\n"


def config_hash(config: Config, map_mode: str = "live", checkpoints: int = 0) -> str:
    """sha256 (hex) of :func:`replay_settings_text`."""
    return hashlib.sha256(replay_settings_text(config, map_mode, checkpoints).encode()).hexdigest()


def plan_batch(
    logs: Sequence[LogInput],
    variants: Sequence[Variant],
    resolve: Callable[[Sequence[str]], Config],
    *,
    base_overrides: Sequence[str] = (),
    map_mode: str = "live",
    checkpoints: int = 0,
) -> Plan:
    """Every (variant, log) cell with its task.

    Parameters
    ----------
    logs : sequence of LogInput
    variants : sequence of Variant
        Names must be unique; none means one variant ``default``.
    resolve : callable
        ``overrides -> Config`` (``load_config`` bound to the ``--config`` file); raises
        ``ConfigError`` on a bad setting, before any work.
    base_overrides : sequence of str
        ``--set`` items of the batch; a log's own overrides come first, the variant's last.
    """
    if map_mode not in MAP_MODES:
        raise ConfigError(f"--map {map_mode!r}: use live or final")
    if checkpoints < 0:
        raise ConfigError(f"checkpoints must be >= 0, got {checkpoints}")
    variants = tuple(variants) or (Variant("default"),)
    names = [v.name for v in variants]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"--variant names must be unique: {', '.join(dup)} given twice")
    if not logs:
        raise ConfigError("a batch needs at least one log")
    cells: list[Cell] = []
    cache: dict[tuple[str, ...], tuple[Config, str]] = {}
    for v in variants:
        for log in logs:
            overrides = (*log.overrides, *base_overrides, *v.overrides)
            if overrides not in cache:
                cfg = resolve(list(overrides))
                cache[overrides] = (cfg, config_hash(cfg, map_mode, checkpoints))
            cfg, h = cache[overrides]
            task = Task(log.path, log.sha256, cfg, h, map_mode, checkpoints)
            cells.append(Cell(v.name, log, task))
    return Plan(tuple(cells), variants, tuple(base_overrides))


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

    shares = {
        "gust_events_flagged": _share(total("events_flagged_false"), total("events_false")),
        "touch_events_flagged": _share(
            total("touch_events_flagged", "events_touch"), total("events_touch")
        ),
        "fp_precision": _share(total("events_flagged_false"), total("events_flagged")),
        "detection_recall": _share(
            total("detection_recall", "truth_touches"), total("truth_touches")
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
    for key in ("gust_events_flagged", "touch_events_flagged", "fp_precision", "detection_recall"):
        row = []
        for name in names:
            s = variants[name]["pooled"]["shares"][key]
            row.append(f"{fmt(s['share'], '.2f')} ({fmt(s['num'], '.0f')}/{fmt(s['den'], '.0f')})")
        lines.append(f"| {key} | " + " | ".join(row) + " |")
    rows = {
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
    lines += ["| log | variant | status | " + " | ".join(cols) + " | contacts | task wall (s) |"]
    lines += ["|---|---|---|" + "---|" * (len(cols) + 2)]
    for log, per in summary["logs"].items():
        for name, r in per.items():
            lines.append(
                f"| {log} | {name} | {r['status']} | "
                + " | ".join(fmt(r.get(k)) for k in cols)
                + f" | {fmt(r.get('contacts'), '.0f')} | {fmt(r.get('task_wall_s'), '.1f')} |"
            )
    if summary.get("failed"):
        lines += ["", "## Failed or missing tasks", ""]
        for f in summary["failed"]:
            err = (f.get("error") or "not run").strip().splitlines()
            lines.append(f"- `{f['folder']}`: {err[-1] if err else 'not run'}")
    return "\n".join(lines) + "\n"
