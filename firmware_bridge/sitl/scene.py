"""Scenes: structures (boxes, vertical cylinders, spheres) inside an exploration region.

World frame = the scene's frame: metres, x and y horizontal, z up (treated as ENU). A scene file is
JSON::

    {"region": {"min": [x, y, z], "max": [x, y, z]},
     "objects": [{"type": "box", "min": [..], "max": [..]},
                 {"type": "cylinder", "center": [x, y, z_base], "radius": r, "height": h},
                 {"type": "sphere", "center": [x, y, z], "radius": r}],
     "start": [x, y, z]}            # optional: where the vehicle hovers at t = 0

Every primitive gives its signed distance, closest surface point and outward normal, and its
*faces* (patches with one outward normal that a pilot can touch). Boxes and vertical cylinders are
products of a 2-D set and a z interval, so the distance from the drone's vertical cylinder
(radius r, height h) splits exactly into a horizontal and a vertical part (see
:func:`firmware_bridge.sitl.physics.contact_penetration`).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from firmware_bridge.errors import BridgeError

Vec = tuple[float, float, float]


class SceneError(BridgeError, ValueError):
    """A scene file is missing, malformed, or names an impossible geometry."""


@dataclass(frozen=True)
class Face:
    """A flat (or lateral) patch of one object that can be touched.

    ``points`` are candidate touch points on the surface, (k, 3) metres, with their outward
    ``normals`` (k, 3), unit vectors.
    """

    object_index: int
    name: str
    points: tuple[Vec, ...]
    normals: tuple[Vec, ...]


def _vec3(value: Any, where: str) -> Vec:
    if not isinstance(value, list | tuple) or len(value) != 3:
        raise SceneError(f"{where}: expected a list of 3 numbers, got {value!r}")
    out = []
    for i, v in enumerate(value):
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise SceneError(f"{where}[{i}]: expected a finite number, got {v!r}")
        out.append(float(v))
    return (out[0], out[1], out[2])


def _positive(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise SceneError(f"{where}: expected a finite number, got {value!r}")
    if value <= 0:
        raise SceneError(f"{where}: must be > 0 m, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class Box:
    """Axis-aligned box, ``min`` and ``max`` corners in metres."""

    min: Vec
    max: Vec

    def closest(self, p: Vec) -> tuple[float, Vec, Vec]:
        """Signed distance (m, < 0 inside), closest surface point and outward normal at ``p``."""
        lo, hi = self.min, self.max
        c = [min(max(p[i], lo[i]), hi[i]) for i in range(3)]
        d = [p[i] - c[i] for i in range(3)]
        dist = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        if dist > 0.0:
            return dist, (c[0], c[1], c[2]), (d[0] / dist, d[1] / dist, d[2] / dist)
        # Inside: push out through the nearest face.
        best, axis, sign = math.inf, 0, 1.0
        for i in range(3):
            for s, gap in ((-1.0, p[i] - lo[i]), (1.0, hi[i] - p[i])):
                if gap < best:
                    best, axis, sign = gap, i, s
        q = list(p)
        q[axis] = hi[axis] if sign > 0 else lo[axis]
        n = [0.0, 0.0, 0.0]
        n[axis] = sign
        return -best, (q[0], q[1], q[2]), (n[0], n[1], n[2])

    def signed_distances(self, points: np.ndarray) -> np.ndarray:
        """:meth:`closest`'s signed distance of each of (n, 3) ``points``, vectorised."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        lo, hi = np.array(self.min), np.array(self.max)
        out = np.linalg.norm(p - np.clip(p, lo, hi), axis=1)
        inside = out == 0.0
        gaps = np.minimum(p[inside] - lo, hi - p[inside]).min(axis=1)
        out[inside] = -gaps
        return out

    def faces(self, index: int, step: float) -> list[Face]:
        """Six faces with a grid of touch points each (``step`` metres apart, >= 1 per face)."""
        out = []
        for axis in range(3):
            u, v = [a for a in range(3) if a != axis]
            for sign, name in ((-1.0, "min"), (1.0, "max")):
                pts = []
                for a in _spread(self.min[u], self.max[u], step):
                    for b in _spread(self.min[v], self.max[v], step):
                        q = [0.0, 0.0, 0.0]
                        q[axis] = self.max[axis] if sign > 0 else self.min[axis]
                        q[u], q[v] = a, b
                        pts.append((q[0], q[1], q[2]))
                n = [0.0, 0.0, 0.0]
                n[axis] = sign
                label = f"{'xyz'[axis]}{name}"
                out.append(Face(index, label, tuple(pts), tuple([(n[0], n[1], n[2])] * len(pts))))
        return out

    @property
    def area(self) -> float:
        """Surface area, square metres."""
        e = [self.max[i] - self.min[i] for i in range(3)]
        return 2.0 * (e[0] * e[1] + e[0] * e[2] + e[1] * e[2])

    def holds(self, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """(n,) whether each of (n, 3) ``points`` lies inside the box or on its surface."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        return np.all((p >= np.array(self.min) - tol) & (p <= np.array(self.max) + tol), axis=1)

    def area_points(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` points uniform on the surface (area-weighted), (n, 3) metres."""
        lo, hi = np.array(self.min), np.array(self.max)
        ext = hi - lo
        areas = np.array([ext[1] * ext[2], ext[0] * ext[2], ext[0] * ext[1]] * 2)
        faces = rng.choice(6, size=n, p=areas / areas.sum())
        pts = lo + rng.random((n, 3)) * ext
        axis = faces % 3
        pts[np.arange(n), axis] = np.where(faces < 3, lo[axis], hi[axis])
        return pts


@dataclass(frozen=True)
class Cylinder:
    """Vertical cylinder: base centre ``center`` (m), ``radius`` and ``height`` (m)."""

    center: Vec
    radius: float
    height: float

    def closest(self, p: Vec) -> tuple[float, Vec, Vec]:
        """Signed distance (m), closest surface point and outward normal at ``p``."""
        cx, cy, z0 = self.center
        z1 = z0 + self.height
        dx, dy = p[0] - cx, p[1] - cy
        rho = math.hypot(dx, dy)
        ux, uy = (dx / rho, dy / rho) if rho > 1e-12 else (1.0, 0.0)
        # Closest point of the product set (disk x [z0, z1]).
        cr = min(rho, self.radius)
        cz = min(max(p[2], z0), z1)
        qx, qy = cx + ux * cr, cy + uy * cr
        ex, ey, ez = p[0] - qx, p[1] - qy, p[2] - cz
        dist = math.sqrt(ex * ex + ey * ey + ez * ez)
        # Outside unless in the product set: inside, p - q is rounding noise (1e-17 m), not 0.
        if dist > 0.0 and (rho > self.radius or cz != p[2]):
            return dist, (qx, qy, cz), (ex / dist, ey / dist, ez / dist)
        gap_side, gap_top, gap_bot = self.radius - rho, z1 - p[2], p[2] - z0
        best = min(gap_side, gap_top, gap_bot)
        if best == gap_side:
            return -best, (cx + ux * self.radius, cy + uy * self.radius, p[2]), (ux, uy, 0.0)
        if best == gap_top:
            return -best, (p[0], p[1], z1), (0.0, 0.0, 1.0)
        return -best, (p[0], p[1], z0), (0.0, 0.0, -1.0)

    def signed_distances(self, points: np.ndarray) -> np.ndarray:
        """:meth:`closest`'s signed distance of each of (n, 3) ``points``, vectorised."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        cx, cy, z0 = self.center
        z1 = z0 + self.height
        rho = np.hypot(p[:, 0] - cx, p[:, 1] - cy)
        out = np.hypot(np.maximum(rho - self.radius, 0.0), p[:, 2] - np.clip(p[:, 2], z0, z1))
        inside = out == 0.0
        gaps = np.minimum(
            self.radius - rho[inside], np.minimum(z1 - p[inside, 2], p[inside, 2] - z0)
        )
        out[inside] = -gaps
        return out

    def faces(self, index: int, step: float) -> list[Face]:
        """Lateral surface (touch points around it), top and bottom discs."""
        cx, cy, z0 = self.center
        n_az = max(4, int(math.ceil(2 * math.pi * self.radius / step)))
        side_pts, side_n = [], []
        for k in range(n_az):
            a = 2 * math.pi * k / n_az
            for z in _spread(z0, z0 + self.height, step):
                side_pts.append((cx + self.radius * math.cos(a), cy + self.radius * math.sin(a), z))
                side_n.append((math.cos(a), math.sin(a), 0.0))
        disc = [(cx, cy)] + [
            (cx + 0.5 * self.radius * math.cos(a), cy + 0.5 * self.radius * math.sin(a))
            for a in (0.0, math.pi)
        ]
        top = tuple((x, y, z0 + self.height) for x, y in disc)
        bot = tuple((x, y, z0) for x, y in disc)
        return [
            Face(index, "side", tuple(side_pts), tuple(side_n)),
            Face(index, "top", top, ((0.0, 0.0, 1.0),) * len(top)),
            Face(index, "bottom", bot, ((0.0, 0.0, -1.0),) * len(bot)),
        ]

    @property
    def area(self) -> float:
        """Surface area (side and both discs), square metres."""
        return 2.0 * math.pi * self.radius * (self.height + self.radius)

    def holds(self, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """(n,) whether each of (n, 3) ``points`` lies inside the cylinder or on its surface."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        cx, cy, z0 = self.center
        rho = np.hypot(p[:, 0] - cx, p[:, 1] - cy)
        top = z0 + self.height
        return (rho <= self.radius + tol) & (p[:, 2] >= z0 - tol) & (p[:, 2] <= top + tol)

    def area_points(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` points uniform on the surface (area-weighted), (n, 3) metres."""
        r, h = self.radius, self.height
        areas = np.array([2 * math.pi * r * h, math.pi * r * r, math.pi * r * r])
        part = rng.choice(3, size=n, p=areas / areas.sum())
        a = rng.random(n) * 2 * math.pi
        rad = np.where(part == 0, r, r * np.sqrt(rng.random(n)))
        z = np.where(part == 0, rng.random(n) * h, np.where(part == 1, h, 0.0))
        c = np.array(self.center)
        return np.column_stack([rad * np.cos(a), rad * np.sin(a), z]) + c


@dataclass(frozen=True)
class Sphere:
    """Sphere: ``center`` and ``radius`` in metres."""

    center: Vec
    radius: float

    def closest(self, p: Vec) -> tuple[float, Vec, Vec]:
        """Signed distance (m), closest surface point and outward normal at ``p``."""
        d = [p[i] - self.center[i] for i in range(3)]
        rho = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        n = (d[0] / rho, d[1] / rho, d[2] / rho) if rho > 1e-12 else (0.0, 0.0, 1.0)
        q = tuple(self.center[i] + self.radius * n[i] for i in range(3))
        return rho - self.radius, (q[0], q[1], q[2]), n

    def signed_distances(self, points: np.ndarray) -> np.ndarray:
        """:meth:`closest`'s signed distance of each of (n, 3) ``points``, vectorised."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        return np.linalg.norm(p - np.array(self.center), axis=1) - self.radius

    def faces(self, index: int, step: float) -> list[Face]:
        """Eight touch directions around the equator, four at 45 degrees up, and the top."""
        dirs = []
        for el, count in ((0.0, 8), (math.pi / 4, 4), (math.pi / 2, 1)):
            for k in range(count):
                a = 2 * math.pi * k / count
                dirs.append((math.cos(el) * math.cos(a), math.cos(el) * math.sin(a), math.sin(el)))
        dirs.append((0.0, 0.0, -1.0))
        pts = tuple(tuple(self.center[i] + self.radius * d[i] for i in range(3)) for d in dirs)
        return [Face(index, "surface", pts, tuple(dirs))]  # type: ignore[arg-type]

    @property
    def area(self) -> float:
        """Surface area, square metres."""
        return 4.0 * math.pi * self.radius**2

    def holds(self, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """(n,) whether each of (n, 3) ``points`` lies inside the sphere or on its surface."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        return np.linalg.norm(p - np.array(self.center), axis=1) <= self.radius + tol

    def area_points(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` points uniform on the sphere, (n, 3) metres."""
        d = rng.standard_normal((n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return np.array(self.center) + self.radius * d


Primitive = Box | Cylinder | Sphere


def _spread(lo: float, hi: float, step: float) -> list[float]:
    """Centres of about ``span / step`` equal parts of [lo, hi] (at least one point)."""
    span = hi - lo
    k = max(1, int(span // step))
    return [lo + span * (0.5 + i) / k if k > 1 else lo + 0.5 * span for i in range(k)]


@dataclass(frozen=True)
class Scene:
    """Exploration region (axis-aligned box, m) plus the structures inside it."""

    region_min: Vec
    region_max: Vec
    objects: tuple[Primitive, ...]
    start: Vec
    name: str = "scene"
    source: dict = field(default_factory=dict, compare=False)

    def closest(self, p: Vec) -> tuple[float, Vec, Vec, int]:
        """Nearest structure to ``p``: (signed distance m, surface point, normal, object index).

        Index is -1 with an infinite distance when the scene has no objects.
        """
        best: tuple[float, Vec, Vec, int] = (math.inf, p, (0.0, 0.0, 1.0), -1)
        for i, obj in enumerate(self.objects):
            d, q, n = obj.closest(p)
            if d < best[0]:
                best = (d, q, n, i)
        return best

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distance to the union of structures, (n, 3) -> (n,) metres (< 0 inside)."""
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        out = np.full(len(pts), np.inf)
        for obj in self.objects:
            np.minimum(out, obj.signed_distances(pts), out=out)
        return out

    def inside_region(self, p: Vec, margin: float = 0.0) -> bool:
        """Whether ``p`` lies inside the region shrunk by ``margin`` metres."""
        return all(
            self.region_min[i] + margin <= p[i] <= self.region_max[i] - margin for i in range(3)
        )

    def faces(self, step: float = 0.5) -> list[Face]:
        """Every face of every object (reachable or not), touch points ``step`` m apart."""
        out: list[Face] = []
        for i, obj in enumerate(self.objects):
            out.extend(obj.faces(i, step))
        return out

    def exposed_area(self, rng: np.random.Generator, n: int = 20_000) -> float:
        """Area of the surface that exists (:meth:`sample_surface`'s), m²: every primitive's
        area times the share of ``n`` points drawn on them by area that are exposed (not on
        the floor, not inside or against another structure). Monte Carlo: its relative error
        is about ``sqrt(hidden share / n)``, under 1 % at the default ``n``."""
        if not self.objects or n <= 0:
            return 0.0
        areas = np.array([o.area for o in self.objects])
        counts = rng.multinomial(n, areas / areas.sum())
        kept = sum(
            int(self._exposed(i, obj.area_points(rng, int(m))).sum())
            for i, (obj, m) in enumerate(zip(self.objects, counts, strict=True))
        )
        return float(areas.sum()) * kept / n

    def _exposed(self, i: int, p: np.ndarray) -> np.ndarray:
        """(k,) bool: points ``p`` on object ``i`` that are surface that exists: above the
        floor and not inside or against another structure."""
        keep = p[:, 2] > float(self.region_min[2]) + 1e-9
        for j, other in enumerate(self.objects):
            if j != i:
                keep &= ~other.holds(p)
        return keep

    def sample_surface(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` ground-truth points uniform by area on the surface that exists, (n, 3) metres.

        That is the boundary of the union of the structures: a face resting on the floor (the
        region's bottom) or lying inside or against another structure (a pillar's top under a
        deck, the deck's underside over it) is no surface a vehicle can touch or a map can draw.
        Sampled by rejection from every primitive in proportion to its area; empty when there
        are no structures or nothing of them is exposed.
        """
        if not self.objects or n <= 0:
            return np.zeros((0, 3))
        areas = np.array([o.area for o in self.objects])
        out: list[np.ndarray] = []
        have = 0
        for _ in range(32):  # each round keeps the exposed share of 2x what is still missing
            counts = rng.multinomial(2 * (n - have) + 16, areas / areas.sum())
            for i, (obj, m) in enumerate(zip(self.objects, counts, strict=True)):
                p = obj.area_points(rng, int(m))
                keep = self._exposed(i, p)
                out.append(p[keep])
                have += int(keep.sum())
            if have >= n:
                break
        pts = np.concatenate(out)
        return pts[rng.permutation(len(pts))[:n]]

    def to_dict(self) -> dict:
        """The scene as the JSON structure it was loaded from (normalized)."""
        objs: list[dict] = []
        for o in self.objects:
            if isinstance(o, Box):
                objs.append({"type": "box", "min": list(o.min), "max": list(o.max)})
            elif isinstance(o, Cylinder):
                objs.append(
                    {
                        "type": "cylinder",
                        "center": list(o.center),
                        "radius": o.radius,
                        "height": o.height,
                    }
                )
            else:
                objs.append({"type": "sphere", "center": list(o.center), "radius": o.radius})
        return {
            "name": self.name,
            "region": {"min": list(self.region_min), "max": list(self.region_max)},
            "objects": objs,
            "start": list(self.start),
        }


def parse_scene(data: Any, name: str = "scene") -> Scene:
    """Validate a scene's JSON structure; errors name the bad field (``objects[2].radius``)."""
    if not isinstance(data, dict):
        raise SceneError(f"scene {name!r}: expected a JSON object, got {type(data).__name__}")
    region = data.get("region")
    if not isinstance(region, dict):
        raise SceneError("region: missing or not an object with 'min' and 'max'")
    rmin, rmax = _vec3(region.get("min"), "region.min"), _vec3(region.get("max"), "region.max")
    for i in range(3):
        if rmax[i] - rmin[i] < 0.5:
            raise SceneError(
                f"region.max[{i}]: must exceed region.min[{i}] by at least 0.5 m "
                f"(got {rmin[i]} .. {rmax[i]})"
            )
    raw_objects = data.get("objects", [])
    if not isinstance(raw_objects, list):
        raise SceneError(f"objects: expected a list, got {type(raw_objects).__name__}")
    objects: list[Primitive] = []
    for k, o in enumerate(raw_objects):
        where = f"objects[{k}]"
        if not isinstance(o, dict):
            raise SceneError(f"{where}: expected an object, got {o!r}")
        kind = o.get("type")
        if kind == "box":
            lo, hi = _vec3(o.get("min"), f"{where}.min"), _vec3(o.get("max"), f"{where}.max")
            for i in range(3):
                if hi[i] <= lo[i]:
                    raise SceneError(f"{where}.max[{i}]: must exceed min[{i}] ({lo[i]} >= {hi[i]})")
            objects.append(Box(lo, hi))
        elif kind == "cylinder":
            c = _vec3(o.get("center"), f"{where}.center")
            r = _positive(o.get("radius"), f"{where}.radius")
            h = _positive(o.get("height"), f"{where}.height")
            objects.append(Cylinder(c, r, h))
        elif kind == "sphere":
            c = _vec3(o.get("center"), f"{where}.center")
            objects.append(Sphere(c, _positive(o.get("radius"), f"{where}.radius")))
        else:
            raise SceneError(
                f"{where}.type: unknown primitive {kind!r}",
                hint="use 'box', 'cylinder' or 'sphere'",
            )
    if "start" in data:
        start = _vec3(data["start"], "start")
    else:
        start = (
            rmin[0] + 0.5,
            rmin[1] + 0.5,
            min(rmin[2] + 1.0, 0.5 * (rmin[2] + rmax[2])),
        )
    scene = Scene(rmin, rmax, tuple(objects), start, name, dict(data))
    if not scene.inside_region(start):
        raise SceneError(f"start: {list(start)} lies outside the region")
    if scene.closest(start)[0] < 0.35:
        raise SceneError(f"start: {list(start)} is inside or within 0.35 m of a structure")
    return scene


def named_scenes() -> list[str]:
    """Names of the scenes shipped with the package (``firmware_bridge/sitl/scenes/*.json``)."""
    folder = resources.files("firmware_bridge.sitl") / "scenes"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".json"))


def load_scene(name_or_path: str | Path) -> Scene:
    """Load a named scene (``wall``, ``pillar``, ``pier``, ``paper``) or a JSON file path."""
    text = str(name_or_path)
    if text in named_scenes():
        ref = resources.files("firmware_bridge.sitl") / "scenes" / f"{text}.json"
        raw, label = ref.read_text(encoding="utf-8"), text
    else:
        path = Path(text)
        if not path.is_file():
            raise SceneError(
                f"scene {text!r}: no such named scene or file",
                hint=f"named scenes: {', '.join(named_scenes())}",
            )
        raw, label = path.read_text(encoding="utf-8"), path.stem
    try:
        data = json.loads(raw)
    except json.JSONDecodeError as exc:
        raise SceneError(f"scene {text!r}: invalid JSON at line {exc.lineno}: {exc.msg}") from None
    return parse_scene(data, name=label)
