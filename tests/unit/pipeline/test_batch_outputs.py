"""A batch task's folder protocol, without Dask: complete or absent, errors kept, rerun skips."""

from __future__ import annotations

import json
import math

from groundstation.config import load_config
from groundstation.pipeline.batch import DONE, FAILED, LogInput, plan_batch
from groundstation.pipeline.batch_outputs import read_record, run_task, write_json_atomic


def _task(path, sha="0" * 64):
    plan = plan_batch([LogInput(str(path), sha)], [], lambda _, ov: load_config(None, list(ov)))
    return plan.tasks[0]


def test_a_failing_task_leaves_its_error_and_no_partial_folder(tmp_path):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"definitely not a recording")
    task = _task(bad)
    out = tmp_path / "out"
    result = run_task(task, str(out), snapshots=0)
    assert result["status"] == "failed" and "not an MCAP recording" in result["error"]
    folder = out / task.folder
    assert sorted(p.name for p in out.iterdir()) == [task.folder]  # no .partial-* left
    failed = json.loads((folder / FAILED).read_text())
    assert failed["error"] == result["error"] and "Traceback" in failed["traceback"]
    assert not (folder / DONE).exists()
    assert read_record(out, task) == {"status": "failed", "error": result["error"]}
    assert read_record(out, _task(bad, "1" * 64)) == {"status": "missing", "error": "not run"}


def test_a_finished_folder_is_never_run_again(tmp_path):
    task = _task(tmp_path / "absent.mcap")  # would fail if it ran
    folder = tmp_path / "out" / task.folder
    folder.mkdir(parents=True)
    write_json_atomic(folder / "report.json", {"chamfer_m": 0.1, "x": math.nan})
    write_json_atomic(folder / DONE, {"key": task.key})
    assert run_task(task, str(tmp_path / "out"))["skipped"] is True
    rec = read_record(tmp_path / "out", task)
    assert rec["status"] == "done" and rec["report"] == {"chamfer_m": 0.1, "x": None}
    assert not (folder / FAILED).exists()
    assert [p.name for p in folder.iterdir() if p.name.startswith(".")] == []  # no temp files
