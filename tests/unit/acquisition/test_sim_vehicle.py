"""A SITL recording names the body it flew: the station's ``[vehicle]`` measured off the
simulated airframe (``acquisition.sim_recording.station_vehicle``)."""

from __future__ import annotations

import math
import tomllib

import numpy as np
import pytest

from firmware_bridge.sitl.airframe import Airframe, cylinder_airframe
from groundstation.acquisition.sim_recording import station_vehicle, vehicle_config
from groundstation.bench.detector import VEHICLE
from groundstation.config import load_config

AIRFRAMES = {
    "x": Airframe(),
    "+": Airframe(layout="+"),
    "big": Airframe(arm_length=0.25, guard_radius=0.18, body_half=(0.08, 0.05, 0.03)),
    "cylinder": cylinder_airframe(0.2, 0.1, 1.0),
}


@pytest.mark.parametrize("name", sorted(AIRFRAMES))
def test_the_station_vehicle_has_the_airframes_extents(name):
    frame = AIRFRAMES[name]
    v = station_vehicle(frame)
    assert v.shape == ("cylinder" if frame.layout == "cylinder" else "guards")
    if v.shape == "guards":
        assert v.layout == frame.layout
        # the lowest point (the feet) and the farthest feet
        assert math.isclose(v.body_half_m[2] + v.leg_length_m, frame.bottom, abs_tol=1e-4)
        feet = max(math.hypot(f[0], f[1]) for _, f in frame.legs()) + frame.leg_radius
        legs = v.leg_points()
        assert np.hypot(legs[:, 0], legs[:, 1]).max() == pytest.approx(feet, abs=1e-4)
        # the rings' outer face: the body's horizontal extent, whatever the layout
        rim = max(np.hypot(*(v.rotor_centres()[:, :2].T))) + v.guard_radius_m
        assert rim == pytest.approx(frame.reach_max, abs=1e-3)
    else:
        assert (v.radius_m, v.height_m) == (0.2, 0.1)


@pytest.mark.parametrize("name", sorted(AIRFRAMES))
def test_the_recorded_table_loads_back_as_the_same_vehicle(name):
    text = vehicle_config(AIRFRAMES[name])
    assert text.startswith("[vehicle]\n")
    assert load_config(base=tomllib.loads(text)).vehicle == station_vehicle(AIRFRAMES[name])


def test_the_benchs_user_given_airframe_is_the_simulated_one_within_a_centimetre():
    """``bench detector`` / ``bench sessions`` replay MuJoCo flights with a user's description
    of the airframe (``bench.detector.VEHICLE``), not the simulator's exact numbers; it must
    still describe the same body."""
    given = load_config(None, list(VEHICLE["mujoco"])).vehicle
    exact = station_vehicle(Airframe())
    assert (given.shape, given.layout) == (exact.shape, exact.layout)
    for key in ("arm_length_m", "guard_radius_m", "guard_z_m", "leg_length_m", "leg_offset_m"):
        assert abs(getattr(given, key) - getattr(exact, key)) <= 0.01, key
    assert np.allclose(given.body_half_m, exact.body_half_m, atol=0.01)
    assert load_config(None, list(VEHICLE["simple"])).vehicle == station_vehicle(
        cylinder_airframe(0.2, 0.1, 1.0)
    )
