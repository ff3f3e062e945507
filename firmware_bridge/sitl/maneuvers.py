"""Aggressive free flight: fast legs, hard braking and turns, and the truth of each manoeuvre.

Real pilots fly a path fast and stop hard at its end; contact-free flights reach 1.2-1.9 G of
50 ms-filtered acceleration there, which a contact detector must not take for a touch. A
:class:`Dash` is one such leg: accelerate along a horizontal line to ``speed`` (3-5 m/s) at
``a_acc``, optionally turn at a corner without slowing (the velocity setpoint switches to the new
direction, the turn's acceleration is ``a_turn``), then brake to a stop at ``a_brake``. The
braking starts when the remaining distance equals the attitude flip (``FLIP_S`` at speed) plus the
stopping distance v^2 / (2 a_brake), and a turn ``s = v^2 |d2 - d1| / (2 a_turn)`` before the
corner, so the parabolic turn stays inside the two clear segments.

:class:`ManeuverLog` records each accelerate / turn / brake interval and its peak acceleration,
raw and as the detector would see it after a 50 ms moving average (pure: the vehicle feeds it the
true acceleration after each physics step while an interval is open).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from firmware_bridge.sitl.control import ControlGains, Setpoint
from firmware_bridge.sitl.physics import GRAVITY
from firmware_bridge.sitl.planner import Planner

Vec = tuple[float, float, float]
FLIP_S = 0.25  # s, attitude change from cruise to full braking tilt (rate-limited)
FILTER_S = 0.05  # s, the detector's moving-average window
BRAKE_LEAD = 1.0 / ControlGains().kv  # s: velocity error per unit of commanded deceleration


@dataclass
class Maneuver:
    """One manoeuvre interval: kind (accelerate | turn | brake), start/end (s), speed (m/s) at
    its start, target acceleration (m/s^2) and the peak true acceleration (gravity removed,
    world frame) raw and 50 ms-averaged, m/s^2."""

    kind: str
    start: float
    end: float
    speed: float
    target_accel: float
    peak_accel: float = 0.0
    peak_accel_filtered: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["peak_accel_g"] = self.peak_accel / GRAVITY
        d["peak_accel_filtered_g"] = self.peak_accel_filtered / GRAVITY
        return d


class ManeuverLog:
    """Open/close manoeuvre intervals and track their peak accelerations (pure)."""

    def __init__(self) -> None:
        self.records: list[Maneuver] = []
        self.active: Maneuver | None = None
        self._window: deque[tuple[float, float, float]] = deque()
        self._sum = [0.0, 0.0, 0.0]

    def open(self, kind: str, t: float, speed: float, target: float) -> None:
        """Start a ``kind`` interval at ``t`` (s), closing any open one."""
        self.close(t)
        self.active = Maneuver(kind, t, t, speed, target)
        self.records.append(self.active)
        self._window.clear()
        self._sum = [0.0, 0.0, 0.0]

    def close(self, t: float) -> None:
        if self.active is not None:
            self.active.end = t
            self.active = None

    def update(self, dt: float, ax: float, ay: float, az: float) -> None:
        """One physics step (``dt`` s) of true acceleration (m/s^2, world, gravity removed)."""
        m = self.active
        if m is None:
            return
        m.end += dt
        m.peak_accel = max(m.peak_accel, math.sqrt(ax * ax + ay * ay + az * az))
        w, s = self._window, self._sum
        w.append((ax, ay, az))
        s[0] += ax
        s[1] += ay
        s[2] += az
        n = max(1, round(FILTER_S / dt))
        if len(w) > n:
            ox, oy, oz = w.popleft()
            s[0] -= ox
            s[1] -= oy
            s[2] -= oz
        if len(w) == n:
            f = math.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2]) / n
            m.peak_accel_filtered = max(m.peak_accel_filtered, f)


@dataclass(frozen=True)
class Dash:
    """A fast horizontal leg through ``points`` (start, optional corner, end; m, ENU) at
    ``speed`` m/s with accelerations ``a_acc``, ``a_turn``, ``a_brake`` (m/s^2)."""

    points: tuple[Vec, ...]
    speed: float
    a_acc: float
    a_turn: float
    a_brake: float


def _unit(a: Vec, b: Vec) -> Vec:
    d = (b[0] - a[0], b[1] - a[1], b[2] - a[2])
    n = math.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
    return (d[0] / n, d[1] / n, d[2] / n)


def _dot(a: Vec, b: Vec) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _tilt(a: float) -> float:
    """Tilt limit (rad) that lets the controller reach ``a`` m/s^2 horizontally, plus margin."""
    return min(math.radians(70.0), math.atan(a / GRAVITY) + math.radians(8.0))


def turn_distance(speed: float, d1: Vec, d2: Vec, a_turn: float) -> float:
    """Distance (m) before the corner at which a turn from ``d1`` to ``d2`` starts."""
    chord = math.sqrt(sum((d2[i] - d1[i]) ** 2 for i in range(3)))
    return speed * speed * chord / (2.0 * a_turn)


class DashRun:
    """Flies one :class:`Dash`; :meth:`setpoint` returns None when the vehicle has stopped."""

    def __init__(self, dash: Dash, log: ManeuverLog, yaw: float):
        self.d, self.log, self.yaw = dash, log, yaw
        self.k = 0
        self.state = "start"
        self.hold: Vec = dash.points[0]
        self.t_stop = 0.0

    def setpoint(self, t: float, pos: Vec, vel: Vec) -> Setpoint | None:
        dash, log = self.d, self.log
        pts = dash.points
        a, b = pts[self.k], pts[self.k + 1]
        d = _unit(a, b)
        z = (None, None, a[2])
        if self.state == "start":
            self.state = "go"
            log.open("accelerate", t, math.hypot(vel[0], vel[1]), dash.a_acc)
        along = _dot(vel, d)
        speed = math.sqrt(_dot(vel, vel))
        if self.state == "go":
            m = log.active
            if m is not None and m.kind == "accelerate" and along >= 0.95 * dash.speed:
                log.close(t)
            rem = _dot((b[0] - pos[0], b[1] - pos[1], b[2] - pos[2]), d)
            if self.k + 2 < len(pts):
                d2 = _unit(b, pts[self.k + 2])
                if rem <= turn_distance(max(along, 0.0), d, d2, dash.a_turn):
                    self.state, self.k = "turn", self.k + 1
                    log.open("turn", t, speed, dash.a_turn)
                    return self.setpoint(t, pos, vel)
            elif rem <= max(along, 0.0) * FLIP_S + along * along / (2.0 * dash.a_brake):
                self.state = "brake"
                log.open("brake", t, speed, dash.a_brake)
                return self.setpoint(t, pos, vel)
            e = (a[0] - pos[0], a[1] - pos[1], 0.0)
            en = _dot(e, d)
            k = 1.5
            v = tuple(d[i] * dash.speed + k * (e[i] - en * d[i]) for i in range(3))
            return Setpoint(
                position=z,  # type: ignore[arg-type]
                velocity=v,  # type: ignore[arg-type]
                yaw=self.yaw,
                max_speed=dash.speed + 0.5,
                a_max=dash.a_acc,
                max_tilt=_tilt(dash.a_acc),
            )
        if self.state == "turn":
            if along >= math.cos(math.radians(10.0)) * speed:
                self.state = "go"
                log.close(t)
            return Setpoint(
                position=z,  # type: ignore[arg-type]
                velocity=(d[0] * dash.speed, d[1] * dash.speed, 0.0),
                yaw=self.yaw,
                max_speed=dash.speed + 0.5,
                a_max=dash.a_turn,
                max_tilt=_tilt(dash.a_turn),
            )
        if self.state == "brake":
            h = math.hypot(vel[0], vel[1])
            m = self.log.active
            late = m is not None and t - m.start > m.speed / dash.a_brake + 1.0
            if h < 0.25 or late:
                self.state, self.t_stop, self.hold = "settle", t, pos
            # Full stick back: a velocity setpoint a_brake / kv behind the current velocity keeps
            # the (P on velocity) controller saturated at a_brake until the vehicle has stopped.
            back = BRAKE_LEAD / h if h > 1e-6 else 0.0
            return Setpoint(
                position=z,  # type: ignore[arg-type]
                velocity=(
                    vel[0] * (1.0 - back * dash.a_brake),
                    vel[1] * (1.0 - back * dash.a_brake),
                    0.0,
                ),
                yaw=self.yaw,
                max_speed=dash.speed + 0.5,
                a_max=dash.a_brake,
                max_tilt=_tilt(dash.a_brake),
            )
        if t - self.t_stop >= 0.15:  # settle: the rebound of the attitude ends the manoeuvre
            log.close(t)
            return None
        return Setpoint(position=self.hold, yaw=self.yaw)


# -- planning ------------------------------------------------------------------------------------


def _extent(planner: Planner, p: Vec, d: Vec, clearance: float, limit: float = 12.0) -> float:
    """How far (m) a line from ``p`` along ``d`` stays inside the region (shrunk) and clear."""
    step, s = 0.1, 0.0
    while s + step <= limit:
        q = (p[0] + d[0] * (s + step), p[1] + d[1] * (s + step), p[2])
        if not planner.in_region(q) or not planner.free(q, margin=clearance):
            break
        s += step
    return s


def _fit_speed(want: float, fits, floor: float = 2.0) -> float:
    """Largest speed <= ``want`` (0.1 m/s steps, >= ``floor``) for which ``fits(v)``, else 0."""
    v = want
    while v >= floor - 1e-9:
        if fits(v):
            return v
        v -= 0.1
    return 0.0


def _stop_room(v: float, a_brake: float) -> float:
    """Distance (m) to flip and brake from ``v`` m/s, with 0.3 m to spare."""
    return v * FLIP_S + v * v / (2 * a_brake) + 0.3


def plan_dashes(
    planner: Planner,
    rng: np.random.Generator,
    legs: int = 8,
    speed: tuple[float, float] = (3.0, 5.0),
    clearance: float = 0.3,
) -> list[Dash]:
    """``legs`` fast legs (about half with a corner) in clear space, drawn from ``rng``.

    Each leg's line keeps ``clearance`` m (plus the drone's radius) from every structure and
    stays inside the planner's region; its speed is drawn from ``speed`` and lowered until the
    leg is long enough to accelerate, flip and brake within it.
    """
    lo, hi = planner.lo, planner.hi
    edge = 0.4
    out: list[Dash] = []
    tries = 0
    while len(out) < legs and tries < 400:
        tries += 1
        floor = speed[0] if tries <= 300 else 2.0  # slower legs only where no fast one fits
        # High enough that the thrust lost while flipping into a 2 G brake never reaches the
        # floor (the drop is 0.1-0.3 m), low enough to leave headroom.
        z_lo = min(lo[2] + 0.7, hi[2])
        z = float(rng.uniform(z_lo, max(z_lo, min(hi[2] - 0.3, lo[2] + 1.3))))
        p = (
            float(rng.uniform(lo[0] + edge, hi[0] - edge)),
            float(rng.uniform(lo[1] + edge, hi[1] - edge)),
            z,
        )
        az = float(rng.uniform(0, 2 * math.pi))
        d1 = (math.cos(az), math.sin(az), 0.0)
        want = float(rng.uniform(*speed))
        a_acc = float(rng.uniform(0.5, 1.0)) * GRAVITY
        a_turn = float(rng.uniform(0.8, 1.8)) * GRAVITY
        a_brake = float(rng.uniform(0.8, 2.0)) * GRAVITY
        corner = bool(rng.random() < 0.5)
        turn_by = float(rng.uniform(math.radians(60), math.radians(120))) * (
            1.0 if rng.random() < 0.5 else -1.0
        )
        if not planner.free(p, margin=clearance):
            continue
        l1 = _extent(planner, p, d1, clearance) - edge
        if l1 < 2.0:
            continue
        if corner:
            d2 = (math.cos(az + turn_by), math.sin(az + turn_by), 0.0)
            for frac in (1.0, 0.8, 0.6):
                b = (p[0] + d1[0] * l1 * frac, p[1] + d1[1] * l1 * frac, z)
                l2 = _extent(planner, b, d2, clearance) - edge

                def fits(v: float, room1: float = l1 * frac, room2: float = l2) -> bool:
                    s = turn_distance(v, d1, d2, a_turn)  # noqa: B023 - evaluated at once
                    acc = v * v / (2 * a_acc) + 0.3  # noqa: B023
                    return room1 >= acc + s and room2 >= s + _stop_room(v, a_brake)  # noqa: B023

                v = _fit_speed(want, fits, floor)
                if v > 0.0:
                    e = (b[0] + d2[0] * l2, b[1] + d2[1] * l2, z)
                    out.append(Dash((p, b, e), round(v, 1), a_acc, a_turn, a_brake))
                    break
            continue
        v = _fit_speed(
            want,
            lambda v: l1 >= v * v / (2 * a_acc) + _stop_room(v, a_brake),  # noqa: B023
            floor,
        )
        if v > 0.0:
            e = (p[0] + d1[0] * l1, p[1] + d1[1] * l1, z)
            out.append(Dash((p, e), round(v, 1), a_acc, a_turn, a_brake))
    return out
