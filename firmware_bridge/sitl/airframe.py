"""The vehicle's body geometry and mass, in one frozen description (pure).

Body frame FLU (x forward, y left, z up), origin at the centre of the arm plane (the point the
mocap tracks and the IMU sits on), metres and kilograms.

Two layouts:

- ``"x"`` / ``"+"``: a quadrotor with four rotors on arms of ``arm_length`` (at 45/135/225/315
  deg from body x for ``"x"``, 0/90/180/270 for ``"+"``), each inside a circular prop guard of
  centreline radius ``guard_radius`` whose rim is a band ``2 guard_tube`` high centred
  ``guard_z`` above the arm plane; a central box of half sizes ``body_half``; four legs from
  the body's bottom corners down to ``leg_length`` below it. The defaults are a 1 kg guarded
  quad whose rim reaches 0.255 m (between two guards) to 0.305 m (along an arm) from the centre.
- ``"cylinder"``: the paper's vertical cylinder of radius ``cylinder_radius`` and height
  ``cylinder_height`` (what the simple engine and the original detector use).

:meth:`Airframe.to_dict` is what the truth records, so a benchmark can configure the detector's
vehicle body as a user would for their drone.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

Vec = tuple[float, float, float]
LAYOUTS = ("x", "+", "cylinder")


@dataclass(frozen=True)
class Airframe:
    """Geometry (m), mass (kg) and rotor constants of the vehicle; see the module docstring."""

    layout: str = "x"
    mass: float = 1.0  # kg, total
    arm_length: float = 0.17  # centre to rotor axis
    guard_radius: float = 0.125  # guard ring centreline radius around each rotor
    guard_tube: float = 0.01  # half the rim band's height (and its thickness), capsule radius
    guard_z: float = 0.0  # rim band centre above the arm plane
    guard_segments: int = 16  # straight capsules per ring (chord sag r (1 - cos(pi/16)): 2.4 mm)
    body_half: Vec = (0.06, 0.04, 0.025)  # central box half sizes
    leg_length: float = 0.08  # from the body's bottom to the foot
    leg_spread: float = 0.03  # foot further out than the leg's top, along the diagonal
    leg_radius: float = 0.005
    rotor_z: float = 0.02  # thrust point above the arm plane
    thrust_to_weight: float = 3.0  # all rotors at full thrust / weight
    yaw_moment: float = 0.016  # m, rotor drag torque per newton of thrust
    motor_tau: float = 0.02  # s, first-order motor (thrust) lag
    # Mass split (kg): the central body takes the rest of ``mass``.
    motor_mass: float = 0.06
    arm_mass: float = 0.02
    guard_mass: float = 0.025
    leg_mass: float = 0.0075
    cylinder_radius: float = 0.2  # layout "cylinder"
    cylinder_height: float = 0.1  # layout "cylinder"

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise ValueError(f"airframe layout {self.layout!r}: use one of {', '.join(LAYOUTS)}")
        if self.body_mass <= 0:
            raise ValueError(f"airframe mass {self.mass} kg is less than its parts")

    @property
    def body_mass(self) -> float:
        """Central body (battery, electronics), kg."""
        parts = 4 * (self.motor_mass + self.arm_mass + self.guard_mass + self.leg_mass)
        return self.mass - (parts if self.layout != "cylinder" else 0.0)

    def rotors(self) -> list[tuple[float, float, float, float]]:
        """(x, y, z, spin) of each rotor; spin +1 turns counter-clockwise seen from above (its
        drag torque on the body is clockwise, -z), -1 clockwise. Diagonal rotors share a spin."""
        off = math.pi / 4 if self.layout == "x" else 0.0
        out = []
        for k in range(4):
            a = off + k * math.pi / 2
            spin = 1.0 if k % 2 == 0 else -1.0
            out.append(
                (self.arm_length * math.cos(a), self.arm_length * math.sin(a), self.rotor_z, spin)
            )
        return out

    def legs(self) -> list[tuple[Vec, Vec]]:
        """(top, foot) of each leg, body frame."""
        hx, hy, hz = self.body_half
        out = []
        for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
            top = (sx * hx * 0.8, sy * hy * 0.8, -hz)
            s = self.leg_spread / math.sqrt(2)
            foot = (top[0] + sx * s, top[1] + sy * s, -hz - self.leg_length)
            out.append((top, foot))
        return out

    def guard_ring(self, rotor: int) -> list[Vec]:
        """Vertices (body frame) of rotor ``rotor``'s rim polygon, the first on the arm's line
        (so the rims reach exactly arm + radius + tube along the arms, and, with a multiple of
        8 segments, exactly between them too)."""
        x, y, _, _ = self.rotors()[rotor]
        phase = math.atan2(y, x)
        n, r = self.guard_segments, self.guard_radius
        return [
            (x + r * math.cos(phase + 2 * math.pi * j / n),
             y + r * math.sin(phase + 2 * math.pi * j / n), self.guard_z)
            for j in range(n)
        ]  # fmt: skip

    def reach(self, azimuth: float) -> float:
        """Horizontal distance (m) from the centre to the body's outline along body-frame
        ``azimuth`` (rad from x): the support function of the rim polygons (capsule chains)
        plus the tube radius, or the cylinder's radius."""
        if self.layout == "cylinder":
            return self.cylinder_radius
        ux, uy = math.cos(azimuth), math.sin(azimuth)
        ring = max(p[0] * ux + p[1] * uy for k in range(4) for p in self.guard_ring(k))
        return ring + self.guard_tube

    @property
    def reach_min(self) -> float:
        """Smallest horizontal reach over all directions (m, sampled every 0.25 deg)."""
        return min(self._reaches())

    @property
    def reach_max(self) -> float:
        """Largest horizontal reach (m): the radius of the cylinder circumscribing the body."""
        return max(self._reaches())

    def _reaches(self) -> list[float]:
        if self.layout == "cylinder":
            return [self.cylinder_radius]
        pts = [p for k in range(4) for p in self.guard_ring(k)]
        out = []
        for a in range(1440):
            ux, uy = math.cos(math.radians(a / 4)), math.sin(math.radians(a / 4))
            out.append(max(p[0] * ux + p[1] * uy for p in pts) + self.guard_tube)
        return out

    @property
    def top(self) -> float:
        """Highest point above the origin (m)."""
        if self.layout == "cylinder":
            return self.cylinder_height / 2
        return max(self.guard_z + self.guard_tube, self.body_half[2])

    @property
    def bottom(self) -> float:
        """Lowest point below the origin (m, positive): the feet, or the cylinder's base."""
        if self.layout == "cylinder":
            return self.cylinder_height / 2
        return self.body_half[2] + self.leg_length + self.leg_radius

    @property
    def planning_height(self) -> float:
        """Height (m) of the origin-centred cylinder that contains the body (for planning)."""
        return 2.0 * max(self.top, self.bottom)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description with the derived extents (the truth's ``airframe``)."""
        if self.layout == "cylinder":
            keys = ("layout", "mass", "cylinder_radius", "cylinder_height")
            d = {k: getattr(self, k) for k in keys}
            d.update(reach_min=self.cylinder_radius, reach_max=self.cylinder_radius)
            d.update(top=self.top, bottom=self.bottom)
            return d
        d = asdict(self)
        del d["cylinder_radius"], d["cylinder_height"]
        d["body_half"] = list(self.body_half)
        d["body_mass"] = self.body_mass
        d["reach_min"] = self.reach_min
        d["reach_max"] = self.reach_max
        d["top"] = self.top
        d["bottom"] = self.bottom
        d["rotors"] = [list(r) for r in self.rotors()]
        d["legs"] = [[list(a), list(b)] for a, b in self.legs()]
        return d


def cylinder_airframe(radius: float, height: float, mass: float) -> Airframe:
    """The paper's cylinder as an :class:`Airframe` (the simple engine's body)."""
    return Airframe(layout="cylinder", mass=mass, cylinder_radius=radius, cylinder_height=height)
