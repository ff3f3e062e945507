"""MJCF (MuJoCo's XML model) of the airframe in a scene, written from the frozen descriptions.

One free-floating body ``quad`` (a ``freejoint``) holds, in body frame FLU:

- ``body``: the central box; ``arm0..3``: capsules from the centre to the rotors;
  ``motor0..3``: small cylinders under the props;
- ``guard{k}_{j}``: each prop guard's rim as ``guard_segments`` capsules around the rotor
  (MuJoCo has no torus), tube radius ``guard_tube``; ``leg0..3``: capsules to the feet;
- sites ``imu`` (origin; ``accelerometer`` and ``gyro`` sensors) and ``rotor0..3`` (thrust
  points). Each rotor is a ``general`` actuator on its site: thrust along site z with a
  first-order lag (``dyntype="filter"``, ``motor_tau``), range 0..T_max, and the rotor's drag
  torque about z (``gear`` yaw term -spin * ``yaw_moment``).

The scene's primitives become static world geoms (``obj{i}``) and the floor a plane at the
region's bottom. Collision filtering: vehicle geoms (contype 1, conaffinity 0) collide only with
scene geoms (contype 0, conaffinity 1), never with each other. Every geom has the given
``solref``/``solimp``; friction is the sliding coefficient (guards on structures, feet on the
floor). Masses are explicit per geom; MuJoCo computes the inertia from the shapes.
"""

from __future__ import annotations

from dataclasses import dataclass
from xml.sax.saxutils import quoteattr

from firmware_bridge.sitl.airframe import Airframe
from firmware_bridge.sitl.physics import GRAVITY
from firmware_bridge.sitl.scene import Box, Cylinder, Scene, Sphere

Vec = tuple[float, float, float]


@dataclass(frozen=True)
class VehicleGeom:
    """A vehicle geom's name and the body part it belongs to (guard, arm, body, leg, motor)."""

    name: str
    part: str


def _f(*values: float) -> str:
    return " ".join(repr(float(v)) for v in values)


def _attrs(**kv: object) -> str:
    return " ".join(f"{k}={quoteattr(str(v))}" for k, v in kv.items())


def vehicle_geoms(a: Airframe) -> list[tuple[VehicleGeom, str]]:
    """(geom, MJCF element) for every collision piece of the airframe, body frame."""
    out: list[tuple[VehicleGeom, str]] = []

    def add(name: str, part: str, **kv: object) -> None:
        out.append((VehicleGeom(name, part), f"<geom {_attrs(name=name, **kv)}/>"))

    add("body", "body", type="box", size=_f(*a.body_half), mass=_f(a.body_mass))
    n = a.guard_segments
    for k, (x, y, z, _spin) in enumerate(a.rotors()):
        add(f"arm{k}", "arm", type="capsule", fromto=_f(0, 0, 0, x, y, 0), size="0.008",
            mass=_f(a.arm_mass))  # fmt: skip
        add(f"motor{k}", "motor", type="cylinder", pos=_f(x, y, z / 2), size=_f(0.014, z / 2),
            mass=_f(a.motor_mass))  # fmt: skip
        ring = a.guard_ring(k)
        for j in range(n):
            p0, p1 = ring[j], ring[(j + 1) % n]
            add(f"guard{k}_{j}", "guard", type="capsule", fromto=_f(*p0, *p1),
                size=_f(a.guard_tube), mass=_f(a.guard_mass / n))  # fmt: skip
    for k, (top, foot) in enumerate(a.legs()):
        add(f"leg{k}", "leg", type="capsule", fromto=_f(*top, *foot),
            size=_f(a.leg_radius), mass=_f(a.leg_mass))  # fmt: skip
    return out


def scene_geoms(scene: Scene) -> list[str]:
    """MJCF world geoms ``obj{i}`` for the scene's primitives (same order as scene.objects)."""
    out = []
    for i, o in enumerate(scene.objects):
        if isinstance(o, Box):
            c = [(o.min[k] + o.max[k]) / 2 for k in range(3)]
            h = [(o.max[k] - o.min[k]) / 2 for k in range(3)]
            out.append(f"<geom {_attrs(name=f'obj{i}', type='box', pos=_f(*c), size=_f(*h))}/>")
        elif isinstance(o, Cylinder):
            c = (o.center[0], o.center[1], o.center[2] + o.height / 2)
            kv = {"name": f"obj{i}", "type": "cylinder", "pos": _f(*c)}
            out.append(f"<geom {_attrs(**kv, size=_f(o.radius, o.height / 2))}/>")
        elif isinstance(o, Sphere):
            kv = {"name": f"obj{i}", "type": "sphere", "pos": _f(*o.center)}
            out.append(f"<geom {_attrs(**kv, size=_f(o.radius))}/>")
        else:  # pragma: no cover - parse_scene only makes the three
            raise TypeError(f"scene object {i}: unsupported primitive {type(o).__name__}")
    return out


def build_mjcf(
    airframe: Airframe,
    scene: Scene,
    rate: int,
    solref: tuple[float, float],
    solimp: tuple[float, float, float],
    friction: float,
    floor_friction: float,
) -> tuple[str, list[VehicleGeom]]:
    """The model's XML and the vehicle geoms in the order they appear (names are unique)."""
    if airframe.layout == "cylinder":
        raise ValueError("the MuJoCo engine needs a rotor layout ('x' or '+'), not 'cylinder'")
    a = airframe
    t_max = a.thrust_to_weight * a.mass * GRAVITY / 4
    fric = _f(friction, 0.005, 0.0001)
    contact = {"condim": 3, "friction": fric, "solref": _f(*solref), "solimp": _f(*solimp)}
    vehicle_default = _attrs(contype=1, conaffinity=0, **contact)
    scene_default = _attrs(contype=0, conaffinity=1, **contact)
    floor = _attrs(
        name="floor",
        type="plane",
        size="0 0 1",
        pos=_f(0, 0, scene.region_min[2]),
        friction=_f(floor_friction, 0.005, 0.0001),
    )
    veh = vehicle_geoms(a)
    motors = []
    for k, (_, _, _, spin) in enumerate(a.rotors()):
        kv = _attrs(
            name=f"motor{k}",
            site=f"rotor{k}",
            gear=_f(0, 0, 1, 0, 0, -spin * a.yaw_moment),
            dyntype="filter",
            dynprm=_f(a.motor_tau),
            gainprm="1",
            biastype="none",
            ctrlrange=_f(0, t_max),
        )
        motors.append(f"    <general {kv}/>")
    option = _attrs(timestep=f"{1.0 / rate:.9g}", gravity=_f(0, 0, -GRAVITY), density=0,
                    viscosity=0)  # fmt: skip
    lines = [
        '<mujoco model="groundstation_quad">',
        '  <compiler angle="radian" autolimits="true" inertiafromgeom="true"/>',
        f"  <option {option}/>",
        "  <default>",
        f'    <default class="vehicle"><geom {vehicle_default}/></default>',
        f'    <default class="scene"><geom {scene_default}/></default>',
        "  </default>",
        "  <worldbody>",
        f'    <geom class="scene" {floor}/>',
        *(f'    <geom class="scene" {g[len("<geom ") :]}' for g in scene_geoms(scene)),
        f'    <body name="quad" pos="{_f(*scene.start)}" childclass="vehicle">',
        '      <freejoint name="root"/>',
        '      <site name="imu" pos="0 0 0" size="0.005"/>',
        *(f"      {xml}" for _, xml in veh),
        *(
            f'      <site name="rotor{k}" pos="{_f(x, y, z)}" size="0.005"/>'
            for k, (x, y, z, _) in enumerate(a.rotors())
        ),
        "    </body>",
        "  </worldbody>",
        "  <actuator>",
        *motors,
        "  </actuator>",
        "  <sensor>",
        '    <accelerometer name="accel" site="imu"/>',
        '    <gyro name="gyro" site="imu"/>',
        "  </sensor>",
        "</mujoco>",
    ]
    return "\n".join(lines) + "\n", [g for g, _ in veh]
