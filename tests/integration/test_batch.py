"""groundstation batch on real Dask clusters.

- Against a real ``dask scheduler`` and two ``dask worker`` processes (the ``dask`` CLI, TCP on
  loopback): the batch gives the same report.json numbers and observations.csv bytes as the
  sequential ``groundstation replay`` of every (log, variant); one worker is SIGKILLed while it
  runs a task, and every task still completes; a corrupt log fails alone, with its error in its
  folder and the summary; a rerun does no work. The default suite runs the shortest bundled log
  with ``--map final``; ``-m soak`` runs the three bundled logs.
- On the default local cluster (``LocalCluster`` in the batch process): a short log and a
  corrupt one, the summary files, and resume after an interrupted run (a stale partial folder).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from groundstation.cli import main as cli_main
from groundstation.pipeline.outputs import TIMING_KEYS

ROOT = Path(__file__).resolve().parents[2]
LOGS = ROOT / "replay_logs"
BIN = Path(sys.executable).parent
VARIANTS = ("base", "low:contact.lateral_threshold_g=0.7")
#: report.json keys that measure time or name the file, not the result.
UNSTABLE = TIMING_KEYS | {"log", "snapshots"}
ENV = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")


def _spawn(argv: list[str], log: Path) -> subprocess.Popen:
    fh = open(log, "w")  # noqa: SIM115 (closed with the process)
    return subprocess.Popen(argv, stdout=fh, stderr=subprocess.STDOUT, env=ENV,
                            start_new_session=True)  # fmt: skip


def _kill(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(30)


@pytest.fixture
def dask_cluster(tmp_path):
    """A scheduler and two workers (w1, w2) started with the dask CLI; yields (address, procs)."""
    sched_file = tmp_path / "scheduler.json"
    procs: dict[str, subprocess.Popen] = {}
    try:
        procs["scheduler"] = _spawn(
            [str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", "0",
             "--no-dashboard", "--scheduler-file", str(sched_file)],
            tmp_path / "scheduler.log",
        )  # fmt: skip
        deadline = time.monotonic() + 120
        while not sched_file.is_file() and time.monotonic() < deadline:
            assert procs["scheduler"].poll() is None, (tmp_path / "scheduler.log").read_text()
            time.sleep(0.2)
        address = json.loads(sched_file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        for name in ("w1", "w2"):
            procs[name] = _spawn(
                [str(BIN / "dask"), "worker", address, "--name", name, "--nworkers", "1",
                 "--nthreads", "1", "--no-dashboard", "--local-directory",
                 str(tmp_path / f"{name}-scratch")],
                tmp_path / f"{name}.log",
            )  # fmt: skip
        from distributed import Client

        with Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=180)
        yield address, procs
    finally:
        for p in procs.values():
            _kill(p)


def _sequential(log: Path, variant: str, out: Path) -> Path:
    """``groundstation replay LOG --out OUT --map final --set ...`` for one variant."""
    _, _, rest = variant.partition(":")
    sets = [x for s in rest.split(",") if s for x in ("--set", s)]
    argv = ["replay", str(log), "--out", str(out), "--map", "final", "--snapshots", "0",
            "--quiet", *sets]  # fmt: skip
    assert cli_main(argv) == 0
    return out


def _stable(report: dict) -> dict:
    out = {k: v for k, v in report.items() if k not in UNSTABLE}
    if isinstance(out.get("replay_mcap"), dict):  # its size includes the command line
        out["replay_mcap"] = {k: v for k, v in out["replay_mcap"].items() if k != "bytes"}
    return out


def _batch_argv(logs, out, *extra) -> list[str]:
    argv = [sys.executable, "-m", "groundstation.cli", "batch", *map(str, logs), "--out", str(out),
            "--map", "final", "--snapshots", "0", "--quiet"]  # fmt: skip
    for v in VARIANTS:
        argv += ["--variant", v]
    return argv + list(extra)


def _kill_a_busy_worker(
    address: str, out: Path, procs: dict, batch: subprocess.Popen
) -> tuple[str, str]:
    """SIGKILL a worker (its whole process group) while it executes a replay of a real log;
    returns its name and the task folder it was running."""
    from distributed import Client

    with Client(address, timeout="60s") as client:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            assert batch.poll() is None, "the batch ended before a worker could be killed"
            executing = client.run(
                lambda dask_worker: [str(ts.key) for ts in dask_worker.state.executing]
            )
            names = {a: w["name"] for a, w in client.scheduler_info()["workers"].items()}
            busy = [
                (names[a], k.removeprefix("replay-"))
                for a, keys in executing.items()
                for k in keys
                if "corrupt" not in k and k.startswith("replay-")
            ]
            if busy and any(out.glob(f".{busy[0][1]}.partial-*")):
                victim, folder = busy[0]
                os.killpg(procs[victim].pid, signal.SIGKILL)
                procs[victim].wait(30)
                return victim, folder
            time.sleep(0.2)
    raise AssertionError("no worker ever ran a replay task")


def _check_against_sequential(out: Path, logs: list[Path], tmp_path: Path) -> None:
    summary = json.loads((out / "summary.json").read_text())
    for log in logs:
        for v in VARIANTS:
            name = v.partition(":")[0]
            folder = out / summary["logs"][log.stem][name]["folder"]
            assert (folder / "done.json").is_file(), folder
            ref = _sequential(log, v, tmp_path / "sequential" / f"{log.stem}-{name}")
            got = json.loads((folder / "report.json").read_text())
            want = json.loads((ref / "report.json").read_text())
            assert _stable(got) == _stable(want), (log.stem, name)
            assert (folder / "observations.csv").read_bytes() == (
                ref / "observations.csv"
            ).read_bytes()
            assert (folder / "mesh.ply").is_file() == (ref / "mesh.ply").is_file()


def _run_on_cluster(dask_cluster, tmp_path: Path, logs: list[Path]) -> None:
    address, procs = dask_cluster
    corrupt = tmp_path / "corrupt.mcap"
    corrupt.write_bytes(b"not a recording " * 200)
    out = tmp_path / "batch"
    batch = subprocess.Popen(
        _batch_argv([*logs, corrupt], out, "--scheduler", address),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV,
    )  # fmt: skip
    try:
        victim, interrupted = _kill_a_busy_worker(address, out, procs, batch)
        stdout, stderr = batch.communicate(timeout=1200)
    finally:
        if batch.poll() is None:
            batch.kill()
    assert procs[victim].poll() is not None
    # the task the killed worker was running was run again, to the end, by the other one
    marker = json.loads((out / interrupted / "done.json").read_text())
    assert marker["worker"] not in (victim, None), (victim, marker["worker"])
    # the corrupt log failed (exit 1) and nothing else did
    assert batch.returncode == 1, stderr
    summary = json.loads((out / "summary.json").read_text())
    failed = summary["failed"]
    assert len(failed) == 2 and all(f["folder"].startswith("corrupt-") for f in failed), failed
    assert all(f["error"] for f in failed)
    for f in failed:
        err = json.loads((out / f["folder"] / "failed.json").read_text())
        assert err["error"] == f["error"] and not (out / f["folder"] / "done.json").exists()
    assert "FAILED corrupt-" in stderr and "corrupt" in (out / "summary.md").read_text()
    assert summary["batch"]["ran"] == 2 * (len(logs) + 1)
    assert (out / "summary.png").stat().st_size > 0
    _check_against_sequential(out, logs, tmp_path)

    # a rerun of the finished logs does no work: no cluster contact, no file rewritten
    stamps = {p: p.stat().st_mtime_ns for p in out.glob("*/done.json")}
    again = subprocess.run(_batch_argv(logs, out, "--scheduler", "tcp://127.0.0.1:9"),
                           capture_output=True, text=True, env=ENV, timeout=300)  # fmt: skip
    assert again.returncode == 0, again.stderr
    assert f"0 tasks run, {2 * len(logs)} finished earlier, 0 failed" in again.stderr
    assert stamps == {p: p.stat().st_mtime_ns for p in out.glob("*/done.json")}
    assert not list(out.glob(".*.partial-*"))  # the killed task's partial folder is gone


def test_batch_on_a_dask_cli_cluster_survives_a_killed_worker(dask_cluster, tmp_path):
    _run_on_cluster(dask_cluster, tmp_path, [LOGS / "wall_slow_touch_gusts.mcap"])


@pytest.mark.soak
@pytest.mark.timeout(3600)  # 6 tasks + 6 sequential replays: ~10 min on a loaded machine
def test_batch_of_every_bundled_log_on_a_dask_cli_cluster(dask_cluster, tmp_path):
    logs = [LOGS / f"{n}.mcap" for n in ("wall_survey", "pillar_survey", "wall_slow_touch_gusts")]
    _run_on_cluster(dask_cluster, tmp_path, logs)


def test_batch_on_the_default_local_cluster_resumes(tmp_path):
    # a recording cut short (as a crash leaves it): replayable up to its last complete chunk
    data = (LOGS / "wall_slow_touch_gusts.mcap").read_bytes()
    short = tmp_path / "short.mcap"
    short.write_bytes(data[: len(data) // 3])
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    out = tmp_path / "out"
    stale = out / ".short-000000000000-000000000000.partial-deadbeef"
    stale.mkdir(parents=True)  # what a killed batch leaves behind
    argv = [sys.executable, "-m", "groundstation.cli", "batch", str(short), str(empty), "--out",
            str(out), "--map", "final", "--snapshots", "0", "--workers", "2"]  # fmt: skip
    done = subprocess.run(argv, capture_output=True, text=True, env=ENV, timeout=900)
    assert done.returncode == 1, done.stderr
    assert "local Dask cluster, 2 worker(s)" in done.stderr
    assert "running" in done.stderr and "failed 1" in done.stderr  # the progress bar
    assert not stale.exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["logs"]["short"]["default"]["status"] == "done"
    assert summary["logs"]["empty"]["default"]["status"] == "failed"
    assert "empty" in summary["failed"][0]["folder"] and summary["failed"][0]["error"]
    for name in ("summary.md", "summary.json", "summary.png"):
        assert (out / name).stat().st_size > 0
    folder = out / summary["logs"]["short"]["default"]["folder"]
    for name in ("report.json", "observations.csv", "settings.toml", "done.json"):
        assert (folder / name).is_file()
    marker = json.loads((folder / "done.json").read_text())
    assert marker["map"] == "final" and len(marker["key"]) == 129
    # the failed task runs again on the next batch; the finished one does not
    again = subprocess.run(argv, capture_output=True, text=True, env=ENV, timeout=900)
    assert again.returncode == 1 and "1 tasks run, 1 finished earlier, 1 failed" in again.stderr
