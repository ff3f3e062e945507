"""One small interface in front of the physics engines, and the factory that picks one.

The vehicle, controller, pilots and truth only read the attributes of :class:`Physics` (plain
floats, for the 1 kHz Python loop) and call :meth:`Physics.step`. Two engines implement it:

- ``simple`` (:class:`~firmware_bridge.sitl.physics.QuadBody`): the home-made rigid body, the
  drone a vertical cylinder with spring-damper contacts (restitution 0.5); no rotation from
  contact. The default, and what the bundled replay logs were made with.
- ``mujoco`` (:class:`~firmware_bridge.sitl.mujoco_physics.MujocoBody`): an independent engine
  (DeepMind's MuJoCo) with the airframe's real geometry (guards, arms, body, legs), four
  rotors with motor lag and thrust limits, soft contacts (restitution ~0.4) with friction on
  the scene's boxes, cylinders and spheres; contacts turn the body as well as push it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from firmware_bridge.errors import BridgeError
from firmware_bridge.sitl.airframe import Airframe
from firmware_bridge.sitl.physics import Contact, QuadBody, QuadParams
from firmware_bridge.sitl.scene import Scene

ENGINES = ("simple", "mujoco")


class PhysicsError(BridgeError, ValueError):
    """An unknown physics engine, or one that cannot be loaded here."""


@dataclass(frozen=True)
class MujocoParams:
    """MuJoCo contact and solver settings.

    ``solref`` (time constant s, damping ratio) sets the contacts' spring-damper: the damping
    ratio 0.34 gives a measured restitution of 0.39-0.42 and 19-20 ms contacts for guard touches
    at 0.3-1 m/s (0.28: 0.44-0.47, 0.40: 0.34-0.36; MuJoCo's default ratio of 1 gives ~0.1);
    ``friction`` is the sliding friction coefficient of the guards on
    the structures (rolling/torsional stay tiny); ``floor_friction`` that of the feet on the
    floor.
    """

    solref: tuple[float, float] = (0.02, 0.34)
    solimp: tuple[float, float, float] = (0.9, 0.95, 0.001)
    friction: float = 0.3
    floor_friction: float = 0.8
    nominal_restitution: float = 0.4  # what ``solref`` was measured to give (for the truth)
    angular_drag: float = 0.002  # N m / (rad/s), rotational air drag


class Physics(Protocol):
    """What an engine exposes (world ENU, body FLU, SI units; all plain floats).

    Attributes
    ----------
    name : engine name (``simple`` | ``mujoco``).
    airframe : the body it simulates.
    mass, drag : kg, N/(m/s) linear air drag (the controller compensates it).
    x, y, z, vx, vy, vz : position of the body origin (m) and its velocity (m/s).
    qw, qx, qy, qz : attitude quaternion, body FLU -> world ENU.
    wx, wy, wz : body rates (rad/s, FLU).
    thrust : total rotor thrust (N) along body z.
    fx, fy, fz : specific force at the last step (m/s^2, world): what an ideal accelerometer
        at the origin measures, rotated to the world.
    contact : the deepest contact at the last step (or None); ``object_index`` -1 = floor.
    contact_accel : |contact force| / mass at the last step (m/s^2).
    rest_height : height of the origin above the floor when landed (m).
    """

    name: str
    airframe: Airframe
    mass: float
    drag: float
    x: float
    y: float
    z: float
    vx: float
    vy: float
    vz: float
    qw: float
    qx: float
    qy: float
    qz: float
    wx: float
    wy: float
    wz: float
    thrust: float
    fx: float
    fy: float
    fz: float
    contact: Contact | None
    contact_accel: float
    rest_height: float

    @property
    def position(self) -> tuple[float, float, float]: ...

    @property
    def velocity(self) -> tuple[float, float, float]: ...

    @property
    def quaternion(self) -> tuple[float, float, float, float]: ...

    def rotation(self) -> tuple[float, ...]: ...

    def step(
        self,
        dt: float,
        thrust_cmd: float,
        rate_cmd: tuple[float, float, float],
        scene: Scene,
        gust: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> None: ...


def make_physics(
    engine: str,
    scene: Scene,
    quad: QuadParams,
    airframe: Airframe | None,
    mujoco: MujocoParams,
    rate: int,
) -> Physics:
    """The ``engine`` body hovering at the scene's start (yaw 0)."""
    if engine == "simple":
        return QuadBody(quad, scene.start)
    if engine == "mujoco":
        try:
            from firmware_bridge.sitl.mujoco_physics import MujocoBody
        except ImportError as exc:  # pragma: no cover - mujoco is a declared dependency
            raise PhysicsError(
                f"--physics mujoco: cannot import the mujoco package ({exc})",
                hint="run ./bootstrap.sh (it installs mujoco from PyPI)",
            ) from exc
        return MujocoBody(scene, airframe or Airframe(), quad, mujoco, rate)
    raise PhysicsError(f"unknown physics engine {engine!r}", hint=f"use {' or '.join(ENGINES)}")
