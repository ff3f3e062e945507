"""A recording carries the body it was flown with, and everything that replays it uses it.

``groundstation sitl --physics mujoco --record`` stores the simulated airframe as the station's
``[vehicle]`` table (and the floor's height, ``[contact] floor_z_m``) in the recording's
configuration; ``replay``, ``batch`` (on a real local
Dask cluster) and ``calibrate`` of that file start from it, ``--set`` on top. Before, all of
them replayed a guarded quadrotor's flight as the paper's cylinder.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tomllib

import pytest

from firmware_bridge.sitl.airframe import Airframe
from groundstation.acquisition.reader import open_recording
from groundstation.acquisition.sim_recording import station_vehicle
from groundstation.cli import main as cli_main

ENV = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")


@pytest.fixture(scope="module")
def mujoco_log(tmp_path_factory):
    log = tmp_path_factory.mktemp("airframe") / "hover.mcap"
    argv = ["sitl", "--physics", "mujoco", "--speed", "max", "--duration", "2",
            "--pilot", "script:hover", "--record", str(log)]  # fmt: skip
    assert cli_main(argv) == 0
    return log


def test_a_sitl_recording_stores_its_airframe(mujoco_log, tmp_path):
    with open_recording(mujoco_log) as rec:
        tree = tomllib.loads(rec.metadata()["config"])
    assert set(tree) == {"vehicle", "contact"} and tree["vehicle"]["shape"] == "guards"
    assert tree["contact"] == {"floor_z_m": 0.0}  # the default scene's floor
    simple = tmp_path / "simple.mcap"
    argv = ["sitl", "--speed", "max", "--duration", "1", "--pilot", "script:hover",
            "--record", str(simple)]  # fmt: skip
    assert cli_main(argv) == 0
    with open_recording(simple) as rec:
        assert tomllib.loads(rec.metadata()["config"])["vehicle"]["shape"] == "cylinder"


def test_replay_and_calibrate_start_from_the_recorded_airframe(mujoco_log, tmp_path, capsys):
    import argparse

    from groundstation.cli.replay import _resolve

    args = argparse.Namespace(config=None, set=[], quiet=False)
    assert _resolve(mujoco_log, args).config.vehicle == station_vehicle(Airframe())
    args = argparse.Namespace(config=None, set=["vehicle.arm_length_m=0.2"], quiet=False)
    vehicle = _resolve(mujoco_log, args).config.vehicle
    assert vehicle.shape == "guards" and vehicle.arm_length_m == 0.2  # --set on top
    assert cli_main(["calibrate", "detector", str(mujoco_log)]) == 0
    err = capsys.readouterr().err
    assert "replay: settings: the configuration recorded in the log ([contact, vehicle])" in err
    assert "calibrate: settings: the configuration recorded in the log ([contact, vehicle])" in err


def test_batch_starts_each_log_from_its_recorded_airframe(mujoco_log, tmp_path):
    out = tmp_path / "out"
    argv = [sys.executable, "-m", "groundstation.cli", "batch", str(mujoco_log), "--out", str(out),
            "--map", "final", "--snapshots", "0", "--workers", "1", "--quiet",
            "--variant", "base", "--variant", "cyl:vehicle.shape=cylinder"]  # fmt: skip
    done = subprocess.run(argv, capture_output=True, text=True, env=ENV, timeout=600)
    assert done.returncode == 0, done.stderr
    assert (
        "batch: 1 of 1 logs start from the configuration recorded in them ([contact, vehicle])"
        in done.stderr
    )
    shapes = {}
    for folder in out.iterdir():
        if (folder / "settings.toml").is_file():
            tree = tomllib.loads((folder / "settings.toml").read_text())
            shapes[tree["vehicle"]["shape"]] = tree["vehicle"]["arm_length_m"]
    assert shapes == {"guards": 0.17, "cylinder": 0.17}  # the variant's --set on top


def test_the_sitl_writes_the_stations_vehicle_for_a_live_session(tmp_path, capsys):
    from groundstation.config import load_config

    toml = tmp_path / "airframe.toml"
    argv = ["sitl", "--physics", "mujoco", "--speed", "max", "--duration", "1",
            "--pilot", "script:hover", "--record", str(tmp_path / "x.mcap"),
            "--station-config", str(toml)]  # fmt: skip
    assert cli_main(argv) == 0
    assert load_config(str(toml)).vehicle == station_vehicle(Airframe())
    assert load_config(str(toml)).contact.floor_z_m == 0.0  # and where its floor is
    assert f"groundstation live --config {toml}" in capsys.readouterr().err
    argv[-1] = str(tmp_path / "no" / "such" / "dir.toml")
    argv[argv.index("--record") + 1] = str(tmp_path / "y.mcap")
    assert cli_main(argv) == 2
    assert "--station-config" in capsys.readouterr().err and not (tmp_path / "y.mcap").exists()
