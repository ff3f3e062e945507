"""The simulated vehicle: physics, controller, IMU, gusts, pilot, failsafe (pure, seeded).

Time is an integer count of physics steps (``physics_rate`` Hz); nothing reads a clock.

Manual flight (PX4 position-mode-like): MANUAL_CONTROL x (forward) / y (right) give horizontal
velocity in the heading frame, z (0..1000, 500 = hold) climb rate, r yaw rate; centred sticks
hold position. Vehicle-side failsafe: no MANUAL_CONTROL for ``stale_after`` (0.5 s) -> HOLD at
the current position; after ``land_after`` more seconds -> LAND; on the floor -> LANDED
(disarmed). Any pilot input in HOLD or LAND resumes MANUAL; from LANDED only a climb command
(z > 600) re-arms. Before the first input the vehicle holds indefinitely (waiting for a pilot).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from firmware_bridge.sitl.airframe import Airframe
from firmware_bridge.sitl.control import ControlGains, Controller, Setpoint
from firmware_bridge.sitl.engine import MujocoParams, Physics, make_physics
from firmware_bridge.sitl.gusts import GustParams, GustSchedule
from firmware_bridge.sitl.imu_model import ImuModel, ImuParams, quat_enu_flu_to_ned_frd
from firmware_bridge.sitl.physics import GRAVITY, QuadParams
from firmware_bridge.sitl.scene import Scene
from firmware_bridge.sitl.truth import ContactTracker

MANUAL, HOLD, LAND, LANDED = "MANUAL", "HOLD", "LAND", "LANDED"


@dataclass(frozen=True)
class VehicleSettings:
    """Everything that shapes the simulated vehicle (SI units).

    ``physics`` picks the engine (``simple`` | ``mujoco``, :mod:`.engine`); ``quad`` holds the
    simple engine's body and the drag/lag constants both share; ``airframe`` the MuJoCo body
    (None: :class:`~firmware_bridge.sitl.airframe.Airframe`'s defaults). Use
    :func:`vehicle_settings` for the engine's own physics rate (800 Hz simple, 1 kHz MuJoCo).
    """

    physics_rate: int = 800  # Hz
    quad: QuadParams = field(default_factory=QuadParams)
    imu: ImuParams = field(default_factory=ImuParams)
    gusts: GustParams = field(default_factory=GustParams)
    gains: ControlGains = field(default_factory=ControlGains)
    stale_after: float = 0.5  # s without MANUAL_CONTROL -> HOLD
    land_after: float = 3.0  # s in HOLD -> LAND
    land_speed: float = 0.5  # m/s, 0.25 m/s in the last 0.3 m
    max_speed: float = 2.0  # m/s at full stick
    max_climb: float = 1.0  # m/s at full stick
    max_yaw_rate: float = math.radians(90.0)  # rad/s at full stick
    physics: str = "simple"
    airframe: Airframe | None = None
    mujoco: MujocoParams = field(default_factory=MujocoParams)


def vehicle_settings(physics: str = "simple", **kwargs: object) -> VehicleSettings:
    """:class:`VehicleSettings` for ``physics`` at that engine's rate unless one is given."""
    kwargs.setdefault("physics_rate", 1000 if physics == "mujoco" else 800)
    return VehicleSettings(physics=physics, **kwargs)  # type: ignore[arg-type]


def planning_cylinder(settings: VehicleSettings) -> tuple[float, float]:
    """Radius and height (m) of the origin-centred cylinder that contains the body."""
    if settings.physics == "simple":
        return settings.quad.radius, settings.quad.height
    a = settings.airframe or Airframe()
    return a.reach_max, a.planning_height


class ManualFlight:
    """MANUAL_CONTROL -> setpoints, with the vehicle-side failsafe state machine."""

    def __init__(self, settings: VehicleSettings, start: tuple[float, float, float], floor: float):
        self.s = settings
        self.floor = floor
        self.mode = HOLD
        self.last_input: float | None = None
        self.mode_since = 0.0
        self.hold: tuple[float, float, float] = start
        self.yaw = 0.0
        self.sticks = (0, 0, 500, 0)
        self._locked: list[float | None] = [None, None, None]
        self.transitions: list[tuple[float, str]] = [(0.0, HOLD)]
        self.done = False

    def _set(self, t: float, mode: str, body: Physics) -> None:
        if mode != self.mode:
            self.mode, self.mode_since = mode, t
            # Hold where the vehicle comes to rest when braking (~0.3 s at the current speed).
            self.hold = tuple(body.position[i] + 0.3 * body.velocity[i] for i in range(3))
            self.transitions.append((t, mode))

    def on_manual_control(self, t: float, x: int, y: int, z: int, r: int) -> None:
        """A MANUAL_CONTROL arrived at sim time ``t`` (s); values in MAVLink units."""
        self.last_input = t
        self.sticks = (x, y, z, r)

    def setpoint(self, t: float, body: Physics, dt: float) -> Setpoint:
        """Failsafe transitions, then the setpoint of the current mode."""
        s = self.s
        fresh = self.last_input is not None and t - self.last_input <= s.stale_after
        if fresh and self.mode in (HOLD, LAND):
            self._set(t, MANUAL, body)
        elif fresh and self.mode == LANDED and self.sticks[2] > 600:
            self._set(t, MANUAL, body)
        elif not fresh and self.mode == MANUAL:
            self._set(t, HOLD, body)
        elif self.mode == HOLD and self.last_input is not None:
            if t - self.mode_since >= s.land_after:
                self._set(t, LAND, body)
        elif self.mode == LAND:
            on_floor = body.z <= self.floor + body.rest_height + 0.02 and abs(body.vz) < 0.1
            if on_floor and t - self.mode_since > 0.5:
                self._set(t, LANDED, body)
        if self.mode == HOLD:
            return Setpoint(position=self.hold, yaw=self.yaw)
        if self.mode == LAND:
            low = body.z - self.floor < 0.35
            vz = -(0.25 if low else s.land_speed)
            return Setpoint(
                position=(self.hold[0], self.hold[1], None), velocity=(0, 0, vz), yaw=self.yaw
            )
        if self.mode == LANDED:
            return Setpoint(armed=False, yaw=self.yaw)
        # MANUAL: sticks -> velocity in the heading frame; centred axes lock position.
        x, y, z, r = (v / 1000.0 for v in self.sticks)
        z = 2.0 * z - 1.0
        self.yaw += r * s.max_yaw_rate * dt
        fwd, right = x * s.max_speed, y * s.max_speed
        c, sn = math.cos(self.yaw), math.sin(self.yaw)
        vel = (fwd * c + right * sn, fwd * sn - right * c, z * s.max_climb)
        pos: list[float | None] = [None, None, None]
        dead = 0.05
        horiz_centred = abs(x) < dead and abs(y) < dead
        for i, centred in ((0, horiz_centred), (1, horiz_centred), (2, abs(z) < dead)):
            if centred:
                if self._locked[i] is None:
                    self._locked[i] = body.position[i] + body.velocity[i] * 0.3
                pos[i] = self._locked[i]
            else:
                self._locked[i] = None
        return Setpoint(
            position=tuple(pos),
            velocity=vel,
            yaw=self.yaw,  # type: ignore[arg-type]
            max_speed=s.max_speed,
        )


class Vehicle:
    """Rigid body + controller + pilot + gusts + IMU + contact truth; advanced one step at a time.

    Parameters
    ----------
    scene : Scene
    pilot : a scripted pilot (``setpoint(t, body)``) or None for :class:`ManualFlight`.
    seed : int, seeds the single numpy Generator all randomness comes from.
    """

    def __init__(
        self, scene: Scene, pilot: object | None, seed: int, settings: VehicleSettings | None = None
    ):
        self.settings = s = settings or VehicleSettings()
        self.scene = scene
        self.rng = np.random.default_rng(seed)
        self.body: Physics = make_physics(
            s.physics, scene, s.quad, s.airframe, s.mujoco, s.physics_rate
        )
        self.controller = Controller(s.gains)
        self.manual = ManualFlight(s, scene.start, scene.region_min[2]) if pilot is None else None
        self.pilot = pilot
        mass = self.body.mass
        self.gusts = GustSchedule(s.gusts, np.random.default_rng(self.rng.integers(2**63)), mass)
        self.imu = ImuModel(s.imu, np.random.default_rng(self.rng.integers(2**63)), mass * GRAVITY)
        self.tracker = ContactTracker()
        self.steps = 0
        self.dt = 1.0 / s.physics_rate
        self.step_ns = 1_000_000_000 // s.physics_rate
        self._acc = [0.0, 0.0, 0.0]
        self._acc_n = 0
        self._last_imu_t = 0.0
        self._clear_check = 0
        self._clearance = math.inf

    @property
    def t(self) -> float:
        """Simulation time, s."""
        return self.steps * self.dt

    @property
    def t_ns(self) -> int:
        return self.steps * self.step_ns

    @property
    def pilot_done(self) -> bool:
        return bool(getattr(self.pilot, "done", False))

    def manual_control(self, x: int, y: int, z: int, r: int) -> None:
        """Feed a MANUAL_CONTROL (ignored while a scripted pilot flies)."""
        if self.manual is not None:
            self.manual.on_manual_control(self.t, x, y, z, r)

    def step(self) -> None:
        """Advance the simulation by one physics step."""
        t = self.t
        b = self.body
        if self.manual is not None:
            sp = self.manual.setpoint(t, b, self.dt)
        else:
            sp = self.pilot.setpoint(t, b)  # type: ignore[union-attr]
        thrust, rates = self.controller.update(b, sp)
        if self._clear_check == 0:  # structure clearance for the gust model, at ~100 Hz
            self._clearance = self.scene.closest(b.position)[0]
        self._clear_check = (self._clear_check + 1) % 8
        gust = self.gusts.force(t, self._clearance, b.position)
        b.step(self.dt, thrust, rates, self.scene, gust)
        self.steps += 1
        self.tracker.update(self.t, b)
        log = getattr(self.pilot, "maneuvers", None)
        if log is not None and log.active is not None:  # true acceleration, gravity removed
            log.update(self.dt, b.fx, b.fy, b.fz - GRAVITY)
        self._acc[0] += b.fx
        self._acc[1] += b.fy
        self._acc[2] += b.fz
        self._acc_n += 1

    def imu_sample(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """IMU sample (accel m/s^2, gyro rad/s; body FRD) averaging the force since the last one."""
        n = max(1, self._acc_n)
        f = (self._acc[0] / n, self._acc[1] / n, self._acc[2] / n)
        self._acc = [0.0, 0.0, 0.0]
        self._acc_n = 0
        b = self.body
        dt = self.t - self._last_imu_t
        self._last_imu_t = self.t
        return self.imu.sample(f, b.rotation(), (b.wx, b.wy, b.wz), b.thrust, dt)

    def attitude(self) -> tuple[tuple[float, float, float, float], tuple[float, float, float]]:
        """(quaternion w, x, y, z body FRD -> local NED, body rates FRD rad/s)."""
        b = self.body
        return quat_enu_flu_to_ned_frd(b.quaternion), (b.wx, -b.wy, -b.wz)

    @property
    def mode(self) -> str:
        if self.manual is not None:
            return self.manual.mode
        return "SCRIPT_DONE" if self.pilot_done else "SCRIPT"

    @property
    def armed(self) -> bool:
        return self.mode != LANDED
