"""The ``mujoco`` physics engine: the airframe's real body in MuJoCo (an independent engine).

Implements :class:`~firmware_bridge.sitl.engine.Physics` around a model written by
:func:`~firmware_bridge.sitl.mjcf.build_mjcf`. Per step (1 kHz by default):

1. The flight controller's inner loop: the cascade's thrust (N) and body-rate setpoint become a
   torque tau = I (w_cmd - w) / rate_tau + w x I w (the same first-order rate response as the
   simple engine, here through the real inertia), mixed into four rotor thrusts by inverting the
   layout's allocation [T, tau_x, tau_y, tau_z] = A [T_0..T_3] and clipped to 0..T_max; the
   rotors' ``filter`` dynamics add the motor lag.
2. Gusts and air drag as an external force on the body (``xfrc_applied``, world frame, at the
   centre of mass): m * gust - drag * v, and -angular_drag * w as torque.
3. ``mj_step``; the accelerometer (specific force, site frame) is rotated to the world with the
   site's orientation of that step, so the IMU model reads exactly MuJoCo's accelerometer.
4. Contacts between vehicle geoms and scene geoms: the deepest becomes :attr:`contact`, with the
   scene object's true surface point and outward normal at MuJoCo's contact position, and the
   body part that touched; the contact forces (``mj_contactForce``) give ``contact_accel``.

MuJoCo is deterministic for a given build and model: the same seed gives the same bytes.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from firmware_bridge.sitl.airframe import Airframe
from firmware_bridge.sitl.engine import MujocoParams
from firmware_bridge.sitl.mjcf import build_mjcf
from firmware_bridge.sitl.physics import GRAVITY, Contact, QuadParams
from firmware_bridge.sitl.scene import Scene

Vec = tuple[float, float, float]


class MujocoBody:
    """The vehicle simulated by MuJoCo; attributes as in the Physics protocol (plain floats).

    Parameters
    ----------
    scene : Scene (its structures become static geoms, the floor a plane).
    airframe : Airframe (layout ``x`` or ``+``).
    quad : QuadParams (``drag`` and ``rate_tau`` are shared with the simple engine).
    params : MujocoParams (contact solver settings, friction, angular drag).
    rate : Hz, the MuJoCo timestep is 1 / rate.
    """

    name = "mujoco"

    def __init__(
        self, scene: Scene, airframe: Airframe, quad: QuadParams, params: MujocoParams, rate: int
    ):
        self.scene, self.airframe, self.params = scene, airframe, params
        self.xml, vgeoms = build_mjcf(
            airframe,
            scene,
            rate,
            params.solref,
            params.solimp,
            params.friction,
            params.floor_friction,
        )
        self.model = m = mujoco.MjModel.from_xml_string(self.xml)
        self.data = d = mujoco.MjData(m)
        self._body = m.body("quad").id
        self._site = m.site("imu").id
        self._accel = m.sensor("accel").adr[0]
        model_mass = float(m.body_subtreemass[self._body])
        if abs(model_mass - airframe.mass) > 1e-9:  # pragma: no cover - the builder's invariant
            raise ValueError(f"model mass {model_mass} kg != airframe mass {airframe.mass} kg")
        self.mass = airframe.mass
        self.drag = quad.drag
        self.rate_tau = quad.rate_tau
        self.rest_height = airframe.bottom
        # Geom id -> (part, name) for the vehicle, -> object index for the scene (-1 floor).
        self._part: dict[int, tuple[str, str]] = {
            m.geom(g.name).id: (g.part, g.name) for g in vgeoms
        }
        self._object: dict[int, int] = {m.geom("floor").id: -1}
        for i in range(len(scene.objects)):
            self._object[m.geom(f"obj{i}").id] = i
        # Inertia about the centre of mass in the body frame: R_i diag(I) R_i^T.
        rq = np.zeros(9)
        mujoco.mju_quat2Mat(rq, m.body_iquat[self._body])
        ri = rq.reshape(3, 3)
        self._inertia = (ri @ np.diag(m.body_inertia[self._body]) @ ri.T).tolist()
        # Allocation: [T, tau_x, tau_y, tau_z] = A @ thrusts (about the centre of mass).
        com = m.body_ipos[self._body]
        rows = [[1.0] * 4, [], [], []]
        for x, y, _, spin in airframe.rotors():
            rows[1].append(y - com[1])
            rows[2].append(-(x - com[0]))
            rows[3].append(-spin * airframe.yaw_moment)
        self._mix = np.linalg.inv(np.array(rows)).tolist()
        self.t_max = airframe.thrust_to_weight * self.mass * GRAVITY / 4
        # Start hovering: motors (filter states) at the hover thrust.
        d.qpos[0:3] = scene.start
        d.qpos[3:7] = (1.0, 0.0, 0.0, 0.0)
        d.act[:] = self.mass * GRAVITY / 4
        d.ctrl[:] = self.mass * GRAVITY / 4
        mujoco.mj_forward(m, d)
        self._force6 = np.zeros(6)
        self._read_state()
        self.fx, self.fy, self.fz = 0.0, 0.0, GRAVITY
        self.contact: Contact | None = None
        self.contact_accel = 0.0

    # -- state -------------------------------------------------------------------------------
    def _read_state(self) -> None:
        d = self.data
        self.x, self.y, self.z, self.qw, self.qx, self.qy, self.qz = d.qpos[0:7].tolist()
        self.vx, self.vy, self.vz, self.wx, self.wy, self.wz = d.qvel[0:6].tolist()
        self.thrust = sum(d.actuator_force.tolist())
        w, x, y, z = self.qw, self.qx, self.qy, self.qz
        self._R = (
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
    def position(self) -> Vec:
        return (self.x, self.y, self.z)

    @property
    def velocity(self) -> Vec:
        return (self.vx, self.vy, self.vz)

    @property
    def quaternion(self) -> tuple[float, float, float, float]:
        return (self.qw, self.qx, self.qy, self.qz)

    def rotation(self) -> tuple[float, ...]:
        """Body -> world rotation matrix, row-major 9-tuple (of the current state)."""
        return self._R

    def describe(self) -> dict:
        """Engine facts for the truth: version, timestep, contact settings."""
        p = self.params
        return {
            "mujoco_version": mujoco.__version__,
            "timestep": float(self.model.opt.timestep),
            "solref": list(p.solref),
            "solimp": list(p.solimp),
            "friction": p.friction,
            "floor_friction": p.floor_friction,
            "nominal_restitution": p.nominal_restitution,
            "geoms": int(self.model.ngeom),
            "thrust_max_per_rotor_n": self.t_max,
        }

    # -- one step ----------------------------------------------------------------------------
    def step(
        self,
        dt: float,
        thrust_cmd: float,
        rate_cmd: tuple[float, float, float],
        scene: Scene,
        gust: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> None:
        """Advance by one MuJoCo timestep (``dt`` must equal it; ``scene`` is the built one)."""
        m, d = self.model, self.data
        wx, wy, wz = self.wx, self.wy, self.wz
        k = 1.0 / self.rate_tau
        ax, ay, az = (rate_cmd[0] - wx) * k, (rate_cmd[1] - wy) * k, (rate_cmd[2] - wz) * k
        inert = self._inertia
        iw = [inert[i][0] * wx + inert[i][1] * wy + inert[i][2] * wz for i in range(3)]
        ia = [inert[i][0] * ax + inert[i][1] * ay + inert[i][2] * az for i in range(3)]
        tau = (
            ia[0] + wy * iw[2] - wz * iw[1],
            ia[1] + wz * iw[0] - wx * iw[2],
            ia[2] + wx * iw[1] - wy * iw[0],
        )
        thrusts = self._allocate(thrust_cmd, tau)
        ctrl = d.ctrl
        for i in range(4):
            ctrl[i] = thrusts[i]
        # External force at the centre of mass (world): gust, linear and angular air drag.
        mass, drag, ad = self.mass, self.drag, self.params.angular_drag
        R = self.rotation()
        xf = d.xfrc_applied[self._body]
        xf[0] = mass * gust[0] - drag * self.vx
        xf[1] = mass * gust[1] - drag * self.vy
        xf[2] = mass * gust[2] - drag * self.vz
        xf[3] = -ad * (R[0] * wx + R[1] * wy + R[2] * wz)
        xf[4] = -ad * (R[3] * wx + R[4] * wy + R[5] * wz)
        xf[5] = -ad * (R[6] * wx + R[7] * wy + R[8] * wz)
        mujoco.mj_step(m, d)
        # Specific force measured during the step, site frame -> world with that step's pose.
        a0, a1, a2 = d.sensordata[self._accel : self._accel + 3].tolist()
        S = d.site_xmat[self._site].tolist()
        self.fx = S[0] * a0 + S[1] * a1 + S[2] * a2
        self.fy = S[3] * a0 + S[4] * a1 + S[5] * a2
        self.fz = S[6] * a0 + S[7] * a1 + S[8] * a2
        self._read_state()
        self._contacts()

    def _allocate(self, thrust: float, tau: tuple[float, float, float]) -> list[float]:
        """Rotor thrusts (N, within 0..T_max) for collective ``thrust`` and body torque ``tau``.

        Desaturation as flight controllers do it: roll/pitch first (scaled down only if their
        spread alone exceeds the range), then yaw within what is left, then the collective
        shifted into the remaining room, so attitude control survives full-stick manoeuvres.
        """
        mix, t_max = self._mix, self.t_max
        rp = [row[1] * tau[0] + row[2] * tau[1] for row in mix]
        yw = [row[3] * tau[2] for row in mix]
        span = max(rp) - min(rp)
        if span > t_max:
            rp = [v * t_max / span for v in rp]
            yw = [0.0] * 4
        else:
            both = [rp[i] + yw[i] for i in range(4)]
            span2 = max(both) - min(both)
            if span2 > t_max:  # keep as much yaw as fits
                k = 0.0 if span2 <= span else (t_max - span) / (span2 - span)
                yw = [v * max(0.0, min(1.0, k)) for v in yw]
        diff = [rp[i] + yw[i] for i in range(4)]
        base = thrust * mix[0][0]  # collective per rotor (T / 4: the layout is symmetric)
        lo, hi = -min(diff), t_max - max(diff)
        base = lo if base < lo else (hi if base > hi else base)
        out = [base + v for v in diff]
        return [0.0 if v < 0.0 else (t_max if v > t_max else v) for v in out]

    def _contacts(self) -> None:
        d = self.data
        n = d.ncon
        if n == 0:
            self.contact, self.contact_accel = None, 0.0
            return
        con = d.contact
        g1, g2 = con.geom1[:n].tolist(), con.geom2[:n].tolist()
        dist = con.dist[:n].tolist()
        best: tuple[float, int, int, int] | None = None  # (depth, contact, object, vehicle geom)
        floor_only = True
        for i in range(n):
            a, b = g1[i], g2[i]
            obj = self._object.get(a, self._object.get(b))
            veh = b if a in self._object else a
            if obj is None or veh not in self._part:
                continue
            if obj >= 0 and floor_only:
                floor_only, best = False, None
            if obj < 0 and not floor_only:
                continue
            if best is None or -dist[i] > best[0]:
                best = (-dist[i], i, obj, veh)
        if best is None:
            self.contact, self.contact_accel = None, 0.0
            return
        # Net contact force on the vehicle from the contacts of the reported kind.
        fsum = [0.0, 0.0, 0.0]
        f6 = self._force6
        for i in range(n):
            a, b = g1[i], g2[i]
            obj = self._object.get(a, self._object.get(b))
            if obj is None or (obj < 0) != floor_only:
                continue
            mujoco.mj_contactForce(self.model, d, i, f6)
            fr = con.frame[i]  # rows: normal (geom1 -> geom2), tangent 1, tangent 2
            sgn = 1.0 if a in self._object else -1.0  # force on the vehicle
            for j in range(3):
                fsum[j] += sgn * (f6[0] * fr[j] + f6[1] * fr[3 + j] + f6[2] * fr[6 + j])
        self.contact_accel = math.sqrt(fsum[0] ** 2 + fsum[1] ** 2 + fsum[2] ** 2) / self.mass
        depth, i, obj, veh = best
        pos = tuple(con.pos[i].tolist())
        if obj < 0:
            point, normal = (pos[0], pos[1], self.scene.region_min[2]), (0.0, 0.0, 1.0)
        else:
            _, point, normal = self.scene.objects[obj].closest(pos)  # type: ignore[arg-type]
        part, name = self._part[veh]
        self.contact = Contact(obj, max(depth, 0.0), normal, point, part, name)
