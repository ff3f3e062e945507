"""``groundstation batch``, the Dask shell: a cluster, task folders on disk, a progress bar.

The pure part (task keys, config hashing, pooling, markdown) is ``pipeline.batch``; this module
only moves tasks to Dask distributed and results to and from files. It lives in the runtime
room because, like the session supervisor, it owns processes (a ``LocalCluster``'s workers) and
their lifetime; the work itself is the production replay (``pipeline.offline.run_offline`` +
``pipeline.outputs.write_outputs``), unchanged.

- :class:`Cluster`: an in-process ``LocalCluster`` (workers = cores, one thread and one BLAS
  thread each, scheduler on loopback, no dashboard) or a client of an existing scheduler
  (``tcp://HOST:PORT``), started only when there is work.
- :func:`run_task` runs on a worker: replay into ``OUT/.<folder>.partial-<id>/``, write
  ``done.json`` last (atomically), then rename the folder to ``OUT/<folder>/``. A task folder is
  either complete or absent; an error leaves ``OUT/<folder>/failed.json`` (and is retried on the
  next run). A worker killed mid-task leaves only a partial folder, removed by the next batch;
  Dask reruns its task on another worker.
- :func:`execute` skips finished folders, submits the rest, shows done / running / failed on
  stderr (tqdm) and returns every task's record for the summary.

Logs and ``OUT`` must be reachable under the same paths from every worker (one machine, or a
shared file system) and the workers must run the same groundstation install.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import json
import math
import os
import shutil
import socket
import sys
import time
import traceback
import uuid
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from groundstation.errors import ConfigError, GroundstationError
from groundstation.pipeline.batch import (
    DONE,
    FAILED,
    TRUTH_METRICS,
    LogInput,
    Plan,
    Task,
    event_u,
    replay_settings_text,
    summary_markdown,
)

#: Environment of local workers: one BLAS/OpenMP thread each (workers = cores).
ONE_THREAD_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file's bytes (read in 1 MiB blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def log_input(path: str | Path, overrides: Sequence[str] = (), **labels: str) -> LogInput:
    """A :class:`LogInput` for an existing file (absolute path, content hash)."""
    p = Path(path).resolve()
    return LogInput(str(p), file_sha256(p), tuple(overrides), tuple(sorted(labels.items())))


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


def _error_text(exc: BaseException) -> str:
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
    from groundstation.pipeline.outputs import write_outputs

    out = Path(out_root)
    final = out / task.folder
    if (final / DONE).is_file():
        return {"status": "done", "folder": task.folder, "skipped": True}
    t0 = time.perf_counter()
    staging = out / f".{task.folder}.partial-{uuid.uuid4().hex[:8]}"
    try:
        staging.mkdir(parents=True)
        settings = replay_settings_text(task.config, task.map_mode, task.checkpoints)
        (staging / "settings.toml").write_text(settings)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", ConvergenceWarning)
            result = run_offline(
                task.log, task.config, map_mode=task.map_mode, checkpoints=task.checkpoints
            )
            write_outputs(result, staging, snapshots=snapshots)
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
        error = _error_text(exc)
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


class Cluster:
    """A Dask client, started on first use.

    Parameters
    ----------
    scheduler : str, optional
        Address of an existing scheduler (``tcp://HOST:PORT``); None starts a ``LocalCluster``.
    workers : int, optional
        Local workers (default: the cores this process may use).
    """

    def __init__(self, scheduler: str | None = None, workers: int | None = None):
        if workers is not None and workers < 1:
            raise ConfigError(f"--workers must be >= 1, got {workers}")
        self.scheduler = scheduler
        self.workers = workers or len(os.sched_getaffinity(0))
        self._cluster = None
        self._client = None

    @property
    def description(self) -> str:
        if self.scheduler:
            return f"Dask scheduler {self.scheduler}"
        return f"local Dask cluster, {self.workers} worker(s) x 1 thread"

    @property
    def client(self):
        if self._client is None:
            import logging

            from distributed import Client, LocalCluster

            if self.scheduler:
                try:
                    self._client = Client(self.scheduler, timeout="20s")
                except (OSError, TimeoutError, TypeError, ValueError) as exc:
                    hint = (
                        "a tls:// scheduler needs the client's certificates in the Dask "
                        "configuration (distributed.comm.tls.ca-file, .client.cert, .client.key)"
                        if self.scheduler.startswith("tls://")
                        else "start one with 'dask scheduler' and 'dask worker ADDRESS', "
                        "or leave --scheduler out for a local cluster"
                    )
                    raise ConfigError(
                        f"--scheduler {self.scheduler}: cannot connect ({type(exc).__name__}: "
                        f"{exc})",
                        hint=hint,
                    ) from None
            else:
                self._cluster = LocalCluster(
                    n_workers=self.workers, threads_per_worker=1, processes=True,
                    host="127.0.0.1", dashboard_address=None, silence_logs=logging.ERROR,
                    env=dict(ONE_THREAD_ENV),
                )  # fmt: skip
                self._client = Client(self._cluster)
        return self._client

    def close(self) -> None:
        if self._client is not None:
            self._client.close()
        if self._cluster is not None:
            self._cluster.close()
        self._client = self._cluster = None

    def __enter__(self) -> Cluster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextlib.contextmanager
def _locked(out: Path) -> Iterator[None]:
    out.mkdir(parents=True, exist_ok=True)
    with open(out / ".batch.lock", "w") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise ConfigError(
                f"another batch is writing to {str(out)!r}",
                hint="wait for it, or use another --out",
            ) from None
        yield


def drive(
    client: Any,
    futures: dict[Any, Any],
    desc: str,
    on_done: Callable[[Any, Any, BaseException | None], bool],
    quiet: bool = False,
) -> None:
    """Wait for ``futures`` (future -> item) with a progress bar of done / running / failed.

    ``on_done(item, result, exception)`` returns True when the item failed.
    """
    from distributed import wait
    from tqdm import tqdm

    pending = set(futures)
    keys = {f.key for f in futures}
    failed = 0
    with tqdm(total=len(futures), desc=desc, unit="task", file=sys.stderr, disable=quiet) as bar:
        while pending:
            with contextlib.suppress(TimeoutError):
                wait(list(pending), timeout=1.0, return_when="FIRST_COMPLETED")
            for f in [f for f in pending if f.done()]:
                pending.discard(f)
                exc = f.exception() if f.status in ("error", "cancelled") else None
                if f.status == "cancelled" and exc is None:
                    exc = RuntimeError("cancelled by the scheduler")
                failed += bool(on_done(futures[f], None if exc else f.result(), exc))
                bar.update(1)
            try:  # tasks on a worker beyond its threads are queued there, not running
                threads = client.nthreads()
                running = sum(
                    min(sum(k in keys for k in ks), threads.get(w, 1))
                    for w, ks in client.processing().items()
                )
            except Exception:  # the bar is cosmetic; a busy scheduler must not stop the batch
                running = -1
            bar.set_postfix_str(f"running {running if running >= 0 else '?'}, failed {failed}")


def run_all(
    cluster: Cluster, fn: Callable[..., Any], calls: Sequence[tuple], desc: str, quiet: bool = False
) -> list[tuple[Any, str | None]]:
    """``fn(*args)`` for every ``args`` in ``calls`` on the cluster: ``(result, None)`` or
    ``(None, error text)`` per call, in order (one failure does not stop the others)."""
    if not calls:
        return []
    client = cluster.client
    futures = {client.submit(fn, *args, pure=False): i for i, args in enumerate(calls)}
    out: list[tuple[Any, str | None]] = [(None, "not run")] * len(calls)

    def on_done(i: int, result: Any, exc: BaseException | None) -> bool:
        out[i] = (None, _error_text(exc)) if exc is not None else (result, None)
        return exc is not None

    drive(client, futures, desc, on_done, quiet)
    return out


@dataclasses.dataclass
class BatchRun:
    """What :func:`execute` did: tasks run, skipped (finished earlier), failed; records."""

    ran: int
    skipped: int
    failed: int
    records: dict[str, dict[str, Any]]
    wall_s: float


def execute(
    plan: Plan, out: str | Path, cluster: Cluster, *, snapshots: int = 3, quiet: bool = False
) -> BatchRun:
    """Run every unfinished task of ``plan`` on ``cluster``; return every task's record."""
    out = Path(out).resolve()
    t0 = time.perf_counter()
    with _locked(out):
        for stale in out.glob(".*.partial-*"):  # left by an interrupted batch or killed worker
            shutil.rmtree(stale, ignore_errors=True)
        tasks = plan.tasks
        todo = [t for t in tasks if not (out / t.folder / DONE).is_file()]
        if todo:
            client = cluster.client
            futures = {
                client.submit(run_task, t, str(out), snapshots, key=f"replay-{t.folder}",
                              pure=False): t
                for t in todo
            }  # fmt: skip

            def on_done(task: Task, result: Any, exc: BaseException | None) -> bool:
                if exc is not None:  # e.g. KilledWorker: the task took down workers repeatedly
                    record_failure(out, task, _error_text(exc))
                    return True
                return result.get("status") != "done"

            drive(client, futures, "batch", on_done, quiet)
        records = {t.folder: read_record(out, t) for t in tasks}
    failed = sum(r["status"] != "done" for r in records.values())
    return BatchRun(len(todo), len(tasks) - len(todo), failed, records, time.perf_counter() - t0)


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
