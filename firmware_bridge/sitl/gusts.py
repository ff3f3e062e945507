"""Gusts: random-direction force pulses that the contact detector mistakes for touches.

Arrivals are a Poisson process (``rate_per_min``); each gust is a half-sine pulse of specific
force a(t) = peak * sin(pi (t - t0) / T) along a random unit direction (uniform azimuth,
elevation within +-``max_elevation``). With the defaults (peak 2.5-4 G, T = 40-60 ms,
elevation within 20 deg) the 50 ms moving average of | |a| - 1 G | exceeds the detector's
0.6 G (>= 0.68 G over 84 gusts in 3 seeds): each gust is a false positive.
Gusts that fall due while the vehicle is near a structure are postponed until it is clear, so
every gust in the ground truth is unambiguous.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from firmware_bridge.sitl.physics import GRAVITY


@dataclass(frozen=True)
class GustParams:
    rate_per_min: float = 3.0
    peak_min: float = 2.5 * GRAVITY  # m/s^2
    peak_max: float = 4.0 * GRAVITY  # m/s^2
    duration_min: float = 0.04  # s
    duration_max: float = 0.06  # s
    max_elevation: float = math.radians(20.0)
    clearance: float = 0.7  # m, postpone while closer than this to a structure


@dataclass
class Gust:
    """One gust: start time (s), duration (s), peak specific force (m/s^2), unit direction."""

    start: float
    duration: float
    peak: float
    direction: tuple[float, float, float]
    position: tuple[float, float, float] | None = None  # where the vehicle was when it began

    def accel(self, t: float) -> float:
        """Specific-force magnitude at time ``t`` (0 outside the pulse)."""
        u = (t - self.start) / self.duration
        return self.peak * math.sin(math.pi * u) if 0.0 <= u <= 1.0 else 0.0


class GustSchedule:
    """Draws gusts in time order; :meth:`force` gives the gust specific force at time t."""

    def __init__(self, params: GustParams, rng: np.random.Generator):
        self.p = params
        self.rng = rng
        self.active: Gust | None = None
        self.history: list[Gust] = []
        self.next_time = self._draw_gap(0.0)

    def _draw_gap(self, t: float) -> float:
        if self.p.rate_per_min <= 0:
            return math.inf
        return t + float(self.rng.exponential(60.0 / self.p.rate_per_min))

    def force(
        self, t: float, clearance: float, position: tuple[float, float, float]
    ) -> tuple[float, float, float]:
        """Gust specific force (m/s^2, world) at ``t``; ``clearance`` = distance to structures."""
        if self.active is None and t >= self.next_time:
            if clearance < self.p.clearance:
                self.next_time = t + 0.25  # postpone until clear of structures
            else:
                p = self.p
                az = float(self.rng.uniform(0, 2 * math.pi))
                el = float(self.rng.uniform(-p.max_elevation, p.max_elevation))
                g = Gust(
                    start=t,
                    duration=float(self.rng.uniform(p.duration_min, p.duration_max)),
                    peak=float(self.rng.uniform(p.peak_min, p.peak_max)),
                    direction=(
                        math.cos(el) * math.cos(az),
                        math.cos(el) * math.sin(az),
                        math.sin(el),
                    ),
                    position=position,
                )
                self.active = g
                self.history.append(g)
        g = self.active
        if g is None:
            return (0.0, 0.0, 0.0)
        if t > g.start + g.duration:
            self.active = None
            self.next_time = self._draw_gap(t)
            return (0.0, 0.0, 0.0)
        a = g.accel(t)
        return (a * g.direction[0], a * g.direction[1], a * g.direction[2])
