"""Gusts: random-direction force pulses that the contact detector mistakes for touches.

Arrivals are a Poisson process (``rate_per_min``); each gust is a half-sine pulse of specific
force a(t) = peak * sin(pi (t - t0) / T) along a random unit direction (uniform azimuth,
elevation within +-``max_elevation``). With the defaults (peak 2.5-4 G, T = 40-60 ms,
elevation within 20 deg) the 50 ms moving average of | |a| - 1 G | exceeds the detector's
0.6 G (>= 0.68 G over 84 gusts in 3 seeds): each gust is a false positive.

Real wind is weaker and slower (5-40 N on a 1 kg vehicle, 50-300 ms): ``peak_min``/``peak_max``
and ``duration_min``/``duration_max`` set the ranges. Real gusts also come in bursts: with
probability ``cluster_probability`` a gust starts a *cluster* of ``cluster_size`` gusts (drawn
uniformly, the first included) that follow each other ``cluster_gap`` seconds apart (end to
start) from about the same direction (azimuth within +-``cluster_spread``), so a hovering
vehicle is hit several times within a few seconds at one spot. Clustering draws no random
numbers when ``cluster_probability`` is 0 (the default), so default runs are unchanged.

Gusts that fall due while the vehicle is near a structure are postponed until it is clear, so
every gust in the ground truth is unambiguous.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from firmware_bridge.sitl.physics import GRAVITY


@dataclass(frozen=True)
class GustParams:
    rate_per_min: float = 3.0
    peak_min: float = 2.5 * GRAVITY  # m/s^2 (specific force: force / vehicle mass)
    peak_max: float = 4.0 * GRAVITY  # m/s^2
    duration_min: float = 0.04  # s
    duration_max: float = 0.06  # s
    max_elevation: float = math.radians(20.0)
    clearance: float = 0.7  # m, postpone while closer than this to a structure
    cluster_probability: float = 0.0  # probability that a gust starts a cluster
    cluster_size: tuple[int, int] = (3, 5)  # gusts per cluster (inclusive range, first included)
    cluster_gap: tuple[float, float] = (0.2, 1.0)  # s from the end of one gust to the next
    cluster_spread: float = math.radians(30.0)  # azimuth spread around the cluster's direction

    @classmethod
    def from_forces(
        cls,
        mass: float,
        force: tuple[float, float] | None = None,
        duration: tuple[float, float] | None = None,
        **kwargs: object,
    ) -> GustParams:
        """Gust settings with peak forces in newtons on a vehicle of ``mass`` kg.

        ``force`` (N) and ``duration`` (s) are (min, max) ranges, None keeps the default;
        ``kwargs`` are other fields (``rate_per_min``, ``cluster_probability``, ...).
        """
        p = cls(**kwargs)  # type: ignore[arg-type]
        if force is not None:
            p = replace(p, peak_min=force[0] / mass, peak_max=force[1] / mass)
        if duration is not None:
            p = replace(p, duration_min=duration[0], duration_max=duration[1])
        return p


@dataclass
class Gust:
    """One gust: start time (s), duration (s), peak specific force (m/s^2), unit direction.

    ``peak_force_n`` is the peak force in newtons (``peak`` times the vehicle mass), ``end`` the
    end time (s), ``cluster`` the id of the cluster it belongs to (None for an isolated gust).
    """

    start: float
    duration: float
    peak: float
    direction: tuple[float, float, float]
    position: tuple[float, float, float] | None = None  # where the vehicle was when it began
    end: float = math.nan
    peak_force_n: float = math.nan  # N
    cluster: int | None = None

    def accel(self, t: float) -> float:
        """Specific-force magnitude at time ``t`` (0 outside the pulse)."""
        u = (t - self.start) / self.duration
        return self.peak * math.sin(math.pi * u) if 0.0 <= u <= 1.0 else 0.0


class GustSchedule:
    """Draws gusts in time order; :meth:`force` gives the gust specific force at time t.

    Parameters
    ----------
    params : GustParams
    rng : numpy Generator (all draws come from it, in time order).
    mass : kg, converts the specific force to newtons for the record.
    """

    def __init__(self, params: GustParams, rng: np.random.Generator, mass: float = 1.0):
        self.p = params
        self.rng = rng
        self.mass = mass
        self.active: Gust | None = None
        self.history: list[Gust] = []
        self.next_time = self._draw_gap(0.0)
        self.clusters = 0
        self._cluster_left = 0  # gusts still to come in the current cluster
        self._cluster_azimuth = 0.0

    def _draw_gap(self, t: float) -> float:
        if self.p.rate_per_min <= 0:
            return math.inf
        return t + float(self.rng.exponential(60.0 / self.p.rate_per_min))

    def _new_gust(self, t: float, position: tuple[float, float, float]) -> Gust:
        p = self.p
        in_cluster = self._cluster_left > 0
        az = float(self.rng.uniform(0, 2 * math.pi))
        if in_cluster:  # same wind: the cluster's azimuth, spread by a fraction of the draw
            az = self._cluster_azimuth + p.cluster_spread * (az / math.pi - 1.0)
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
        g.end = g.start + g.duration
        g.peak_force_n = g.peak * self.mass
        if in_cluster:
            self._cluster_left -= 1
            g.cluster = self.clusters - 1
        elif p.cluster_probability > 0 and float(self.rng.random()) < p.cluster_probability:
            lo, hi = p.cluster_size
            self._cluster_left = int(self.rng.integers(lo, hi + 1)) - 1
            self._cluster_azimuth = az
            g.cluster = self.clusters
            self.clusters += 1
        return g

    def force(
        self, t: float, clearance: float, position: tuple[float, float, float]
    ) -> tuple[float, float, float]:
        """Gust specific force (m/s^2, world) at ``t``; ``clearance`` = distance to structures."""
        if self.active is None and t >= self.next_time:
            if clearance < self.p.clearance:
                self.next_time = t + 0.25  # postpone until clear of structures
            else:
                g = self._new_gust(t, position)
                self.active = g
                self.history.append(g)
        g = self.active
        if g is None:
            return (0.0, 0.0, 0.0)
        if t > g.start + g.duration:
            self.active = None
            if self._cluster_left > 0:
                self.next_time = t + float(self.rng.uniform(*self.p.cluster_gap))
            else:
                self.next_time = self._draw_gap(t)
            return (0.0, 0.0, 0.0)
        a = g.accel(t)
        return (a * g.direction[0], a * g.direction[1], a * g.direction[2])
