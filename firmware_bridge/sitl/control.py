"""Cascaded position -> velocity -> attitude -> rate controller (pure, plain floats).

Position error -> velocity setpoint (P, speed-limited) -> acceleration setpoint (P on velocity,
limited) -> thrust vector (tilt-limited) -> desired attitude from thrust direction and yaw ->
body-rate setpoint from the geometric attitude error e_R = 1/2 vee(R_d^T R - R^T R_d)
(Lee, Leok and McClamroch 2010, eq. 10).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from firmware_bridge.sitl.physics import GRAVITY


@dataclass(frozen=True)
class Setpoint:
    """What a pilot (scripted or MANUAL_CONTROL) asks of the vehicle.

    ``position`` axes that are None are velocity-controlled from ``velocity`` instead (m, m/s,
    ENU). ``yaw`` in rad (ENU, from +x counter-clockwise). ``armed`` False cuts the motors.
    ``a_max`` (m/s^2, horizontal) and ``max_tilt`` (rad), when set, replace the controller's
    limits for this setpoint: an aggressive pilot accelerates and brakes harder than the default
    cascade allows (real pilots brake at 1-2 G at the end of a fast leg).
    """

    position: tuple[float | None, float | None, float | None] = (None, None, None)
    velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    yaw: float = 0.0
    max_speed: float = 1.5  # m/s, horizontal
    armed: bool = True
    a_max: float | None = None  # m/s^2, horizontal; None = ControlGains.a_max
    max_tilt: float | None = None  # rad; None = ControlGains.max_tilt


@dataclass(frozen=True)
class ControlGains:
    kp_pos: float = 1.8  # 1/s
    kv: float = 5.0  # 1/s
    a_max: float = 5.0  # m/s^2 horizontal
    az_max: float = 3.0  # m/s^2 vertical
    vz_max: float = 1.2  # m/s
    max_tilt: float = math.radians(35.0)
    k_att: float = 9.0  # (rad/s)/rad
    max_rate: float = 6.0  # rad/s


class Controller:
    """Maps a :class:`Setpoint` and the body state to (thrust N, body rate setpoint rad/s)."""

    def __init__(self, gains: ControlGains | None = None):
        self.g = gains or ControlGains()

    def update(self, body, sp: Setpoint) -> tuple[float, tuple[float, float, float]]:
        """One control step for ``body`` (any :class:`~firmware_bridge.sitl.engine.Physics`);
        see the module docstring for the cascade."""
        g = self.g
        if not sp.armed:
            return 0.0, (0.0, 0.0, 0.0)
        pos = (body.x, body.y, body.z)
        vel = (body.vx, body.vy, body.vz)
        v_sp = [
            sp.velocity[i] if sp.position[i] is None else g.kp_pos * (sp.position[i] - pos[i])
            for i in range(3)
        ]
        h = math.hypot(v_sp[0], v_sp[1])
        if h > sp.max_speed:
            v_sp[0] *= sp.max_speed / h
            v_sp[1] *= sp.max_speed / h
        v_sp[2] = max(-g.vz_max, min(g.vz_max, v_sp[2]))
        ax, ay = g.kv * (v_sp[0] - vel[0]), g.kv * (v_sp[1] - vel[1])
        az = max(-g.az_max, min(g.az_max, g.kv * (v_sp[2] - vel[2])))
        a_max = g.a_max if sp.a_max is None else sp.a_max
        h = math.hypot(ax, ay)
        if h > a_max:
            ax, ay = ax * a_max / h, ay * a_max / h
        m, drag = body.mass, body.drag
        # Thrust vector (world), compensating linear drag; tilt-limited.
        fx = m * ax + drag * vel[0]
        fy = m * ay + drag * vel[1]
        fz = max(0.2 * m * GRAVITY, m * (az + GRAVITY) + drag * vel[2])
        h = math.hypot(fx, fy)
        lim = fz * math.tan(g.max_tilt if sp.max_tilt is None else sp.max_tilt)
        if h > lim:
            fx, fy = fx * lim / h, fy * lim / h
        norm = math.sqrt(fx * fx + fy * fy + fz * fz)
        b3 = (fx / norm, fy / norm, fz / norm)
        R = body.rotation()
        thrust = max(0.0, fx * R[2] + fy * R[5] + fz * R[8])  # projection on actual body z
        # Desired attitude: b3 and heading yaw.
        c1 = (math.cos(sp.yaw), math.sin(sp.yaw), 0.0)
        b2 = _cross(b3, c1)
        n2 = math.sqrt(b2[0] ** 2 + b2[1] ** 2 + b2[2] ** 2)
        b2 = (b2[0] / n2, b2[1] / n2, b2[2] / n2)
        b1 = _cross(b2, b3)
        # e_R = 1/2 vee(Rd^T R - R^T Rd); with M = Rd^T R, M_ij = b_i . r_j (r_j: columns of R)
        r0, r1, r2 = (R[0], R[3], R[6]), (R[1], R[4], R[7]), (R[2], R[5], R[8])
        e = (
            0.5 * (_dot(b3, r1) - _dot(b2, r2)),
            0.5 * (_dot(b1, r2) - _dot(b3, r0)),
            0.5 * (_dot(b2, r0) - _dot(b1, r1)),
        )
        rates = tuple(max(-g.max_rate, min(g.max_rate, -g.k_att * ei)) for ei in e)
        return thrust, rates  # type: ignore[return-value]


def _dot(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[float, float, float]:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])
