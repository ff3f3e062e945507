"""Helpers for the SITL unit tests: fly a vehicle and collect its 200 Hz IMU view."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from firmware_bridge.sitl.gusts import GustParams
from firmware_bridge.sitl.physics import GRAVITY
from firmware_bridge.sitl.vehicle import Vehicle, vehicle_settings


@dataclass
class Flight:
    vehicle: Vehicle
    t: np.ndarray  # (n,) s
    accel: np.ndarray  # (n, 3) body FRD, m/s^2
    accel_world: np.ndarray  # (n, 3) ENU, gravity removed, m/s^2
    position: np.ndarray  # (n, 3) ENU, m
    outside_region: int


def fly(
    scene, pilot, seconds, seed=0, gust_rate=0.0, until_done=False, physics="simple", gusts=None
) -> Flight:
    """Run ``pilot`` (a scripted pilot or None for manual) on the ``physics`` engine and sample
    the IMU at 200 Hz. ``gusts`` (GustParams) replaces ``gust_rate`` when given."""
    gusts = gusts or GustParams(rate_per_min=gust_rate)
    v = Vehicle(scene, pilot, seed, vehicle_settings(physics, gusts=gusts))
    per = v.settings.physics_rate // 200
    ts, acc, accw, pos = [], [], [], []
    outside = 0
    while v.t < seconds and not (until_done and v.pilot_done):
        for _ in range(per):
            v.step()
        a, _ = v.imu_sample()
        R = np.array(v.body.rotation()).reshape(3, 3)
        a_flu = np.array([a[0], -a[1], -a[2]])
        ts.append(v.t)
        acc.append(a)
        accw.append(R @ a_flu - np.array([0.0, 0.0, GRAVITY]))
        pos.append(v.body.position)
        outside += not scene.inside_region(v.body.position)
    return Flight(v, np.array(ts), np.array(acc), np.array(accw), np.array(pos), outside)


def moving_average(x: np.ndarray, window: int = 10) -> np.ndarray:
    """Trailing moving average along axis 0 (50 ms at 200 Hz by default)."""
    c = np.cumsum(np.concatenate([np.zeros((1,) + x.shape[1:]), x]), axis=0)
    out = np.empty_like(x, dtype=float)
    for i in range(len(x)):
        lo = max(0, i + 1 - window)
        out[i] = (c[i + 1] - c[lo]) / (i + 1 - lo)
    return out
