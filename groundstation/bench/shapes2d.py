"""The paper's 2D simulation data: three shapes, their exact signed distances, and the data sets.

Protocol (DESIGN.md §3; Shibata et al., Sec. "simulation"): shapes square, circle and cross
centred at the origin; contact points (y = 0) every 0.01 m along the edges (every 3 degrees on
the circle); internal (y = -1) and external (y = +1) points uniform in [-3, 3]^2, labelled by
inside/outside; each external point is replaced with probability 2 % by an outlier pair (a false
contact y = 0 at that place plus an internal point y = -1 that a detector would emit with it);
n ~ 590 in total.

Choices where the paper is silent (they are printed by the bench too):

* **Shape sizes.** The circle's "every 3 degrees" gives 120 contacts whatever its radius. The
  sizes are chosen so that the square and the cross also get exactly 120 contacts at 0.01 m,
  i.e. every shape has a 1.2 m perimeter and the contact spacing is 0.01 m on all three:
  square of side 0.3 m; Greek cross of overall extent 0.3 m and arm width 0.1 m (five 0.1 m
  squares, twelve 0.1 m edges); circle of radius 1.2 / (2 pi) = 0.191 m.
  This is the only reading in which "every 0.01 m" and n ~ 590 hold for all three shapes with
  the same number of free-space samples: a 1 m square would already carry 400 contacts.
* **Free-space samples.** 460 points uniform in [-3, 3]^2 (about 1 of them falls inside the
  shape), so n = 120 + 460 + (number of outlier pairs, about 9) ~ 589.
* **Outlier pair.** The false contact sits at the replaced external point; its internal point
  is placed at exactly d_in = 0.1 m (the structure's minimum thickness, DESIGN.md §3) in a
  uniformly random direction, as the detector's x_in = x_c - d_in n does for a random normal n.

Everything is deterministic given a ``numpy.random.Generator``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np

from groundstation.errors import ConfigError

#: Half-width of the square, metres (side 0.3 m: 120 contacts at 0.01 m).
SQUARE_HALF = 0.15
#: Circle radius, metres (perimeter 1.2 m, so 3 degrees = 0.01 m of arc).
CIRCLE_RADIUS = 1.2 / (2 * math.pi)
#: Cross: half overall extent and half arm width, metres (extent 0.3 m, arm width 0.1 m).
CROSS_HALF_EXTENT = 0.15
CROSS_HALF_ARM = 0.05
#: Default data-set sizes and rates of the protocol.
CONTACT_SPACING = 0.01
CIRCLE_STEP_DEG = 3.0
N_FREE = 460
REGION_HALF = 3.0
OUTLIER_PROB = 0.02
PAIR_DISTANCE = 0.1

# Codes of Dataset.kind.
CONTACT, INTERNAL, EXTERNAL, FALSE_CONTACT, FALSE_INTERNAL = 0, 1, 2, 3, 4
KIND_NAMES = ("contact", "internal", "external", "false_contact", "false_internal")


def square_sdf(p: np.ndarray, half: float = SQUARE_HALF) -> np.ndarray:
    """Exact signed distance (metres) of (m, 2) points to an origin-centred axis-aligned square."""
    q = np.abs(np.asarray(p, dtype=np.float64)) - half
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    return outside + np.minimum(q.max(axis=1), 0.0)


def circle_sdf(p: np.ndarray, radius: float = CIRCLE_RADIUS) -> np.ndarray:
    """Exact signed distance (metres) of (m, 2) points to an origin-centred circle."""
    return np.linalg.norm(np.asarray(p, dtype=np.float64), axis=1) - radius


def cross_sdf(
    p: np.ndarray, half_extent: float = CROSS_HALF_EXTENT, half_arm: float = CROSS_HALF_ARM
) -> np.ndarray:
    """Exact signed distance (metres) of (m, 2) points to an origin-centred plus-shaped cross.

    The cross is the union of the rectangles |x| <= a, |y| <= b and |x| <= b, |y| <= a
    (a = half_extent, b = half_arm). Exact formula after folding to x >= y >= 0 (I. Quilez,
    "2D distance functions", sdCross with r = 0): q = p - (a, b), k = max(q_x, q_y);
    w = q if k > 0 else (b - p_x, -k); distance = sign(k) * |max(w, 0)|.
    """
    p = np.abs(np.asarray(p, dtype=np.float64))
    swap = p[:, 1] > p[:, 0]
    p = np.where(swap[:, None], p[:, ::-1], p)
    q = p - np.array([half_extent, half_arm])
    k = q.max(axis=1)
    w = np.where((k > 0)[:, None], q, np.stack([half_arm - p[:, 0], -k], axis=1))
    return np.sign(k) * np.linalg.norm(np.maximum(w, 0.0), axis=1)


def _polygon_points(corners: np.ndarray, spacing: float) -> np.ndarray:
    """Points every ``spacing`` metres of arc length around a closed polygon, from corner 0."""
    closed = np.vstack([corners, corners[:1]])
    seg = np.diff(closed, axis=0)
    seg_len = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    n = int(round(cum[-1] / spacing))
    s = np.arange(n) * (cum[-1] / n)
    i = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg) - 1)
    t = (s - cum[i]) / seg_len[i]
    return closed[i] + t[:, None] * seg[i]


@dataclasses.dataclass(frozen=True)
class Shape2D:
    """A 2D test shape centred at the origin.

    Attributes
    ----------
    name : str
    sdf : callable (m, 2) -> (m,)
        Exact signed distance, metres (< 0 inside).
    corners : (c, 2) float64 or None
        Polygon corners (counter-clockwise), None for the circle.
    radius : float
        Circle radius (metres) when ``corners`` is None.
    """

    name: str
    sdf: Callable[[np.ndarray], np.ndarray]
    corners: np.ndarray | None = None
    radius: float = 0.0

    def contacts(self) -> np.ndarray:
        """Contact points of the protocol: (120, 2) float64, metres."""
        if self.corners is None:
            ang = np.deg2rad(np.arange(0.0, 360.0, CIRCLE_STEP_DEG))
            return self.radius * np.stack([np.cos(ang), np.sin(ang)], axis=1)
        return _polygon_points(self.corners, CONTACT_SPACING)

    def boundary(self, spacing: float = 0.002) -> np.ndarray:
        """Dense samples of the true boundary, about ``spacing`` metres apart: (k, 2)."""
        if self.corners is None:
            n = max(8, int(math.ceil(2 * math.pi * self.radius / spacing)))
            ang = np.linspace(0.0, 2 * math.pi, n, endpoint=False)
            return self.radius * np.stack([np.cos(ang), np.sin(ang)], axis=1)
        return _polygon_points(self.corners, spacing)

    def outline(self) -> np.ndarray:
        """Closed polyline of the boundary for plotting: (k, 2), last point = first point."""
        pts = self.boundary(0.005) if self.corners is None else self.corners
        return np.vstack([pts, pts[:1]])


def _cross_corners(a: float, b: float) -> np.ndarray:
    return np.array(
        [[a, -b], [a, b], [b, b], [b, a], [-b, a], [-b, b], [-a, b], [-a, -b], [-b, -b],
         [-b, -a], [b, -a], [b, -b]]
    )  # fmt: skip


def make_shape(name: str) -> Shape2D:
    """One of the paper's shapes by name: ``"square"``, ``"circle"`` or ``"cross"``."""
    h = SQUARE_HALF
    if name == "square":
        corners = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
        return Shape2D("square", square_sdf, corners=corners)
    if name == "circle":
        return Shape2D("circle", circle_sdf, radius=CIRCLE_RADIUS)
    if name == "cross":
        return Shape2D(
            "cross", cross_sdf, corners=_cross_corners(CROSS_HALF_EXTENT, CROSS_HALF_ARM)
        )
    raise ConfigError(f"unknown shape {name!r}", hint="choose square, circle or cross")


SHAPES = ("square", "circle", "cross")


@dataclasses.dataclass(frozen=True)
class Dataset:
    """Training data of one simulated run.

    Attributes
    ----------
    X : (n, 2) float64, metres
    y : (n,) float64 labels in {-1, 0, +1}
    kind : (n,) int8, one of CONTACT, INTERNAL, EXTERNAL, FALSE_CONTACT, FALSE_INTERNAL
    pair : (n,) int64, for FALSE_INTERNAL rows the row index of its false contact, else -1
    """

    X: np.ndarray
    y: np.ndarray
    kind: np.ndarray
    pair: np.ndarray

    @property
    def outlier(self) -> np.ndarray:
        """(n,) bool: the false contacts (the outliers scored by Q)."""
        return self.kind == FALSE_CONTACT

    @property
    def normal(self) -> np.ndarray:
        """(n,) bool: genuine data (neither member of an outlier pair)."""
        return self.kind <= EXTERNAL

    def counts(self) -> dict[str, int]:
        """Number of rows of each kind, by name."""
        return {name: int(np.sum(self.kind == k)) for k, name in enumerate(KIND_NAMES)}


def make_dataset(
    shape: Shape2D,
    rng: np.random.Generator,
    *,
    n_free: int = N_FREE,
    outlier_prob: float = OUTLIER_PROB,
    region_half: float = REGION_HALF,
    pair_distance: float = PAIR_DISTANCE,
) -> Dataset:
    """Draw one data set of the protocol (module docstring).

    Parameters
    ----------
    shape : Shape2D
    rng : numpy.random.Generator
        Source of all randomness (same state, same data).
    n_free : int
        Free-space samples, uniform in ``[-region_half, region_half]^2``.
    outlier_prob : float
        Probability that an external sample is replaced by an outlier pair.
    region_half : float
        Half-width of the square sampling region, metres.
    pair_distance : float
        Distance from a false contact to its internal point, metres.
    """
    if n_free < 0 or not 0.0 <= outlier_prob <= 1.0:
        raise ConfigError(f"n_free {n_free} must be >= 0 and outlier_prob {outlier_prob} in [0, 1]")
    contacts = shape.contacts()
    free = rng.uniform(-region_half, region_half, size=(n_free, 2))
    inside = shape.sdf(free) < 0
    replaced = ~inside & (rng.random(n_free) < outlier_prob)
    ang = rng.uniform(0.0, 2 * math.pi, size=n_free)
    offset = pair_distance * np.stack([np.cos(ang), np.sin(ang)], axis=1)

    X = [contacts]
    kind = [np.full(len(contacts), CONTACT, dtype=np.int8)]
    X.append(free[~replaced])
    kind.append(np.where(inside[~replaced], INTERNAL, EXTERNAL).astype(np.int8))
    n_pairs = int(replaced.sum())
    X.append(free[replaced])
    kind.append(np.full(n_pairs, FALSE_CONTACT, dtype=np.int8))
    X.append(free[replaced] + offset[replaced])
    kind.append(np.full(n_pairs, FALSE_INTERNAL, dtype=np.int8))

    X_all = np.concatenate(X)
    kind_all = np.concatenate(kind)
    y = np.select(
        [kind_all == EXTERNAL, kind_all == INTERNAL, kind_all == FALSE_INTERNAL],
        [1.0, -1.0, -1.0],
        0.0,
    )
    pair = np.full(len(X_all), -1, dtype=np.int64)
    first_false = len(X_all) - 2 * n_pairs
    pair[first_false + n_pairs :] = np.arange(first_false, first_false + n_pairs)
    return Dataset(X=X_all, y=y, kind=kind_all, pair=pair)
