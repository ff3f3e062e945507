"""Controlled trials of a physics engine: one touch, one gust, and what they look like.

:func:`touch_trial` flies the vehicle into the ``wall`` scene's -x face at a chosen normal speed
and angle; :func:`gust_trial` hits a hovering vehicle with one gust of a chosen force and
duration. Both report the truth (restitution, contact duration, ...) and the peak acceleration
as the detector sees it: the 50 ms moving average of the gravity-free acceleration, both true
(at the physics rate) and from the simulated IMU at 200 Hz (vibration and noise included,
rotated with the true attitude). Pure and deterministic from the seed.

``python -m firmware_bridge.sitl.measure [ENGINE ...]`` prints the table of both engines.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass

import numpy as np

from firmware_bridge.sitl.gusts import GustParams
from firmware_bridge.sitl.maneuvers import ManeuverLog
from firmware_bridge.sitl.physics import GRAVITY
from firmware_bridge.sitl.pilots import Planner, ScriptPilot
from firmware_bridge.sitl.scene import load_scene
from firmware_bridge.sitl.truth import ContactEvent
from firmware_bridge.sitl.vehicle import Vehicle, planning_cylinder, vehicle_settings


@dataclass
class Trial:
    """A flown trial: the vehicle, its 200 Hz IMU view and the true 50 ms-filtered peak."""

    vehicle: Vehicle
    t: np.ndarray  # (n,) s
    accel_world: np.ndarray  # (n, 3) m/s^2, from the IMU, gravity removed
    truth_peak: float  # m/s^2, 50 ms average of the true acceleration, in the window
    truth_raw_peak: float  # m/s^2, the true acceleration's peak (physics rate), in the window
    window: tuple[float, float]  # s

    def imu_peak(self, t0: float, t1: float) -> float:
        """Peak of the 50 ms (10-sample) moving average of |a| (IMU view) in [t0, t1], m/s^2."""
        a = self.accel_world
        c = np.cumsum(np.vstack([np.zeros((1, 3)), a]), axis=0)
        ma = np.full_like(a, np.nan)
        ma[9:] = (c[10:] - c[:-10]) / 10.0
        sel = (self.t >= t0) & (self.t <= t1)
        return float(np.nanmax(np.linalg.norm(ma[sel], axis=1)))


def _fly(v: Vehicle, stop, window) -> Trial:
    """Step ``v`` until ``stop(v)``; log IMU samples and the true filtered peak in ``window()``."""
    per = v.settings.physics_rate // 200
    log = ManeuverLog()
    ts, acc = [], []
    opened = False
    while not stop(v):
        for _ in range(per):
            v.step()
            w = window(v)
            if w is not None and not opened:
                log.open("trial", v.t, 0.0, 0.0)
                opened = True
            if log.active is not None:
                b = v.body
                log.update(v.dt, b.fx, b.fy, b.fz - GRAVITY)
                if w is not None and v.t > w[1]:
                    log.close(v.t)
        a, _ = v.imu_sample()
        R = np.array(v.body.rotation()).reshape(3, 3)
        ts.append(v.t)
        acc.append(R @ np.array([a[0], -a[1], -a[2]]) - np.array([0.0, 0.0, GRAVITY]))
    m = log.records[0] if log.records else None
    win = (m.start, m.end) if m else (math.nan, math.nan)
    peak = m.peak_accel_filtered if m else math.nan
    raw = m.peak_accel if m else math.nan
    return Trial(v, np.array(ts), np.array(acc), peak, raw, win)


def touch_trial(
    physics: str,
    normal_speed: float,
    angle_deg: float = 0.0,
    azimuth: float = 0.0,
    seed: int = 0,
    **settings: object,
) -> tuple[Trial, ContactEvent]:
    """Touch the ``wall`` scene's -x face at (4.0, 2.0, 1.0) (normal speed m/s, ``angle_deg``
    off the normal; ``azimuth`` 0 sideways, pi/2 upwards); no gusts. Returns the trial and the
    contact event; the trial's window is the contact plus 0.1 s."""
    scene = load_scene("wall")  # box x 4.0..4.2, y 1..3, z 0..1.5
    vs = vehicle_settings(physics, gusts=GustParams(rate_per_min=0.0), **settings)
    r, h = planning_cylinder(vs)
    planner = Planner(scene, r, h)
    tgt = planner.touch_target(0, "xmin", (4.0, 2.0, 1.0), (-1.0, 0.0, 0.0))
    aimed = None if tgt is None else planner.angled(tgt, math.radians(angle_deg), azimuth, (0.8,))
    if aimed is None:
        raise ValueError(f"no clear 0.8 m run-up at {angle_deg} deg in the wall scene")
    speed = normal_speed / math.cos(math.radians(angle_deg))
    acts = [("goto", aimed.standoff, 1.0), ("hover", 0.5), ("touch", aimed, speed),
            ("goto", aimed.standoff, 1.0), ("hover", 0.3)]  # fmt: skip
    pilot = ScriptPilot(scene, acts)
    v = Vehicle(scene, pilot, seed, vs)

    def window(v: Vehicle):
        ev = [e for e in v.tracker.events if e.object_index == 0]
        return None if not ev else (ev[0].start, ev[0].start + 0.15)

    trial = _fly(v, lambda v: pilot.done or v.t > 30.0, window)
    events = [e for e in v.tracker.events if e.object_index == 0]
    if len(events) != 1:
        raise RuntimeError(f"expected one touch of the wall, got {len(events)}")
    return trial, events[0]


def gust_trial(
    physics: str, force_n: float, duration_s: float, seed: int = 0
) -> tuple[Trial, object]:
    """One gust of ``force_n`` N (peak) lasting ``duration_s`` on a vehicle hovering in the
    open (``paper`` scene's start); the trial's window is the gust plus 0.1 s."""
    scene = load_scene("paper")
    vs = vehicle_settings(physics)
    mass = 1.0
    gusts = GustParams.from_forces(
        mass, force=(force_n, force_n), duration=(duration_s, duration_s), rate_per_min=30.0
    )
    vs = vehicle_settings(physics, gusts=gusts)
    v = Vehicle(scene, ScriptPilot(scene, []), seed, vs)

    def window(v: Vehicle):
        h = v.gusts.history
        return None if not h else (h[0].start, h[0].end + 0.1)

    trial = _fly(v, lambda v: bool(v.gusts.history) and v.t > v.gusts.history[0].end + 0.3, window)
    return trial, v.gusts.history[0]


def main(argv: list[str] | None = None) -> int:
    """Print the touch and gust tables for the engines named in ``argv`` (default both)."""
    engines = (argv if argv else sys.argv[1:]) or ["simple", "mujoco"]
    g = GRAVITY
    print("| engine | normal speed (m/s) | restitution | contact (ms) | peak (G) "
          "| 50 ms true (G) | 50 ms IMU (G) | body part |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    for engine in engines:
        for speed in (0.3, 0.6, 1.0):
            tr, ev = touch_trial(engine, speed)
            imu = tr.imu_peak(ev.start - 0.02, ev.start + 0.15)
            print(f"| {engine} | {ev.normal_speed:.2f} | {ev.restitution:.2f} "
                  f"| {1000 * (ev.end - ev.start):.0f} | {ev.peak_accel / g:.1f} "
                  f"| {tr.truth_peak / g:.2f} | {imu / g:.2f} | {ev.body_part} |")  # fmt: skip
    print()
    print(
        "| engine | gust force (N) | duration (s) | 50 ms true (G) | 50 ms IMU (G) | pushed into |"
    )
    print("|---|---|---|---|---|---|")
    for engine in engines:
        for force in (5.0, 15.0, 40.0):
            for dur in (0.05, 0.15, 0.3):
                tr, gust = gust_trial(engine, force, dur)
                imu = tr.imu_peak(gust.start, gust.end + 0.1)
                hit = {e.kind for e in tr.vehicle.tracker.events if e.start <= gust.end + 0.1}
                print(f"| {engine} | {force:g} | {dur:g} | {tr.truth_peak / g:.2f} "
                      f"| {imu / g:.2f} | {', '.join(sorted(hit)) or '-'} |")  # fmt: skip
    return 0


if __name__ == "__main__":
    t0 = time.monotonic()
    rc = main()
    print(f"\n({time.monotonic() - t0:.1f} s)", file=sys.stderr)
    raise SystemExit(rc)
