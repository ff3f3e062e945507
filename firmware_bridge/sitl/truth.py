"""Ground truth: every contact the simulation produced, and the truth sidecar document.

A contact event opens when the drone's body first overlaps a structure (or the floor) and
closes when it has been clear for ``merge_gap`` seconds. Its kind is ``touch`` when the normal
impact speed is >= ``slow_speed`` (the detector should see it), ``slow_touch`` below (it should
not), ``ground`` for the floor (landing); gusts are events of kind ``gust`` with no contact point.

What a detector benchmark scores by, per contact (all at the first step in contact unless said):

- ``normal_speed`` (m/s): the vehicle's speed towards the surface, -v . n, just before the
  contact began; ``approach_speed``: |v|; ``approach_angle_deg``: the angle between the flight
  direction and the inward normal (0 = straight in). ``impact_speed``, the original key, is
  -v . n (clipped at 0) after the first step in contact, so a little lower.
- ``onset_point``: the true contact point on the structure's surface, ``onset_normal`` the
  outward normal there, ``onset_position`` the vehicle's position; ``point``/``normal``/
  ``vehicle_position`` are the same at the deepest penetration (original keys).
- ``body_part`` (``cylinder`` | ``guard`` | ``arm`` | ``body`` | ``leg``), ``body_geom`` and
  ``body_point``: where on the body it touched, body frame FLU, metres from the body origin.
- ``rebound_speed`` (m/s, v . n at the step the body comes free; negative if it did not move
  away) and ``restitution`` = rebound / normal speed.
- ``gust``: the index of a gust that blew up to 0.5 s before the onset (it may have pushed the
  vehicle into the structure), else None.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

from firmware_bridge.sitl.gusts import Gust
from firmware_bridge.sitl.physics import GRAVITY

Vec = tuple[float, float, float]
GUST_AFTERMATH = 0.5  # s after a gust in which a contact is attributed to it


@dataclass
class ContactEvent:
    """One contact: times in s, point/normal/position in m (world ENU), accelerations m/s^2."""

    kind: str
    start: float
    end: float
    object_index: int | None
    point: Vec | None
    normal: Vec
    vehicle_position: Vec
    impact_speed: float
    peak_accel: float
    max_depth: float = 0.0
    normal_speed: float | None = None
    approach_speed: float | None = None
    approach_angle_deg: float | None = None
    onset_point: Vec | None = None
    onset_normal: Vec | None = None
    onset_position: Vec | None = None
    body_part: str | None = None
    body_geom: str | None = None
    body_point: Vec | None = None
    rebound_speed: float | None = None
    restitution: float | None = None
    peak_force_n: float | None = None  # gusts: peak force, N
    cluster: int | None = None  # gusts: cluster id (None: isolated)
    gust: int | None = None  # contacts: index of a gust active up to 0.5 s before the onset

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["peak_accel_g"] = self.peak_accel / GRAVITY
        d["duration"] = self.end - self.start
        return d


def _body_frame(body, world: Vec) -> Vec:
    """``world`` point (m) in the body frame (FLU, relative to the origin)."""
    R = body.rotation()
    d = (world[0] - body.x, world[1] - body.y, world[2] - body.z)
    return (
        R[0] * d[0] + R[3] * d[1] + R[6] * d[2],
        R[1] * d[0] + R[4] * d[1] + R[7] * d[2],
        R[2] * d[0] + R[5] * d[1] + R[8] * d[2],
    )


@dataclass
class ContactTracker:
    """Opens and closes :class:`ContactEvent` from the body's per-step contact state."""

    slow_speed: float = 0.3  # m/s
    merge_gap: float = 0.05  # s
    events: list[ContactEvent] = field(default_factory=list)
    _open: ContactEvent | None = None
    _last_seen: float = 0.0
    _free: bool = True  # the open event's body has come free since its last contact step
    _v: tuple[float, float, float] = (0.0, 0.0, 0.0)  # velocity after the previous step

    def update(self, t: float, body) -> None:
        """Record the contact state after the physics step that ended at time ``t`` (s).

        ``body`` is any :class:`~firmware_bridge.sitl.engine.Physics`.
        """
        c = body.contact
        ev = self._open
        v_before, self._v = self._v, (body.vx, body.vy, body.vz)
        if c is None:
            if ev is not None and not self._free:  # the first step free: the rebound
                self._free = True
                n = ev.onset_normal or ev.normal
                rebound = body.vx * n[0] + body.vy * n[1] + body.vz * n[2]
                ev.rebound_speed = rebound
                vn = ev.normal_speed or 0.0
                ev.restitution = rebound / vn if vn > 0.05 else None
            if ev is not None and t - self._last_seen >= self.merge_gap:
                ev.end = self._last_seen
                self._open = None
            return
        self._free = False
        obj = c.object_index
        if ev is None or ev.object_index != (obj if obj >= 0 else None):
            if ev is not None:
                ev.end = self._last_seen
            n = c.normal
            speed = -(body.vx * n[0] + body.vy * n[1] + body.vz * n[2])
            kind = "ground" if obj < 0 else ("touch" if speed >= self.slow_speed else "slow_touch")
            # Approach: the velocity just before the step in which the contact began (a soft
            # contact's damping already acts within its first step).
            vn = -(v_before[0] * n[0] + v_before[1] * n[1] + v_before[2] * n[2])
            v = math.sqrt(v_before[0] ** 2 + v_before[1] ** 2 + v_before[2] ** 2)
            cos = vn / v if v > 1e-9 else 1.0
            ev = ContactEvent(
                kind,
                t,
                t,
                obj if obj >= 0 else None,
                c.point,
                c.normal,
                body.position,
                max(0.0, speed),
                0.0,
                normal_speed=vn,
                approach_speed=v,
                approach_angle_deg=math.degrees(math.acos(max(-1.0, min(1.0, cos)))),
                onset_point=c.point,
                onset_normal=c.normal,
                onset_position=body.position,
                body_part=c.part,
                body_geom=c.geom,
                body_point=_body_frame(body, c.point),
            )
            self.events.append(ev)
            self._open = ev
        self._last_seen = t
        ev.end = t
        if body.contact_accel > ev.peak_accel:
            ev.peak_accel = body.contact_accel
        if c.depth > ev.max_depth:
            ev.max_depth, ev.point, ev.normal = c.depth, c.point, c.normal
            ev.vehicle_position = body.position

    def all_events(self, gusts: list[Gust]) -> list[ContactEvent]:
        """Contact events and gusts, in start-time order.

        A contact that begins while a gust blows or within ``GUST_AFTERMATH`` seconds after it
        carries that gust's index in ``gust`` (a strong gust can push the vehicle into a
        structure: such a touch is real, but not one the pilot made).
        """
        out = list(self.events)
        for e in out:
            for k, g in enumerate(gusts):
                if g.start <= e.start <= g.start + g.duration + GUST_AFTERMATH:
                    e.gust = k
        for g in gusts:
            out.append(
                ContactEvent(
                    "gust",
                    g.start,
                    g.start + g.duration,
                    None,
                    None,
                    g.direction,
                    g.position or (math.nan,) * 3,
                    0.0,
                    g.peak,
                    peak_force_n=g.peak_force_n,
                    cluster=g.cluster,
                )
            )
        return sorted(out, key=lambda e: e.start)


def truth_document(
    scene: dict,
    vehicle: dict,
    seed: int,
    events: list[ContactEvent],
    gusts: list[Gust],
    settings: dict,
    duration: float,
    physics: dict | None = None,
    airframe: dict | None = None,
    maneuvers: list[dict] | None = None,
) -> dict[str, Any]:
    """The JSON-ready truth sidecar (schema ``sitl-truth/1``; later keys are additions).

    ``physics`` names the engine and its contact settings, ``airframe`` the body
    (:meth:`~firmware_bridge.sitl.airframe.Airframe.to_dict`), ``maneuvers`` the free flight's
    accelerate / turn / brake intervals with their peak accelerations.
    """
    doc = {
        "schema": "sitl-truth/1",
        "frame": "world ENU (x, y horizontal, z up), metres, seconds of simulation time",
        "seed": seed,
        "duration": duration,
        "scene": scene,
        "vehicle": vehicle,
        "settings": settings,
        "contacts": [e.to_dict() for e in events],
        "gusts": [asdict(g) for g in gusts],
    }
    if physics is not None:
        doc["physics"] = physics
    if airframe is not None:
        doc["airframe"] = airframe
    if maneuvers is not None:
        doc["maneuvers"] = maneuvers
    return doc
