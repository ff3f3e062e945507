"""3D synthetic observation sets and sessions with ground truth (pure, seeded).

Two generators, both built on a named SITL scene (``firmware_bridge.sitl.scene``) for geometry
and truth, and both emitting observations as the contact detector would (DESIGN.md §3): a
contact ``x_c`` (y = 0) on a reachable face with ~1.5 cm noise, an internal point
``x_c - d_in n`` (y = -1, d_in = 0.1 m) with every contact, external points (y = +1) at the
drone's position while it is not in contact, and false contacts (a gust: y = 0 in free space plus
its internal point 0.1 m behind along the gust's "normal").

* :func:`paper3d` - the paper-like set: the 8 x 4 x 2 m region, n ~ 2,700 (1,100 contacts in
  short sliding strokes, 1,100 internal points, 450 external points, 2 % false-contact pairs).
* :func:`session40` - a 40-minute flight: strokes at 25 Hz while sliding along faces (heavy
  near-duplicates), external points at 0.5 Hz in free flight, gust clusters of 5-50 consecutive
  false contacts; ~6e4 raw observations in time order. The first pass touches every face patch
  once (``covered_s``); later passes revisit random patches, so the structure stops growing.

Ground truth is the scene's signed distance (:func:`scene_sdf`, vectorised) and dense samples of
the surface that exists (``truth_samples``: the union's boundary, without faces on the region
floor or against another structure). Reachable faces: every box/cylinder face except a bottom
face standing on the floor.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from firmware_bridge.sitl.scene import Box, Cylinder, Scene, load_scene
from groundstation.bench.shapes2d import (
    CONTACT,
    EXTERNAL,
    FALSE_CONTACT,
    FALSE_INTERNAL,
    INTERNAL,
    KIND_NAMES,
)
from groundstation.errors import ConfigError

D_IN = 0.1  # internal point depth behind a contact, metres (DESIGN.md §3)
DRONE_RADIUS = 0.2  # drone centre to contact distance, metres (external points stay beyond it)
CONTACT_HZ = 25.0  # contact logging rate (DESIGN.md §3)
EXTERNAL_HZ = 0.5  # external point sampling rate (DESIGN.md §3)


@dataclasses.dataclass(frozen=True)
class ObservationSet3D:
    """Observations with ground truth, in time order.

    Attributes
    ----------
    X : (n, 3) float64, metres
    y : (n,) float64, labels in {-1, 0, +1}
    kind : (n,) int8, ``shapes2d`` kind codes (CONTACT, INTERNAL, EXTERNAL, FALSE_*)
    ids : (n,) int64, observation ids (0..n-1 in emission order)
    t_ns : (n,) int64, emission time, ns since the session start
    scene : Scene
    truth_samples : (k, 3) float64, dense samples of the reachable true surface, metres
    covered_s : float
        Session time (s) when every reachable face patch had been touched once.
    name : str
    event : (n,) int64 or None
        Contact event of each contact and internal row (a stroke, one gust), -1 for external
        rows; None when the generator has no events.
    normals : (n, 3) float64 or None
        The detector's outward normal of each contact and internal row (zeros for external).
    cluster : (n,) bool or None
        Rows of false contacts that belong to a gust cluster (several gusts at one spot).
    touched : (k, 3) float64 or None
        True contact points of the genuine touches (where the surface was touched).
    placement_m : float
        Std (m) of the contact placement noise, which the observations carry as the detector's
        placement uncertainty ``sigma_m`` (the impulse detector reports one per contact); NaN:
        none reported.
    """

    X: np.ndarray
    y: np.ndarray
    kind: np.ndarray
    ids: np.ndarray
    t_ns: np.ndarray
    scene: Scene
    truth_samples: np.ndarray
    covered_s: float
    name: str
    event: np.ndarray | None = None
    normals: np.ndarray | None = None
    cluster: np.ndarray | None = None
    touched: np.ndarray | None = None
    placement_m: float = math.nan

    @property
    def outlier(self) -> np.ndarray:
        """(n,) bool: the false contacts (scored by Q)."""
        return self.kind == FALSE_CONTACT

    @property
    def normal(self) -> np.ndarray:
        """(n,) bool: genuine observations (neither member of a false pair)."""
        return self.kind <= EXTERNAL

    def counts(self) -> dict[str, int]:
        """Rows of each kind, by name."""
        return {name: int(np.sum(self.kind == k)) for k, name in enumerate(KIND_NAMES)}

    def sdf(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (m, < 0 inside) of (m, 3) points to the scene's structures."""
        return scene_sdf(self.scene, points)

    def _rows(self, sel) -> ObservationSet3D:
        def cut(a):
            return None if a is None else a[sel]

        return dataclasses.replace(
            self, X=self.X[sel], y=self.y[sel], kind=self.kind[sel], ids=self.ids[sel],
            t_ns=self.t_ns[sel], event=cut(self.event), normals=cut(self.normals),
            cluster=cut(self.cluster),
        )  # fmt: skip

    def upto(self, t_s: float) -> ObservationSet3D:
        """The observations emitted up to session time ``t_s`` seconds (a prefix)."""
        k = int(np.searchsorted(self.t_ns, int(t_s * 1e9), side="right"))
        return self._rows(slice(0, k))

    def clean(self) -> ObservationSet3D:
        """The clean control: the same set without its false contacts and their internal
        points (accuracy that comes from smoothing shows up as no gap to it)."""
        return self._rows(self.kind <= EXTERNAL)

    def observations(self, p_false: np.ndarray | None = None) -> list:
        """The rows as detector :class:`~groundstation.contact.detector.Observation` records
        (``p_false``: an optional (n,) prior per row; NaN: none)."""
        from groundstation.contact.detector import Observation

        ev = self.event if self.event is not None else np.where(self.y > 0, -1, self.ids)
        nrm = self.normals if self.normals is not None else np.zeros_like(self.X)
        pf = np.full(len(self.y), np.nan) if p_false is None else p_false
        sig = self.placement_m
        return [
            Observation(
                int(i),
                int(t),
                x,
                float(y),
                n,
                int(e),
                0.0,
                p_false=float(p),
                sigma_m=sig if y <= 0 else math.nan,
            )
            for i, t, x, y, n, e, p in zip(
                self.ids, self.t_ns, self.X, self.y, nrm, ev, pf, strict=True
            )
        ]


# --------------------------------------------------------------------------- geometry


def _box_sdf(p: np.ndarray, b: Box) -> np.ndarray:
    lo, hi = np.asarray(b.min), np.asarray(b.max)
    q = np.abs(p - 0.5 * (lo + hi)) - 0.5 * (hi - lo)
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def _cylinder_sdf(p: np.ndarray, c: Cylinder) -> np.ndarray:
    cx, cy, z0 = c.center
    rho = np.hypot(p[:, 0] - cx, p[:, 1] - cy)
    q = np.stack([rho - c.radius, np.abs(p[:, 2] - (z0 + 0.5 * c.height)) - 0.5 * c.height], 1)
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0)


def scene_sdf(scene: Scene, points: np.ndarray) -> np.ndarray:
    """Vectorised signed distance to the union of the scene's objects, (m, 3) -> (m,) metres.

    Exact for each primitive (box and capped vertical cylinder formulas); the union is the
    minimum, exact outside and for disjoint objects. Equals ``Scene.signed_distance``.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.full(p.shape[0], np.inf)
    for obj in scene.objects:
        if isinstance(obj, Box):
            d = _box_sdf(p, obj)
        elif isinstance(obj, Cylinder):
            d = _cylinder_sdf(p, obj)
        else:
            d = np.linalg.norm(p - np.asarray(obj.center), axis=1) - obj.radius
        np.minimum(out, d, out=out)
    return out


def _on_floor(scene: Scene, obj, face_name: str) -> bool:
    z_floor = scene.region_min[2]
    if isinstance(obj, Box):
        return face_name == "zmin" and abs(obj.min[2] - z_floor) < 1e-9
    if isinstance(obj, Cylinder):
        return face_name == "bottom" and abs(obj.center[2] - z_floor) < 1e-9
    return False


def reachable_patches(scene: Scene, step: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Touch patches of the reachable faces: centres (P, 3) and outward normals (P, 3), metres."""
    pts, nrm = [], []
    for face in scene.faces(step):
        if _on_floor(scene, scene.objects[face.object_index], face.name):
            continue
        pts.extend(face.points)
        nrm.extend(face.normals)
    if not pts:
        raise ConfigError(f"scene {scene.name!r} has no reachable face to touch")
    return np.asarray(pts, dtype=np.float64), np.asarray(nrm, dtype=np.float64)


def truth_samples(scene: Scene, rng: np.random.Generator, n: int = 20000) -> np.ndarray:
    """``n`` points uniform (by area) on the true surface that exists, (n, 3) metres: the
    union's boundary without the floor faces (``Scene.sample_surface``, the same truth the
    session scores use)."""
    return scene.sample_surface(rng, n)


def _project(scene: Scene, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest surface points and outward normals of (m, 3) points (``Scene.closest``)."""
    q, n = np.empty_like(pts), np.empty_like(pts)
    for i, p in enumerate(pts):
        _, qi, ni, _ = scene.closest((float(p[0]), float(p[1]), float(p[2])))
        q[i], n[i] = qi, ni
    return q, n


def _tangent(normal: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    v = rng.standard_normal(3)
    v -= normal * (v @ normal)
    nv = np.linalg.norm(v)
    return v / nv if nv > 1e-9 else np.array([1.0, 0.0, 0.0])


def _stroke(
    scene: Scene,
    start: np.ndarray,
    normal: np.ndarray,
    n_pts: int,
    speed: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """True contact points and normals of a slide along a face at ``speed`` m/s, 25 Hz."""
    s = np.arange(n_pts) * (speed / CONTACT_HZ)
    line = start + s[:, None] * _tangent(normal, rng)
    return _project(scene, line)


def _free_points(
    scene: Scene, rng: np.random.Generator, n: int, near: np.ndarray | None = None
) -> np.ndarray:
    """``n`` drone positions in free space (>= DRONE_RADIUS + 0.1 m from every structure).

    With ``near`` (k, 3), points are drawn within ~1.2 m of those points (where the drone flies
    while working the structure); otherwise uniform in the region.
    """
    lo, hi = np.asarray(scene.region_min), np.asarray(scene.region_max)
    out: list[np.ndarray] = []
    have = 0
    while have < n:
        m = 2 * (n - have) + 16
        if near is None:
            cand = lo + rng.random((m, 3)) * (hi - lo)
        else:
            base = near[rng.integers(0, near.shape[0], m)]
            cand = base + rng.normal(0.0, 0.6, (m, 3))
        ok = np.all((cand >= lo) & (cand <= hi), axis=1)
        cand = cand[ok]
        cand = cand[scene_sdf(scene, cand) >= DRONE_RADIUS + 0.1]
        out.append(cand[: n - have])
        have += out[-1].shape[0]
    return np.concatenate(out)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _contact_rows(
    true_pts: np.ndarray, normals: np.ndarray, rng: np.random.Generator, noise: float
) -> tuple[np.ndarray, np.ndarray]:
    """Detector output for touches at ``true_pts``: noisy contacts and their internal points."""
    xc = true_pts + rng.normal(0.0, noise, true_pts.shape)
    # The detector's normal comes from the acceleration direction: a few degrees off.
    n_est = _unit(normals + rng.normal(0.0, 0.05, normals.shape))
    return xc, xc - D_IN * n_est


def _gust_rows(
    centre: np.ndarray, count: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """A gust: ``count`` false contacts around one drone position plus their internal points."""
    n_gust = _unit(rng.standard_normal(3))
    drift = np.cumsum(rng.normal(0.0, 0.004, (count, 3)), axis=0)  # the drone barely moves
    xc = centre - DRONE_RADIUS * n_gust + drift
    return xc, xc - D_IN * n_gust


def _load(scene: Scene | str) -> Scene:
    return scene if isinstance(scene, Scene) else load_scene(scene)


# --------------------------------------------------------------------------- generators


def paper3d(
    seed: int = 0,
    *,
    scene: Scene | str = "paper",
    n_contacts: int = 900,
    n_external: int = 450,
    false_rate: float = 0.02,
    clusters: int = 3,
    cluster_size: tuple[int, int] = (6, 10),
    stroke_len: int = 10,
    noise: float = 0.01,
    n_truth: int = 20000,
) -> ObservationSet3D:
    """The paper-like 3D observation set (n ~ 2,300 with the defaults), in time order.

    The drone flies from patch to patch of the reachable faces and slides a short stroke on each
    (``stroke_len`` contacts at 25 Hz at 0.25 m/s, one contact event per stroke, each contact
    with its internal point and the detector's normal). External points are its positions in free
    flight: half along the approach paths near the structure, half anywhere in the region. False
    contacts: isolated gusts (``false_rate`` per genuine contact, one event each, at a drone
    position in free space near the structure, with the drone's path through that position as
    external points, as the detector emits them) and ``clusters`` gust clusters: 6-10 gusts
    0.5 s apart pushing a hovering drone at one spot (one event each, a burst in time and space;
    the hover position is an external point before and after).

    Parameters
    ----------
    seed : int
        Seed of all randomness.
    scene : Scene or name
        Structure (default the SITL ``paper`` scene: a box and a pillar in 8 x 4 x 2 m).
    n_contacts : int
        Genuine contacts.
    n_external : int
        External (free-space) points.
    false_rate : float
        Isolated false-contact pairs per genuine contact (paper: 2 %).
    clusters : int
        Gust clusters.
    cluster_size : (int, int)
        Gusts per cluster, inclusive range.
    stroke_len : int
        Contacts per stroke.
    noise : float
        Contact position noise (std per axis), metres.
    n_truth : int
        Dense ground-truth surface samples.
    """
    if n_contacts < 1 or n_external < 0 or not 0.0 <= false_rate <= 1.0 or stroke_len < 1:
        raise ConfigError(
            f"paper3d: n_contacts={n_contacts} (>= 1), n_external={n_external} (>= 0), "
            f"false_rate={false_rate} (0..1), stroke_len={stroke_len} (>= 1)"
        )
    sc = _load(scene)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 3]))
    centres, normals = reachable_patches(sc, 0.5)
    n_strokes = math.ceil(n_contacts / stroke_len)
    order = np.concatenate(
        [rng.permutation(len(centres)) for _ in range(math.ceil(n_strokes / len(centres)))]
    )[:n_strokes]
    rows: list[tuple] = []  # (t_s, X (k,3), kind, event, normals (k,3), cluster)
    touched = []
    t, event, prev = 0.0, 0, np.asarray(sc.start, dtype=np.float64)
    n_near = n_external // 2
    left = n_contacts
    for s, k in enumerate(order):
        start = centres[k] + _jitter_in_plane(normals[k], rng, 0.25)
        p_true, n_true = _stroke(sc, start, normals[k], min(stroke_len, left), 0.25, rng)
        left -= p_true.shape[0]
        standoff = p_true[0] + (DRONE_RADIUS + 0.1) * n_true[0]
        # the approach: free points along the path from the last standoff
        m = n_near // n_strokes + (1 if s < n_near % n_strokes else 0)
        if m:
            frac = (np.arange(m) + 1.0) / (m + 1.0)
            path = prev + frac[:, None] * (standoff - prev) + rng.normal(0.0, 0.1, (m, 3))
            path = _push_out(sc, path)
            rows.append((t + frac * 2.0, path, EXTERNAL, -1, np.zeros_like(path), False))
        t += 2.0
        xc, xin = _contact_rows(p_true, n_true, rng, noise)
        n_est = _unit(xc - xin)
        tt = t + np.arange(len(xc)) / CONTACT_HZ
        rows.append((tt, xc, CONTACT, event, n_est, False))
        rows.append((tt, xin, INTERNAL, event, n_est, False))
        touched.append(p_true)
        event += 1
        t = tt[-1] + 1.0 / CONTACT_HZ
        prev = p_true[-1] + (DRONE_RADIUS + 0.1) * n_true[-1]
    t_end = t
    near = np.concatenate(touched)
    uniform = _free_points(sc, rng, n_external - n_near)
    rows.append((rng.uniform(0.0, t_end, len(uniform)), uniform, EXTERNAL, -1,
                 np.zeros_like(uniform), False))  # fmt: skip
    stand = np.concatenate([r[1] for r in rows if r[2] == EXTERNAL])
    n_false = int(rng.binomial(n_contacts, false_rate)) if false_rate > 0 else 0
    for c in _free_points(sc, rng, n_false, near=near):
        fc, fi = _gust_rows(c, 1, rng)
        tg = np.full(1, rng.uniform(0.0, t_end))
        nn = _unit(fc - fi)
        rows.append((tg, fc, FALSE_CONTACT, event, nn, False))
        rows.append((tg, fi, FALSE_INTERNAL, event, nn, False))
        # the drone flew through where the gust hit it: its path there is free space
        path = _push_out(sc, c + np.linspace(-0.3, 0.3, 7)[:, None] * _unit(rng.standard_normal(3)))
        rows.append((tg[0] + np.linspace(-0.6, 0.6, 7), path, EXTERNAL, -1,
                     np.zeros_like(path), False))  # fmt: skip
        event += 1
    for _ in range(clusters):
        size = int(rng.integers(cluster_size[0], cluster_size[1] + 1))
        where = stand[rng.integers(0, len(stand))]  # the drone hovers where it flew
        fc, fi = _gust_rows(where, size, rng)
        tg = rng.uniform(0.0, t_end) + 0.5 * np.arange(size)
        nn = _unit(fc - fi)
        hover = where[None, :] + rng.normal(0.0, 0.02, (2, 3))  # the hover position, sampled
        rows.append((tg[[0, -1]] + [-1.0, 1.0], hover, EXTERNAL, -1, np.zeros_like(hover), False))
        for j in range(size):
            rows.append((tg[j : j + 1], fc[j : j + 1], FALSE_CONTACT, event, nn[j : j + 1], True))
            rows.append((tg[j : j + 1], fi[j : j + 1], FALSE_INTERNAL, event, nn[j : j + 1], True))
            event += 1
    t_s = np.concatenate([np.broadcast_to(r[0], (len(r[1]),)) for r in rows])
    X = np.concatenate([r[1] for r in rows])
    kind = np.concatenate([np.full(len(r[1]), r[2], dtype=np.int8) for r in rows])
    ev = np.concatenate([np.full(len(r[1]), r[3], dtype=np.int64) for r in rows])
    nrm = np.concatenate([r[4] for r in rows])
    clu = np.concatenate([np.full(len(r[1]), r[5], dtype=bool) for r in rows])
    o = np.argsort(t_s, kind="stable")
    return ObservationSet3D(
        X=X[o],
        y=_labels(kind[o]),
        kind=kind[o],
        ids=np.arange(len(X), dtype=np.int64),
        t_ns=np.round(t_s[o] * 1e9).astype(np.int64),
        scene=sc,
        truth_samples=truth_samples(sc, rng, n_truth),
        covered_s=float(t_end),
        name="paper3d",
        event=ev[o],
        normals=nrm[o],
        cluster=clu[o],
        touched=np.concatenate(touched),
        placement_m=float(noise),
    )


def _jitter_in_plane(normal: np.ndarray, rng: np.random.Generator, scale: float) -> np.ndarray:
    return _tangent(normal, rng) * rng.uniform(0.0, scale)


def _labels(kind: np.ndarray) -> np.ndarray:
    return np.select(
        [kind == EXTERNAL, (kind == INTERNAL) | (kind == FALSE_INTERNAL)], [1.0, -1.0], 0.0
    )


def session40(
    seed: int = 0,
    *,
    scene: Scene | str = "paper",
    duration_s: float = 2400.0,
    contact_fraction: float = 0.5,
    gusts_per_min: float = 1.0,
    noise: float = 0.015,
    n_truth: int = 20000,
) -> ObservationSet3D:
    """A simulated flight session: ~6e4 raw observations over 40 minutes, in time order.

    The pilot alternates free flight and slides along faces. Strokes last 2-6 s at 0.1-0.3 m/s
    (25 Hz contacts, each with its internal point), so consecutive contacts are 4-12 mm apart.
    The first pass visits every reachable 0.5 m face patch once in random order (its end is
    ``covered_s``); later strokes revisit random patches. Free flight between strokes emits
    external points at 0.5 Hz near the structure, and gusts (Poisson, ``gusts_per_min``) emit
    5-50 consecutive false contacts at 25 Hz at one drone position.

    Parameters
    ----------
    seed : int
    scene : Scene or name
    duration_s : float
        Session length, seconds.
    contact_fraction : float
        Fraction of the time spent sliding along a face (0.5 gives ~6e4 rows in 40 min).
    gusts_per_min : float
        Gust clusters per minute of free flight.
    noise : float
        Contact position noise (std per axis), metres.
    n_truth : int
    """
    if not (duration_s > 0 and 0.0 < contact_fraction < 1.0 and gusts_per_min >= 0):
        raise ConfigError(
            f"session40: duration_s={duration_s} (> 0), contact_fraction={contact_fraction} "
            f"(0..1 exclusive), gusts_per_min={gusts_per_min} (>= 0)"
        )
    sc = _load(scene)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 40]))
    centres, normals = reachable_patches(sc, 0.5)
    first_pass = list(rng.permutation(len(centres)))
    chunks: list[tuple] = []  # (X, kind, t_s, event, normals)
    touched = []
    t, covered_s, ext_next, event = 0.0, math.nan, 0.0, 0
    prev = np.asarray(sc.start, dtype=np.float64)
    mean_stroke = 4.0
    mean_free = mean_stroke * (1.0 - contact_fraction) / contact_fraction
    while t < duration_s:
        # Free flight towards the next patch.
        free_s = rng.exponential(mean_free) + 0.5
        k = first_pass.pop(0) if first_pass else int(rng.integers(len(centres)))
        target = centres[k] + (DRONE_RADIUS + 0.1) * normals[k]
        t_ext = np.arange(ext_next, t + free_s, 1.0 / EXTERNAL_HZ)
        t_ext = t_ext[t_ext >= t]
        if t_ext.size:
            frac = ((t_ext - t) / free_s)[:, None]
            path = prev + frac * (target - prev) + rng.normal(0.0, 0.15, (t_ext.size, 3))
            path = _push_out(sc, path)
            chunks.append((path, EXTERNAL, t_ext, -1, np.zeros_like(path)))
            ext_next = t_ext[-1] + 1.0 / EXTERNAL_HZ
        n_gusts = rng.poisson(gusts_per_min * free_s / 60.0)
        for _ in range(n_gusts):
            tg = t + rng.uniform(0.0, free_s)
            count = int(rng.integers(5, 51))
            where = _push_out(sc, (prev + rng.uniform(0, 1) * (target - prev))[None])[0]
            fc, fi = _gust_rows(where, count, rng)
            tt = tg + np.arange(count) / CONTACT_HZ
            nn = _unit(fc - fi)
            chunks.append((fc, FALSE_CONTACT, tt, event, nn))
            chunks.append((fi, FALSE_INTERNAL, tt, event, nn))
            event += 1
        t += free_s
        # Slide along the face: one contact event per stroke.
        dur = rng.uniform(2.0, 6.0)
        n_pts = max(2, int(dur * CONTACT_HZ))
        start = centres[k] + _jitter_in_plane(normals[k], rng, 0.2)
        p, n = _stroke(sc, start, normals[k], n_pts, rng.uniform(0.1, 0.3), rng)
        xc, xin = _contact_rows(p, n, rng, noise)
        tt = t + np.arange(n_pts) / CONTACT_HZ
        n_est = _unit(xc - xin)
        chunks.append((xc, CONTACT, tt, event, n_est))
        chunks.append((xin, INTERNAL, tt, event, n_est))
        touched.append(p[tt < duration_s])
        event += 1
        prev = p[-1] + (DRONE_RADIUS + 0.1) * n[-1]
        t += n_pts / CONTACT_HZ
        if not first_pass and math.isnan(covered_s):
            covered_s = t
    X = np.concatenate([c[0] for c in chunks])
    kind = np.concatenate([np.full(len(c[0]), c[1], dtype=np.int8) for c in chunks])
    t_s = np.concatenate([c[2] for c in chunks])
    ev = np.concatenate([np.full(len(c[0]), c[3], dtype=np.int64) for c in chunks])
    nrm = np.concatenate([c[4] for c in chunks])
    keep = t_s < duration_s
    order = np.argsort(t_s[keep], kind="stable")
    X, kind, t_s = X[keep][order], kind[keep][order], t_s[keep][order]
    return ObservationSet3D(
        X=X,
        y=_labels(kind),
        kind=kind,
        ids=np.arange(len(X), dtype=np.int64),
        t_ns=np.round(t_s * 1e9).astype(np.int64),
        scene=sc,
        truth_samples=truth_samples(sc, rng, n_truth),
        covered_s=float(duration_s if math.isnan(covered_s) else covered_s),
        name="session40",
        event=ev[keep][order],
        normals=nrm[keep][order],
        cluster=np.zeros(len(X), dtype=bool),
        touched=np.concatenate(touched),
        placement_m=float(noise),
    )


def _push_out(scene: Scene, pts: np.ndarray) -> np.ndarray:
    """Keep drone positions inside the region and at least DRONE_RADIUS + 0.1 m off structures."""
    lo = np.asarray(scene.region_min) + 0.05
    hi = np.asarray(scene.region_max) - 0.05
    p = np.clip(pts, lo, hi)
    clearance = DRONE_RADIUS + 0.1
    for _ in range(3):
        bad = scene_sdf(scene, p) < clearance - 1e-9
        if not np.any(bad):
            return p
        q, n = _project(scene, p[bad])
        n[:, 2] = np.maximum(n[:, 2], 0.0)  # never push through the floor
        n = np.where(np.linalg.norm(n, axis=1, keepdims=True) > 0, n, [0.0, 0.0, 1.0])
        p[bad] = np.clip(q + clearance * _unit(n), lo, hi)
    bad = scene_sdf(scene, p) < clearance - 1e-9
    p[bad, 2] = hi[2]  # last resort: fly over the structure
    return p
