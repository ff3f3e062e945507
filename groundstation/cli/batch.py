"""``groundstation batch LOG... --out DIR [--variant NAME:key=value,...]... [--scheduler ADDRESS]
[--map live|final] [--config FILE] [--set KEY=VALUE]...``

Replays every (log, variant) pair as one task on Dask distributed: an in-process local
cluster by default (``--workers``, default = cores; one thread and one BLAS thread per worker),
or an existing cluster with ``--scheduler tcp://HOST:PORT``. Each task runs what ``groundstation
replay LOG --out OUT/<task folder> [--map ...] --set ...`` runs and writes the same files there;
the folder is named ``<log>-<log sha256[:12]>-<settings hash[:12]>`` so a rerun skips finished
tasks and an interrupted batch resumes. A failed task keeps its error in ``failed.json`` and the
summary; the others go on. At the end ``OUT/summary.md``, ``summary.json`` and ``summary.png``
pool the truth metrics per variant (``pipeline.pooling``). Exit status 1 when a task failed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from groundstation.errors import InputDataError


def add_batch_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("logs", nargs="+", metavar="LOG", help="recordings (.mcap)")
    parser.add_argument("--out", required=True, help="output folder (one folder per task)")
    parser.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME[:KEY=V,...]",
        help="a setting variant (repeatable; default: one variant 'default' with no overrides)",
    )
    parser.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="existing Dask scheduler, e.g. tcp://10.0.0.5:8786 (default: a local cluster)",
    )
    parser.add_argument(
        "--workers", type=int, default=None, help="local cluster workers (default: cores)"
    )
    parser.add_argument(
        "--map",
        choices=("live", "final"),
        default="live",
        help="as replay --map: live refit cadence (default) or the final map (fits only where "
        "the live mapper learns its kernel)",
    )
    parser.add_argument("--config", default=None, help="TOML configuration file (every task)")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="override a setting"
    )
    parser.add_argument("--snapshots", type=int, default=3, help="PNG snapshots per task")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def resolve_logs(paths: list[str]) -> list[Path]:
    """The given recordings, each once; every one must exist."""
    logs = list(dict.fromkeys(Path(p) for p in paths))
    missing = [str(p) for p in logs if not p.is_file()]
    if missing:
        raise InputDataError(f"recordings not found: {', '.join(missing)}")
    return logs


def run_batch(args: argparse.Namespace) -> int:
    from groundstation.errors import ConfigError
    from groundstation.pipeline.batch import Variant, plan_batch
    from groundstation.pipeline.batch_outputs import write_summary
    from groundstation.pipeline.pooling import summarize, summary_markdown
    from groundstation.runtime.batch import Cluster, execute, log_input, software_id
    from groundstation.runtime.configuration import recorded_note, recording_resolver

    if args.snapshots < 0:
        raise ConfigError(f"--snapshots must be >= 0, got {args.snapshots}")
    variants = [Variant.parse(v) for v in args.variant]
    logs = [log_input(p) for p in resolve_logs(args.logs)]
    plan = plan_batch(
        logs,
        variants,
        recording_resolver(args.config),
        base_overrides=args.set,
        map_mode=args.map,
        software=software_id(),
    )
    for line in recorded_note([log.recorded for log in logs], "batch"):
        print(line, file=sys.stderr)
    out = Path(args.out)
    with Cluster(args.scheduler, args.workers) as cluster:
        print(
            f"batch: {len(plan.cells)} (log, variant) pairs = {len(plan.tasks)} tasks "
            f"on {cluster.description}",
            file=sys.stderr,
        )
        run = execute(plan, out, cluster, snapshots=args.snapshots, quiet=args.quiet)
    summary = summarize(plan, run.records)
    summary["batch"] = {
        "ran": run.ran, "skipped": run.skipped, "failed": run.failed, "wall_s": run.wall_s,
        "cluster": cluster.description, "map": args.map,
    }  # fmt: skip
    text = summary_markdown(summary, "groundstation batch")
    write_summary(summary, out, markdown=text)
    print(text)
    print(
        f"batch: {run.ran} tasks run, {run.skipped} finished earlier, {run.failed} failed, "
        f"{run.wall_s:.1f} s; wrote {out / 'summary.md'}, summary.json, summary.png",
        file=sys.stderr,
    )
    for f in summary["failed"]:
        print(f"batch: FAILED {f['folder']}: {f['error']}", file=sys.stderr)
    return 1 if run.failed else 0
