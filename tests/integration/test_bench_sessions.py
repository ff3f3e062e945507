"""bench sessions through its command: the batch shell, the summary and the control chart.

The flights it generates by default take minutes each, so this test gives it recordings
(``--logs``): one unreadable, whose task fails without stopping the bench. The pure parts
(flights and their controls, groups, ratios) are tested in ``tests/unit/bench``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

ENV = dict(os.environ, OPENBLAS_NUM_THREADS="1")


def test_bench_sessions_runs_its_tasks_through_batch(tmp_path):
    bad = tmp_path / "broken.mcap"
    bad.write_bytes(b"")
    out = tmp_path / "sessions"
    argv = [sys.executable, "-m", "groundstation.cli", "bench", "sessions", "--logs", str(bad),
            "--out", str(out), "--jobs", "1", "--variant", "base", "--variant",
            "low:contact.lateral_threshold_g=0.7"]  # fmt: skip
    done = subprocess.run(argv, capture_output=True, text=True, env=ENV, timeout=600)
    assert done.returncode == 1, done.stderr
    assert "2 tasks on local Dask cluster, 1 worker(s)" in done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["batch"]["map"] == "final"  # the bench judges the final map
    assert set(summary["groups"]) == {"base", "low"}
    assert len(summary["failed"]) == 2 and "not an MCAP recording" in summary["failed"][0]["error"]
    assert len(list((out / "tasks").glob("broken-*/failed.json"))) == 2
    text = (out / "summary.md").read_text()
    assert text.startswith("# bench sessions") and "## variant low" in text
    for name in ("summary.png", "control.png"):
        assert (out / name).stat().st_size > 0
    # a bad setting is refused before any work
    bad_set = subprocess.run([*argv[:-4], "--set", "mapper.nope=1"], capture_output=True,
                             text=True, env=ENV, timeout=300)  # fmt: skip
    assert bad_set.returncode == 2 and "mapper" in bad_set.stderr
