"""The stop rule of scripted SITL recordings: 2 s after the script, or at the script limit."""

from __future__ import annotations

import argparse
import types

from groundstation.cli import sitl


def _sim(t: float, done: bool):
    return types.SimpleNamespace(vehicle=types.SimpleNamespace(t=t, pilot_done=done))


def test_a_finished_script_ends_two_seconds_later():
    args = argparse.Namespace(duration=None, pilot="script:survey")
    sim = _sim(50.0, True)
    stop = sitl._stop_after_script(args, sim)
    assert not stop()  # the end is noted at t = 50 s
    sim.vehicle.t = 51.9
    assert not stop()
    sim.vehicle.t = 52.1
    assert stop()


def test_a_script_that_never_finishes_stops_at_the_limit(capsys):
    args = argparse.Namespace(duration=None, pilot="script:free")
    sim = _sim(sitl.SCRIPT_LIMIT_S - 1.0, False)
    stop = sitl._stop_after_script(args, sim)
    assert not stop()
    sim.vehicle.t = sitl.SCRIPT_LIMIT_S + 0.01
    assert stop()
    assert "did not finish" in capsys.readouterr().err


def test_a_duration_or_a_manual_pilot_is_not_cut():
    for args in (
        argparse.Namespace(duration=2000.0, pilot="script:free"),
        argparse.Namespace(duration=None, pilot="manual"),
    ):
        assert not sitl._stop_after_script(args, _sim(sitl.SCRIPT_LIMIT_S + 100, False))()
