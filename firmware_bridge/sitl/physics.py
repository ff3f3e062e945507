"""Rigid-body quadrotor with contact and gust forces (pure, plain floats for speed).

World frame ENU (z up), body frame FLU, quaternion (w, x, y, z) body -> world. Semi-implicit Euler
at the physics rate (default 800 Hz). The state carries the *specific force* f = (F_total - m g)/m,
i.e. what an ideal accelerometer measures (world frame); the IMU model rotates it into body FRD.

Contact (DESIGN.md section 3): the drone is the vertical cylinder of radius ``radius`` and height
``height`` that the detector circumscribes it with. Boxes and vertical cylinders are products of a
2-D set and a z interval, and so is the drone, so their Minkowski sum is the product of the
horizontal and vertical sums: they overlap iff the horizontal distance from the drone's centre to
the object is < r AND the vertical distance is < h/2. The penetration is the smaller of the two
escapes; a stiff spring-damper F_n = max(0, k * pen + c * d(pen)/dt) pushes along that normal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from firmware_bridge.sitl.airframe import cylinder_airframe
from firmware_bridge.sitl.scene import Scene

GRAVITY = 9.80665  # m/s^2


@dataclass(frozen=True)
class QuadParams:
    """Airframe, contact and control constants (SI units)."""

    mass: float = 1.0  # kg
    radius: float = 0.2  # m, contact cylinder (the detector's r)
    height: float = 0.1  # m, contact cylinder (the detector's h)
    drag: float = 0.15  # N/(m/s), linear
    thrust_tau: float = 0.02  # s, motor lag
    rate_tau: float = 0.03  # s, closed rate-loop lag
    contact_stiffness: float = 6000.0  # N/m  -> contact lasts ~ pi*sqrt(m/k) = 40 ms
    contact_restitution: float = 0.5  # rebound speed / impact speed (propeller guard)
    ground_stiffness: float = 4000.0  # N/m, landing gear
    ground_friction: float = 3.0  # N/(m/s) horizontal, while resting on the floor

    @property
    def contact_damping(self) -> float:
        """Damping c (N s/m) giving the restitution e: zeta = -ln e / sqrt(pi^2 + ln^2 e)."""
        ln_e = math.log(self.contact_restitution)
        zeta = -ln_e / math.sqrt(math.pi**2 + ln_e**2)
        return 2.0 * zeta * math.sqrt(self.contact_stiffness * self.mass)


@dataclass
class Contact:
    """Overlap of the drone's body with one structure at one physics step.

    ``part`` names the body part that touches (``cylinder`` in this engine; ``guard``, ``arm``,
    ``body`` or ``leg`` with MuJoCo), ``geom`` the exact piece (e.g. ``guard2_7``).
    """

    object_index: int  # -1 for the floor
    depth: float  # m, > 0
    normal: tuple[float, float, float]  # outward from the structure, unit
    point: tuple[float, float, float]  # closest surface point of the structure, m
    part: str = "cylinder"
    geom: str = "cylinder"


def contact_penetration(
    scene: Scene, p: tuple[float, float, float], radius: float, height: float
) -> Contact | None:
    """Deepest overlap of the drone cylinder centred at ``p`` with any structure (or None).

    Exact for boxes and vertical cylinders (product shapes); spheres use the same split of the
    closest-point offset, a close approximation.
    """
    best: Contact | None = None
    half = 0.5 * height
    reach = math.hypot(radius, half)
    for i, obj in enumerate(scene.objects):
        d, c, n = obj.closest(p)
        if d > reach:
            continue
        dx, dy, dz = p[0] - c[0], p[1] - c[1], p[2] - c[2]
        dxy = math.hypot(dx, dy)
        if d < 0.0:  # centre inside the object: escape along the object's normal
            extra = radius if abs(n[2]) < 0.5 else half
            cand = Contact(i, extra - d, n, c)
        else:
            pen_h, pen_v = radius - dxy, half - abs(dz)
            if pen_h <= 0.0 or pen_v <= 0.0:
                continue
            if dxy > 1e-9 and (pen_h <= pen_v or abs(dz) < 1e-9):
                cand = Contact(i, pen_h, (dx / dxy, dy / dxy, 0.0), c)
            else:
                cand = Contact(i, pen_v, (0.0, 0.0, 1.0 if dz >= 0.0 else -1.0), c)
        if best is None or cand.depth > best.depth:
            best = cand
    return best


class QuadBody:
    """State and one integration step of the rigid body (the ``simple`` engine, implementing
    :class:`~firmware_bridge.sitl.engine.Physics`). All attributes are plain floats.

    Parameters
    ----------
    params : QuadParams
    position : (3,) metres, ENU.
    yaw : rad, heading of body x from world x, counter-clockwise.
    """

    name = "simple"

    def __init__(self, params: QuadParams, position: tuple[float, float, float], yaw: float = 0.0):
        self.p = params
        self.airframe = cylinder_airframe(params.radius, params.height, params.mass)
        self.mass, self.drag = params.mass, params.drag
        self.rest_height = params.height / 2
        self.x, self.y, self.z = position
        self.vx = self.vy = self.vz = 0.0
        self.qw, self.qx, self.qy, self.qz = math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)
        self.wx = self.wy = self.wz = 0.0
        self.thrust = params.mass * GRAVITY  # N, starts hovering
        # Specific force (world, m/s^2) and contact accel at the last step.
        self.fx, self.fy, self.fz = 0.0, 0.0, GRAVITY
        self.contact: Contact | None = None
        self.contact_accel = 0.0  # |F_contact| / m, m/s^2

    # -- kinematics helpers --------------------------------------------------------------------
    def rotation(self) -> tuple[float, ...]:
        """Body -> world rotation matrix, row-major 9-tuple."""
        w, x, y, z = self.qw, self.qx, self.qy, self.qz
        return (
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        )

    @property
    def position(self) -> tuple[float, float, float]:
        return (self.x, self.y, self.z)

    @property
    def velocity(self) -> tuple[float, float, float]:
        return (self.vx, self.vy, self.vz)

    @property
    def quaternion(self) -> tuple[float, float, float, float]:
        """(w, x, y, z) body FLU -> world ENU."""
        return (self.qw, self.qx, self.qy, self.qz)

    # -- one step ------------------------------------------------------------------------------
    def step(
        self,
        dt: float,
        thrust_cmd: float,
        rate_cmd: tuple[float, float, float],
        scene: Scene,
        gust: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> None:
        """Advance by ``dt`` seconds.

        Parameters
        ----------
        thrust_cmd : N along body +z.
        rate_cmd : body FLU angular rate setpoint, rad/s.
        gust : external force per unit mass, world frame, m/s^2.
        """
        P = self.p
        m = P.mass
        self.thrust += (thrust_cmd - self.thrust) * min(1.0, dt / P.thrust_tau)
        a = min(1.0, dt / P.rate_tau)
        self.wx += (rate_cmd[0] - self.wx) * a
        self.wy += (rate_cmd[1] - self.wy) * a
        self.wz += (rate_cmd[2] - self.wz) * a

        w, x, y, z = self.qw, self.qx, self.qy, self.qz
        bx, by, bz = 2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)
        t = self.thrust
        fx = t * bx - P.drag * self.vx + m * gust[0]
        fy = t * by - P.drag * self.vy + m * gust[1]
        fz = t * bz - P.drag * self.vz + m * gust[2]

        # Structure contact: spring-damper along the normal, push only.
        pos = (self.x, self.y, self.z)
        c = contact_penetration(scene, pos, P.radius, P.height)
        fc = 0.0
        if c is not None:
            nx, ny, nz = c.normal
            rate = -(self.vx * nx + self.vy * ny + self.vz * nz)  # d(pen)/dt
            fc = max(0.0, P.contact_stiffness * c.depth + P.contact_damping * rate)
            fx += fc * nx
            fy += fc * ny
            fz += fc * nz
        # Floor: stiff, critically damped landing gear plus friction while resting on it.
        pen_g = scene.region_min[2] + 0.5 * P.height - self.z
        if pen_g > 0.0:
            k = P.ground_stiffness
            fg = max(0.0, k * pen_g - 2.0 * math.sqrt(k * m) * self.vz)
            fz += fg
            fx -= P.ground_friction * self.vx
            fy -= P.ground_friction * self.vy
            if c is None:
                c = Contact(-1, pen_g, (0.0, 0.0, 1.0), (self.x, self.y, scene.region_min[2]))
                fc = fg
        self.contact = c
        self.contact_accel = fc / m

        # Semi-implicit Euler: v then p with the new v.
        self.fx, self.fy, self.fz = fx / m, fy / m, fz / m
        self.vx += self.fx * dt
        self.vy += self.fy * dt
        self.vz += (self.fz - GRAVITY) * dt
        self.x += self.vx * dt
        self.y += self.vy * dt
        self.z += self.vz * dt

        # q <- q (x) [1, w dt / 2], renormalized.
        hx, hy, hz = 0.5 * dt * self.wx, 0.5 * dt * self.wy, 0.5 * dt * self.wz
        nw = w - x * hx - y * hy - z * hz
        nx_ = x + w * hx + y * hz - z * hy
        ny_ = y + w * hy + z * hx - x * hz
        nz_ = z + w * hz + x * hy - y * hx
        s = 1.0 / math.sqrt(nw * nw + nx_ * nx_ + ny_ * ny_ + nz_ * nz_)
        self.qw, self.qx, self.qy, self.qz = nw * s, nx_ * s, ny_ * s, nz_ * s
