"""``groundstation sitl --physics mujoco`` as a real process: the recording replays through the
station's decoders, the truth names the engine, airframe and gust settings, the command stored
in the recording reproduces the same decoded samples, and bad options exit 2 with a hint."""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

from groundstation.acquisition.decoders import content_key
from groundstation.acquisition.reader import open_recording
from groundstation.acquisition.replay import iter_replay

ROOT = Path(__file__).resolve().parents[2]
SITL = [sys.executable, "-m", "groundstation.cli", "sitl"]
RUN = ["--scene", "yard", "--pilot", "script:varied", "--seed", "4", "--duration", "12",
       "--physics", "mujoco", "--gust-rate", "12", "--gust-force", "5:15",
       "--gust-duration", "0.05:0.2", "--gust-cluster", "0.5", "--speed", "max"]  # fmt: skip

pytestmark = pytest.mark.timeout(300)


def _run(args: list[str], cwd: Path = ROOT) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.run(
        SITL + args, cwd=cwd, env=env, capture_output=True, text=True, timeout=240
    )


def _samples(path: Path) -> dict[str, list]:
    out: dict[str, list] = defaultdict(list)
    for e in iter_replay(str(path)):
        out[e.topic].append(content_key(e))
    return out


def test_mujoco_recording_replays_and_reproduces(tmp_path):
    log = tmp_path / "mj.mcap"
    done = _run([*RUN, "--record", str(log)])
    assert done.returncode == 0, done.stderr
    with open_recording(log) as rec:
        truth = rec.truth()
        created_by = rec.metadata()["created_by"]
    assert truth["physics"]["engine"] == "mujoco" and truth["physics"]["mujoco_version"]
    assert truth["settings"]["physics"] == "mujoco"
    assert truth["airframe"]["layout"] == "x" and 0.25 <= truth["airframe"]["reach_min"]
    assert truth["settings"]["gust_force_n"] == [5.0, 15.0]
    gusts = truth["gusts"]
    assert gusts and all(5.0 <= g["peak_force_n"] <= 15.0 for g in gusts)
    samples = _samples(log)
    assert len(samples["samples.imu"]) > 195 * 12 and len(samples["samples.pose"]) > 180 * 12
    # The stored command line reproduces the run (MuJoCo is deterministic across processes).
    for opt in ("--physics mujoco", "--gust-force 5:15", "--gust-cluster 0.5"):
        assert opt in created_by
    again = tmp_path / "again"
    again.mkdir()
    argv = shlex.split(created_by)[2:]  # drop "groundstation sitl"
    redo = _run(argv, cwd=again)
    assert redo.returncode == 0, redo.stderr
    assert _samples(again / "mj.mcap") == samples


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--gust-force", "40:5"], "--gust-force"),
        (["--gust-duration", "0:0.2"], "--gust-duration"),
        (["--gust-cluster", "2"], "--gust-cluster"),
        (["--gust-cluster-size", "0:3"], "--gust-cluster-size"),
        (["--friction", "-1"], "--friction"),
        (["--physics", "bullet"], "--physics"),
    ],
)
def test_bad_physics_and_gust_options_exit_2(tmp_path, args, message):
    done = _run(["--duration", "1", "--speed", "max", "--record", str(tmp_path / "x.mcap"), *args])
    assert done.returncode == 2
    assert message in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "x.mcap").exists()
