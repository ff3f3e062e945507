"""Files of a batch: one task's folder (written on a worker) and the batch summary files.

Task folder ``OUT/<log>-<log sha256[:12]>-<settings hash[:12]>/`` (``pipeline.batch.Task.folder``):
the files of ``groundstation replay --out`` (``pipeline.outputs``: report.json,
observations.csv, mesh.ply, snapshots/), ``settings.toml`` (the resolved settings) and
``done.json`` (key, refit times, per-event u, wall time, warnings, worker), written last.
:func:`run_task` writes all of it into ``OUT/.<folder>.partial-<id>/`` and renames that to the
task folder, so a task folder is complete or absent: a worker killed mid-task leaves only a
partial folder (removed by the next batch). A failed task leaves ``<folder>/failed.json`` with
its error instead (and runs again next time).

Summary: ``summary.md``, ``summary.json`` and ``summary.png`` (:func:`write_summary`).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import socket
import time
import traceback
import uuid
import warnings
from pathlib import Path
from typing import Any

from groundstation.errors import GroundstationError
from groundstation.pipeline.batch import DONE, FAILED, Task, replay_settings_text
from groundstation.pipeline.pooling import TRUTH_METRICS, event_u, summary_markdown


def _clean(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_clean(v) for v in obj]
    if hasattr(obj, "item") and callable(obj.item):  # numpy scalars
        return _clean(obj.item())
    return obj


def write_json_atomic(path: Path, payload: Any) -> None:
    """Write JSON (NaN as null) to ``path`` via a temporary file and ``os.replace``."""
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    with open(tmp, "w") as fh:
        json.dump(_clean(payload), fh, indent=1, sort_keys=True)
        fh.write("\n")
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def error_text(exc: BaseException) -> str:
    """``Type: message (hint: ...)`` of an exception, for failed.json and the summary."""
    text = f"{type(exc).__name__}: {exc.message if isinstance(exc, GroundstationError) else exc}"
    if isinstance(exc, GroundstationError) and exc.hint:
        text += f" (hint: {exc.hint})"
    return text


def record_failure(out: Path, task: Task, error: str, trace: str = "") -> None:
    """``OUT/<folder>/failed.json`` with the error (a finished folder is left alone)."""
    folder = out / task.folder
    if (folder / DONE).is_file():
        return
    folder.mkdir(parents=True, exist_ok=True)
    payload = {"key": task.key, "log": task.log, "error": error, "traceback": trace,
               "host": socket.gethostname()}  # fmt: skip
    write_json_atomic(folder / FAILED, payload)


def run_task(task: Task, out_root: str, snapshots: int = 3) -> dict[str, Any]:
    """Run one task on a worker: what ``groundstation replay LOG --out DIR`` runs.

    Returns
    -------
    dict
        ``{"status": "done" | "failed", "folder": ..., "error": ...}`` (small; the results are
        in the folder).
    """
    from groundstation.errors import ConvergenceWarning
    from groundstation.pipeline.offline import run_offline
    from groundstation.pipeline.outputs import KEEP_MESHES, write_outputs

    out = Path(out_root)
    final = out / task.folder
    if (final / DONE).is_file():
        return {"status": "done", "folder": task.folder, "skipped": True}
    t0 = time.perf_counter()
    staging = out / f".{task.folder}.partial-{uuid.uuid4().hex[:8]}"
    try:
        staging.mkdir(parents=True)
        settings = replay_settings_text(task.config, task.map_mode, task.checkpoints, task.software)
        (staging / "settings.toml").write_text(settings)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", ConvergenceWarning)
            result = run_offline(
                task.log,
                task.config,
                keep_meshes=KEEP_MESHES,
                map_mode=task.map_mode,
                checkpoints=task.checkpoints,
            )
            write_outputs(result, staging, snapshots=snapshots, config=task.config)
        marker = {
            "key": task.key, "log": task.log, "log_sha256": task.log_sha256,
            "config_hash": task.config_hash, "map": task.map_mode,
            "checkpoints": task.checkpoints,
            "refit_s": [f.timings.get("total_s", math.nan) for f in result.fits],
            "event_u": event_u(result), "replay_wall_s": result.wall_s,
            "task_wall_s": time.perf_counter() - t0,
            "warnings": sorted({str(w.message) for w in caught})[:20],
            "host": socket.gethostname(), "pid": os.getpid(), "worker": _worker_name(),
        }  # fmt: skip
        write_json_atomic(staging / DONE, marker)  # last file of the task
        if (final / DONE).is_file():  # a duplicate run finished first: keep its folder
            shutil.rmtree(staging, ignore_errors=True)
        else:
            if final.exists():
                shutil.rmtree(final)  # an earlier failed attempt
            os.rename(staging, final)
        return {"status": "done", "folder": task.folder}
    except Exception as exc:
        shutil.rmtree(staging, ignore_errors=True)
        error = error_text(exc)
        record_failure(out, task, error, traceback.format_exc())
        return {"status": "failed", "folder": task.folder, "error": error}


def _worker_name() -> str | None:
    """Name of the Dask worker running this task (None outside a worker)."""
    try:
        from distributed import get_worker

        return str(get_worker().name)
    except (ImportError, ValueError):
        return None


def read_record(out: Path, task: Task) -> dict[str, Any]:
    """The record of a task folder: status, report.json and done.json, or the error."""
    folder = out / task.folder
    if (folder / DONE).is_file():
        try:
            return {
                "status": "done",
                "done": json.loads((folder / DONE).read_text()),
                "report": json.loads((folder / "report.json").read_text()),
            }
        except (OSError, ValueError) as exc:
            return {"status": "failed", "error": f"unreadable results: {exc}"}
    if (folder / FAILED).is_file():
        try:
            return {"status": "failed", "error": json.loads((folder / FAILED).read_text())["error"]}
        except (OSError, ValueError, KeyError) as exc:
            return {"status": "failed", "error": f"unreadable failed.json: {exc}"}
    return {"status": "missing", "error": "not run"}


def write_summary(
    summary: dict[str, Any], out: str | Path, *, markdown: str | None = None, title: str = ""
) -> list[Path]:
    """``summary.md``, ``summary.json`` and ``summary.png`` (one panel per truth metric, every
    log's value per variant and the variant's mean) in ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    text = markdown if markdown is not None else summary_markdown(summary, title or "batch")
    (out / "summary.md").write_text(text)
    write_json_atomic(out / "summary.json", summary)
    paths = [out / "summary.md", out / "summary.json"]
    paths.append(metrics_chart(summary, out / "summary.png", title))
    return paths


def metrics_chart(summary: dict[str, Any], path: Path, title: str = "") -> Path:
    """Strip chart of every truth metric: one column of points per variant, mean as a bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = [*TRUTH_METRICS, "task_wall_s"]
    names = list(summary["variants"])
    ncol = 4
    nrow = math.ceil(len(keys) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.2 * ncol, 2.4 * nrow), squeeze=False)
    for ax, key in zip(axes.flat, keys, strict=False):
        for i, name in enumerate(names):
            ys = [r[name].get(key) for r in summary["logs"].values() if name in r]
            ys = [float(y) for y in ys if y is not None and math.isfinite(float(y))]
            if ys:
                ax.plot([i] * len(ys), ys, "o", alpha=0.5, ms=4)
                ax.hlines(sum(ys) / len(ys), i - 0.3, i + 0.3, color="k")
        ax.set_xlim(-0.6, len(names) - 0.4)
        ax.set_title(key, fontsize=8)
        ax.set_xticks(range(len(names)), names, fontsize=7, rotation=30)
        ax.tick_params(axis="y", labelsize=7)
    for ax in list(axes.flat)[len(keys) :]:
        ax.axis("off")
    fig.suptitle(title or "batch: per-log values (points) and mean (bar) per variant", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
