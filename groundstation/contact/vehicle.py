"""The vehicle's body: where on it a contact with a given outward normal happens (pure).

A contact with a structure whose outward normal is ``n`` (world frame) happens at the point of
the body farthest along ``-n``: the body's *support point* in direction ``-n``. For a convex
part that is exact; for a union of parts (four prop guards, legs, the central body) it is the
support point of the union, i.e. of the part that faces the structure. With the vehicle's pose
at the onset of the impulse, that point is where the structure's surface was.

Two shapes (``[vehicle] shape``):

- ``cylinder``: the paper's vertical cylinder of radius ``radius_m`` and height ``height_m``
  circumscribing the drone, axis along world z whatever the attitude (as the paper's rule
  ``x - r n`` / ``x - h n`` assumes). The bundled simple SITL engine collides with exactly this.
- ``guards``: a quadrotor with four prop guards (thin rings of radius ``guard_radius_m`` around
  rotors on arms of ``arm_length_m``, in the body's x-y plane ``guard_z_m`` above the centre of
  mass, ``layout`` "x" or "+"), a central box (``body_half_m``) and legs (vertical segments of
  ``leg_length_m`` below the body at ``leg_offset_m`` from the centre on the arm diagonals). Body
  frame FLU (x forward, y left, z up); the attitude rotates it into the world.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import numpy as np

from groundstation.errors import ConfigError


@dataclasses.dataclass(frozen=True)
class VehicleSettings:
    """Geometry of the vehicle's body (metres, body frame FLU: x forward, y left, z up).

    Attributes
    ----------
    shape : "cylinder" | "guards"
        The paper's circumscribing cylinder, or a guarded quadrotor (module docstring).
    radius_m, height_m : float
        Cylinder radius and height (paper: 0.2 m and 0.1 m).
    layout : "x" | "+"
        Rotor layout of a guarded quadrotor: arms at 45/135/225/315 deg ("x") or along the
        body axes ("+").
    arm_length_m : float
        Centre of mass to rotor axis, metres.
    guard_radius_m : float
        Radius of each prop guard ring (rim distance from the rotor axis), metres.
    guard_z_m : float
        Height of the guard rings' plane above the centre of mass, metres.
    body_half_m : tuple of 3 float
        Half sizes of the central body box, metres.
    leg_length_m : float
        Length of the legs below the body box (0: no legs), metres.
    leg_offset_m : float
        Horizontal distance of the legs from the centre, on the arm directions, metres.
    """

    shape: Literal["cylinder", "guards"] = "cylinder"
    radius_m: float = 0.2
    height_m: float = 0.1
    layout: Literal["x", "+"] = "x"
    arm_length_m: float = 0.17
    guard_radius_m: float = 0.12
    guard_z_m: float = 0.0
    body_half_m: tuple[float, float, float] = (0.06, 0.06, 0.03)
    leg_length_m: float = 0.08
    leg_offset_m: float = 0.08

    def __post_init__(self) -> None:
        if self.shape not in ("cylinder", "guards"):
            raise ConfigError(f"vehicle.shape must be cylinder or guards, got {self.shape!r}")
        if self.layout not in ("x", "+"):
            raise ConfigError(f"vehicle.layout must be x or +, got {self.layout!r}")
        for name in ("radius_m", "height_m", "arm_length_m", "guard_radius_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"vehicle.{name} must be > 0 m, got {getattr(self, name)!r}")
        for name in ("leg_length_m", "leg_offset_m"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"vehicle.{name} must be >= 0 m, got {getattr(self, name)!r}")
        if len(self.body_half_m) != 3 or not all(v > 0 for v in self.body_half_m):
            raise ConfigError(f"vehicle.body_half_m must be 3 sizes > 0, got {self.body_half_m!r}")

    @property
    def reach_m(self) -> float:
        """Largest distance of any body point from the centre of mass, metres."""
        if self.shape == "cylinder":
            return math.hypot(self.radius_m, 0.5 * self.height_m)
        rim = self.arm_length_m + self.guard_radius_m
        bx, by, bz = self.body_half_m
        return max(
            math.hypot(rim, self.guard_z_m),
            math.hypot(math.hypot(bx, by), bz + self.leg_length_m),
        )

    @property
    def inner_radius_m(self) -> float:
        """Radius of the vertical disc round the centre of mass that the body fills whatever
        its yaw, metres: the cylinder's radius; for a guarded quadrotor (props spinning fill
        each guard ring) the reach of the two rings either side of the line half-way between
        two arms, along that line (the rotors lie ``arm_length * sin 45deg`` off it in either
        layout), or the central body's smaller half-width where the rings leave a gap there.
        Farther out, in that direction, lies the gap between two guards: no part of the body.
        (A sliver beside the central body, nearer the centre than the rings reach, counts as
        body: a point there is a few centimetres from the centre of mass.)"""
        if self.shape == "cylinder":
            return self.radius_m
        off = self.arm_length_m * math.sin(math.pi / 4)
        box = min(self.body_half_m[0], self.body_half_m[1])
        if self.guard_radius_m <= off:
            return box
        return max(box, off + math.sqrt(self.guard_radius_m**2 - off**2))

    @property
    def inner_half_height_m(self) -> float:
        """Half the thickness the body has across that disc, metres: the cylinder's half
        height; a guarded quadrotor's central body's (its guards are rings in one plane, its
        legs thin rods)."""
        return 0.5 * self.height_m if self.shape == "cylinder" else self.body_half_m[2]

    def rotor_centres(self) -> np.ndarray:
        """(4, 3) rotor axis points in the guard plane, body FLU, metres."""
        a0 = math.pi / 4 if self.layout == "x" else 0.0
        ang = a0 + np.arange(4) * math.pi / 2
        L = self.arm_length_m
        return np.stack([L * np.cos(ang), L * np.sin(ang), np.full(4, self.guard_z_m)], axis=1)

    def leg_points(self) -> np.ndarray:
        """(8, 3) end points of the legs (top and bottom of each), body FLU, metres."""
        if self.leg_length_m <= 0:
            return np.zeros((0, 3))
        a0 = math.pi / 4
        ang = a0 + np.arange(4) * math.pi / 2
        d = self.leg_offset_m
        top = -self.body_half_m[2]
        pts = []
        for a in ang:
            x, y = d * math.cos(a), d * math.sin(a)
            pts += [(x, y, top), (x, y, top - self.leg_length_m)]
        return np.asarray(pts, dtype=np.float64)


def _support_guards(v: VehicleSettings, d: np.ndarray) -> np.ndarray:
    """Support points of the guarded body in body directions ``d`` (k, 3) unit, FLU: (k, 3).

    Candidates in order: each guard ring's farthest point along ``d``, the body box's corner,
    the leg ends; the first of the farthest wins (a tie between two rings keeps the first)."""
    dxy = d * np.array([1.0, 1.0, 0.0])
    nxy = np.linalg.norm(dxy, axis=1, keepdims=True)
    ring = np.where(nxy > 1e-9, v.guard_radius_m * dxy / np.maximum(nxy, 1e-12), 0.0)
    rings = v.rotor_centres()[None, :, :] + ring[:, None, :]  # (k, 4, 3)
    corner = np.copysign(np.asarray(v.body_half_m, dtype=np.float64), d)[:, None, :]
    legs = np.broadcast_to(v.leg_points()[None], (d.shape[0], *v.leg_points().shape))
    cand = np.concatenate([rings, corner, legs], axis=1)
    best = np.argmax(np.einsum("kcj,kj->kc", cand, d), axis=1)
    return cand[np.arange(d.shape[0]), best]


def _support_cylinder(v: VehicleSettings, d: np.ndarray) -> np.ndarray:
    """Support points of the world-vertical cylinder in world directions ``d`` (k, 3) unit."""
    nxy = np.hypot(d[:, 0], d[:, 1])[:, None]
    # a face-on vertical direction touches the flat end anywhere: take its centre
    ring = np.where(
        nxy > 1e-9, d * np.array([1.0, 1.0, 0.0]) * v.radius_m / np.maximum(nxy, 1e-12), 0.0
    )
    ring[:, 2] = 0.5 * v.height_m * np.sign(d[:, 2])
    return ring


#: Directions averaged over the cap of the normal's uncertainty (``contact_offset``).
CAP_DIRECTIONS = 64
_GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


def cap_directions(d: np.ndarray, half_angle_rad: float, k: int = CAP_DIRECTIONS) -> np.ndarray:
    """(k, 3) unit directions uniform by solid angle over the cap of ``half_angle_rad`` around
    the unit vector ``d`` (a Fibonacci spiral: deterministic, evenly spread)."""
    i = np.arange(k) + 0.5
    cos_a = 1.0 - (1.0 - math.cos(half_angle_rad)) * i / k
    sin_a = np.sqrt(np.maximum(0.0, 1.0 - cos_a * cos_a))
    phi = i * _GOLDEN_ANGLE
    a = np.array([1.0, 0.0, 0.0]) if abs(d[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(d, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    return (
        cos_a[:, None] * d[None, :]
        + (sin_a * np.cos(phi))[:, None] * e1[None, :]
        + (sin_a * np.sin(phi))[:, None] * e2[None, :]
    )


def contact_offset(
    v: VehicleSettings,
    normal_world: np.ndarray,
    r_world_body: np.ndarray,
    spread_rad: float = 0.0,
) -> np.ndarray:
    """Offset (world, metres) from the centre of mass to the body point that touches a surface
    with outward normal ``normal_world``.

    Where the body is flat facing the structure (the cylinder's side facing a wall, its end
    facing a floor, two guard rings side by side facing a wall) every point of that flat part
    touches, and the support point of the exact direction jumps from one end to the other
    with the normal's smallest tilt: a wall touch by the cylinder lands on its top or bottom
    rim (0.05 m off), a floor touch on its rim (0.2 m off), a wall touch between two guards on
    one of them (0.12 m off). With ``spread_rad`` > 0 the offset is the mean of the support
    points over every direction within that angle of the normal (the uncertainty of the
    measured normal): the middle of the flat part, which lies on a flat structure, and on a
    curved part a few millimetres inside its rim.

    Parameters
    ----------
    v : VehicleSettings
    normal_world : (3,) float64
        Outward unit normal of the structure, world frame (ENU).
    r_world_body : (3, 3) float64
        Rotation body FLU -> world ENU at the time of the contact.
    spread_rad : float
        Half angle of the cone of directions averaged, radians (0: the exact support point).

    Returns
    -------
    (3,) float64, metres, world frame
    """
    d_world = -np.asarray(normal_world, dtype=np.float64)
    d_world = d_world / max(float(np.linalg.norm(d_world)), 1e-12)
    dirs = d_world[None, :] if spread_rad <= 0.0 else cap_directions(d_world, spread_rad)
    if v.shape == "cylinder":
        return _support_cylinder(v, dirs).mean(axis=0)
    R = np.asarray(r_world_body, dtype=np.float64)
    return R @ _support_guards(v, dirs @ R).mean(axis=0)


def paper_offset(normal_world: np.ndarray, radius_m: float, height_m: float) -> np.ndarray:
    """The paper's rule: ``-r n`` when the horizontal part of n dominates, else ``-h n``."""
    n = np.asarray(normal_world, dtype=np.float64)
    horizontal = math.hypot(n[0], n[1]) >= abs(n[2])
    return -(radius_m if horizontal else height_m) * n
