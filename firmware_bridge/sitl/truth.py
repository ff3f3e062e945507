"""Ground truth: every contact the simulation produced, and the truth sidecar document.

A contact event opens when the drone's cylinder first overlaps a structure (or the floor) and
closes when it has been clear for ``merge_gap`` seconds. Its kind is ``touch`` when the normal
impact speed is >= ``slow_speed`` (the detector should see it), ``slow_touch`` below (it should
not), ``ground`` for the floor (landing); gusts are events of kind ``gust`` with no contact point.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

from firmware_bridge.sitl.gusts import Gust
from firmware_bridge.sitl.physics import GRAVITY, QuadBody


@dataclass
class ContactEvent:
    """One contact: times in s, point/normal/position in m (world ENU), accelerations m/s^2."""

    kind: str
    start: float
    end: float
    object_index: int | None
    point: tuple[float, float, float] | None
    normal: tuple[float, float, float]
    vehicle_position: tuple[float, float, float]
    impact_speed: float
    peak_accel: float
    max_depth: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["peak_accel_g"] = self.peak_accel / GRAVITY
        return d


@dataclass
class ContactTracker:
    """Opens and closes :class:`ContactEvent` from the body's per-step contact state."""

    slow_speed: float = 0.3  # m/s
    merge_gap: float = 0.05  # s
    events: list[ContactEvent] = field(default_factory=list)
    _open: ContactEvent | None = None
    _last_seen: float = 0.0

    def update(self, t: float, body: QuadBody) -> None:
        """Record the contact state after the physics step that ended at time ``t`` (s)."""
        c = body.contact
        ev = self._open
        if c is None:
            if ev is not None and t - self._last_seen >= self.merge_gap:
                ev.end = self._last_seen
                self._open = None
            return
        obj = c.object_index
        if ev is None or ev.object_index != (obj if obj >= 0 else None):
            if ev is not None:
                ev.end = self._last_seen
            speed = -(body.vx * c.normal[0] + body.vy * c.normal[1] + body.vz * c.normal[2])
            kind = "ground" if obj < 0 else ("touch" if speed >= self.slow_speed else "slow_touch")
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
        """Contact events and gusts, in start-time order."""
        out = list(self.events)
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
) -> dict[str, Any]:
    """The JSON-ready truth sidecar (schema ``sitl-truth/1``)."""
    return {
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
