"""Where a drone can fly and touch in a scene: reachability, touch targets, collision-free paths.

For any scene, a touch of every reachable face: for each candidate touch point P with outward
normal n, the drone's centre at contact is C = P + n r (horizontal n) or C = P + n h/2 (vertical
n); the approach starts at a standoff S = C + n d (d = 0.6 m, shortened to >= 0.35 m near the
region's bounds) and is reachable when S lies inside the region, the segment S -> C is clear of
every structure, and the first contact at C is with the target face. Transit between standoffs
is a straight line when clear, else an A* path on a 0.2 m grid. The drone is planned as the
vertical cylinder (radius r, height h) that circumscribes it (pure, deterministic).
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

from firmware_bridge.sitl.physics import contact_penetration
from firmware_bridge.sitl.scene import Scene

Vec = tuple[float, float, float]


@dataclass(frozen=True)
class TouchTarget:
    """A planned touch: face label, contact centre C, outward normal n, standoff S.

    ``direction`` is the unit flight direction of the approach (None: straight in, along -n);
    the drone flies from S along it through C.
    """

    face: tuple[int, str]  # (object index, face name)
    centre: Vec
    normal: Vec
    standoff: Vec
    direction: Vec | None = None


def _add(a: Vec, b: Vec, s: float = 1.0) -> Vec:
    return (a[0] + s * b[0], a[1] + s * b[1], a[2] + s * b[2])


def _dist(a: Vec, b: Vec) -> float:
    return math.dist(a, b)


class Planner:
    """Reachability and collision-free paths for a drone of radius r, height h in a scene."""

    def __init__(self, scene: Scene, radius: float, height: float, margin: float = 0.12):
        self.scene, self.r, self.h, self.margin = scene, radius, height, margin
        lo, hi = scene.region_min, scene.region_max
        self.lo = (lo[0] + radius + 0.1, lo[1] + radius + 0.1, lo[2] + 0.25)
        self.hi = (hi[0] - radius - 0.1, hi[1] - radius - 0.1, hi[2] - height / 2 - 0.05)

    def in_region(self, p: Vec) -> bool:
        return all(self.lo[i] <= p[i] <= self.hi[i] for i in range(3))

    def free(self, p: Vec, margin: float | None = None) -> bool:
        """No structure within ``margin`` of the drone cylinder centred at ``p``."""
        m = self.margin if margin is None else margin
        return contact_penetration(self.scene, p, self.r + m, self.h + 2 * m) is None

    def segment_free(self, a: Vec, b: Vec, margin: float | None = None) -> bool:
        n = max(1, int(math.ceil(_dist(a, b) / 0.05)))
        return all(
            self.free(_add(a, (b[0] - a[0], b[1] - a[1], b[2] - a[2]), k / n), margin)
            for k in range(n + 1)
        )

    def touch_target(self, obj: int, face: str, point: Vec, n: Vec) -> TouchTarget | None:
        """Plan the touch of ``point`` (outward normal ``n``) or None if it is unreachable."""
        off = self.r if abs(n[2]) < 0.5 else self.h / 2
        centre = _add(point, n, off)
        probe = _add(centre, n, -0.01)  # just after first contact
        c = contact_penetration(self.scene, probe, self.r, self.h)
        if c is None or c.object_index != obj:
            return None
        if c.normal[0] * n[0] + c.normal[1] * n[1] + c.normal[2] * n[2] < 0.9:
            return None
        if not (self.lo[2] - 0.1 <= centre[2] <= self.hi[2]):
            return None
        for d in (0.6, 0.5, 0.45, 0.4, 0.35, 0.3):
            s = _add(centre, n, d)
            if not self.in_region(s) or not self.free(s):
                continue
            if self.segment_free(_add(centre, n, 0.03), s, margin=0.02):
                return TouchTarget((obj, face), centre, n, s)
        return None

    def angled(
        self, tgt: TouchTarget, angle: float, azimuth: float, run_ups: tuple[float, ...]
    ) -> TouchTarget | None:
        """``tgt`` approached ``angle`` rad off its normal (tangent direction ``azimuth`` rad in
        the face plane), from the longest clear run-up in ``run_ups`` (m); None if none fits."""
        n = tgt.normal
        t1, t2 = _tangents(n)
        ca, sa = math.cos(angle), math.sin(angle)
        cz, sz = math.cos(azimuth), math.sin(azimuth)
        d = tuple(-ca * n[i] + sa * (cz * t1[i] + sz * t2[i]) for i in range(3))
        for run in run_ups:
            s = _add(tgt.centre, d, -run)  # type: ignore[arg-type]
            if not self.in_region(s) or not self.free(s):
                continue
            if self.segment_free(_add(tgt.centre, d, -0.04), s, margin=0.02):  # type: ignore[arg-type]
                return TouchTarget(tgt.face, tgt.centre, n, s, d)  # type: ignore[arg-type]
        return None

    def path(self, a: Vec, b: Vec) -> list[Vec]:
        """Waypoints from ``a`` to ``b`` (excluding ``a``) avoiding structures; [] if none."""
        if self.segment_free(a, b):
            return [b]
        step = 0.2
        lo = self.lo
        dims = tuple(max(1, int((self.hi[i] - lo[i]) / step) + 1) for i in range(3))

        def cell(p: Vec) -> tuple[int, int, int]:
            return tuple(  # type: ignore[return-value]
                min(dims[i] - 1, max(0, round((p[i] - lo[i]) / step))) for i in range(3)
            )

        def centre(c: tuple[int, int, int]) -> Vec:
            return (lo[0] + c[0] * step, lo[1] + c[1] * step, lo[2] + c[2] * step)

        free_cache: dict[tuple[int, int, int], bool] = {}

        def ok(c: tuple[int, int, int]) -> bool:
            if c not in free_cache:
                free_cache[c] = self.free(centre(c))
            return free_cache[c]

        start, goal = cell(a), cell(b)
        openq = [(0.0, 0.0, start)]
        came: dict[tuple[int, int, int], tuple[int, int, int] | None] = {start: None}
        cost = {start: 0.0}
        nbrs = [
            (i, j, k)
            for i in (-1, 0, 1)
            for j in (-1, 0, 1)
            for k in (-1, 0, 1)
            if (i, j, k) != (0, 0, 0)
        ]
        found = False
        while openq:
            _, g, cur = heapq.heappop(openq)
            if cur == goal:
                found = True
                break
            if g > cost.get(cur, math.inf):
                continue
            for d in nbrs:
                nxt = (cur[0] + d[0], cur[1] + d[1], cur[2] + d[2])
                if not all(0 <= nxt[i] < dims[i] for i in range(3)) or not ok(nxt):
                    continue
                ng = g + step * math.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
                if ng < cost.get(nxt, math.inf):
                    cost[nxt], came[nxt] = ng, cur
                    h = _dist(centre(nxt), centre(goal))
                    heapq.heappush(openq, (ng + h, ng, nxt))
        if not found:
            return []
        cells = []
        c: tuple[int, int, int] | None = goal
        while c is not None:
            cells.append(centre(c))
            c = came[c]
        cells.reverse()
        # Shortcut: keep a waypoint only when the straight line past it is blocked.
        pts = [a] + cells[1:-1] + [b]
        out, anchor, i = [], a, 1
        while i < len(pts):
            j = len(pts) - 1
            while j > i and not self.segment_free(anchor, pts[j]):
                j -= 1
            out.append(pts[j])
            anchor, i = pts[j], j + 1
        return out


def plan_survey(
    scene: Scene, radius: float, height: float, spacing: float = 0.6
) -> list[TouchTarget]:
    """Every reachable touch of every face, ordered greedily by distance from the start."""
    planner = Planner(scene, radius, height)
    targets = []
    for face in scene.faces(step=spacing):
        for p, n in zip(face.points, face.normals, strict=True):
            t = planner.touch_target(face.object_index, face.name, p, n)
            if t is not None:
                targets.append(t)
    ordered, here = [], scene.start
    while targets:
        k = min(range(len(targets)), key=lambda i: _dist(here, targets[i].standoff))
        ordered.append(targets.pop(k))
        here = ordered[-1].standoff
    return ordered


def _tangents(n: Vec) -> tuple[Vec, Vec]:
    """Two unit vectors spanning the plane normal to ``n`` (the first horizontal when it can)."""
    if abs(n[2]) < 0.9:
        h = math.hypot(n[0], n[1])
        t1 = (-n[1] / h, n[0] / h, 0.0)
    else:
        t1 = (1.0, 0.0, 0.0)
    t2 = (
        n[1] * t1[2] - n[2] * t1[1],
        n[2] * t1[0] - n[0] * t1[2],
        n[0] * t1[1] - n[1] * t1[0],
    )
    k = math.sqrt(t2[0] ** 2 + t2[1] ** 2 + t2[2] ** 2)
    return t1, (t2[0] / k, t2[1] / k, t2[2] / k)
