"""``groundstation batch``, the Dask shell: a cluster, task submission, a progress bar.

The plan and the pooling are pure (``pipeline.batch``, ``pipeline.pooling``); what one task
does on disk is ``pipeline.batch_outputs.run_task`` (the production replay,
``pipeline.offline.run_offline`` + ``pipeline.outputs.write_outputs``, into its folder). This
module only moves tasks to Dask distributed and reads the folders back. It lives in the runtime
room because, like the session supervisor, it owns processes (a ``LocalCluster``'s workers) and
their lifetime.

- :class:`Cluster`: an in-process ``LocalCluster`` (workers = cores, one thread and one BLAS
  thread each, scheduler on loopback, no dashboard) or a client of an existing scheduler
  (``tcp://HOST:PORT``, ``tls://...``), started only when there is work.
- :func:`execute` skips finished task folders, removes partial ones, submits the rest, shows
  done / running / failed on stderr (tqdm) and returns every task's record for the summary. A
  worker that dies mid-task is noticed by the scheduler, which reruns its task elsewhere; a task
  that keeps killing workers ends as failed (``KilledWorker``), recorded in its folder.

Logs and ``OUT`` must be reachable under the same paths from every worker (one machine, or a
shared file system) and the workers must run the same groundstation install.
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import functools
import hashlib
import importlib.metadata
import os
import shutil
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from groundstation.errors import ConfigError
from groundstation.pipeline.batch import DONE, LogInput, Plan, Task
from groundstation.pipeline.batch_outputs import error_text, read_record, record_failure, run_task
from groundstation.runtime.configuration import recorded_text

#: Environment of local workers: one BLAS/OpenMP thread each (workers = cores).
ONE_THREAD_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def file_sha256(path: str | Path) -> str:
    """Hex sha256 of a file's bytes (read in 1 MiB blocks)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def tree_digest(root: str | Path) -> str:
    """Hex sha256 of every file under ``root``: each one's relative path and bytes, in path
    order (``__pycache__`` folders left out: they follow the sources)."""
    root = Path(root)
    h = hashlib.sha256()
    files = sorted(
        (p.relative_to(root).as_posix(), p)
        for p in root.rglob("*")
        if p.is_file() and "__pycache__" not in p.relative_to(root).parts
    )
    for rel, p in files:
        h.update(rel.encode() + b"\0")
        h.update(p.read_bytes())
        h.update(b"\0")
    return h.hexdigest()


@functools.cache
def software_id() -> str:
    """This install's identity, ``<version>+<digest[:12]>``: the package version and the
    :func:`tree_digest` of the package's folder. A batch task's key includes it, so results of
    other code are never taken for this code's."""
    try:
        version = importlib.metadata.version("groundstation")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    return f"{version}+{tree_digest(Path(__file__).resolve().parents[1])[:12]}"


def log_input(path: str | Path, overrides: Sequence[str] = (), **labels: str) -> LogInput:
    """A :class:`LogInput` for an existing file (absolute path, content hash, the configuration
    recorded in it)."""
    p = Path(path).resolve()
    labelled = tuple(sorted(labels.items()))
    return LogInput(str(p), file_sha256(p), tuple(overrides), labelled, recorded_text(p))


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
        out[i] = (None, error_text(exc)) if exc is not None else (result, None)
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
                    record_failure(out, task, error_text(exc))
                    return True
                return result.get("status") != "done"

            drive(client, futures, "batch", on_done, quiet)
        records = {t.folder: read_record(out, t) for t in tasks}
    failed = sum(r["status"] != "done" for r in records.values())
    return BatchRun(len(todo), len(tasks) - len(todo), failed, records, time.perf_counter() - t0)
