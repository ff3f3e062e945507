"""Vehicle-side failsafe: no MANUAL_CONTROL for 0.5 s -> HOLD, later LAND, then LANDED."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_bridge.sitl.gusts import GustParams
from firmware_bridge.sitl.scene import load_scene
from firmware_bridge.sitl.vehicle import HOLD, LAND, LANDED, MANUAL, Vehicle, VehicleSettings


def _vehicle():
    s = VehicleSettings(gusts=GustParams(rate_per_min=0.0))
    return Vehicle(load_scene("paper"), None, seed=3, settings=s)


def _run(v, seconds, sticks=None, every=0.05):
    """Step for ``seconds``; send MANUAL_CONTROL ``sticks`` every ``every`` s when given."""
    end = v.t + seconds
    next_input = v.t
    while v.t < end:
        if sticks is not None and v.t >= next_input:
            v.manual_control(*sticks)
            next_input += every
        v.step()


def test_waits_for_a_pilot_holding_position():
    v = _vehicle()
    _run(v, 6.0)
    assert v.mode == HOLD
    assert np.linalg.norm(np.subtract(v.body.position, v.scene.start)) < 0.05


def test_stale_input_holds_then_lands():
    v = _vehicle()
    _run(v, 1.5, sticks=(300, 0, 500, 0))  # forward at 0.6 m/s
    assert v.mode == MANUAL
    assert v.body.vx > 0.5  # yaw 0 = nose east: forward is +x
    t_last = v.manual.last_input
    _run(v, 0.45)
    assert v.mode == MANUAL  # not yet stale
    _run(v, 0.1)
    assert v.mode == HOLD
    t_hold = v.manual.transitions[-1][0]
    assert t_hold - t_last == pytest.approx(0.5, abs=0.01)
    _run(v, 2.0)  # brakes and holds
    assert abs(v.body.vx) < 0.1
    held = v.body.position
    _run(v, 0.8)
    assert np.linalg.norm(np.subtract(v.body.position, held)) < 0.05
    _run(v, 0.3)
    assert v.mode == LAND
    assert v.body.vz < -0.2
    _run(v, 6.0)
    assert v.mode == LANDED and not v.armed
    assert v.body.z < v.scene.region_min[2] + 0.1
    assert v.body.thrust < 0.5
    kinds = [e.kind for e in v.tracker.events]
    assert kinds == ["ground"]


def test_input_resumes_manual_and_landed_needs_climb_to_rearm():
    v = _vehicle()
    _run(v, 1.0, sticks=(0, 0, 500, 0))
    _run(v, 1.0)
    assert v.mode == HOLD
    _run(v, 0.2, sticks=(0, 300, 500, 0))
    assert v.mode == MANUAL
    _run(v, 12.0)
    assert v.mode == LANDED
    _run(v, 1.0, sticks=(0, 0, 500, 0))  # centred throttle: stays down
    assert v.mode == LANDED
    _run(v, 2.0, sticks=(0, 0, 900, 0))  # climb
    assert v.mode == MANUAL and v.body.z > 0.5


def test_manual_yaw_and_climb():
    v = _vehicle()
    z0 = v.body.z
    _run(v, 2.0, sticks=(0, 0, 1000, 500))  # full climb, yaw left at 45 deg/s
    assert v.body.z - z0 > 1.0 * 2.0 * 0.5
    assert v.manual.yaw == pytest.approx(np.radians(90.0), abs=0.02)
