"""From observations to the rows, groups and evidence the mixture GP fits (pure).

- **Rows.** Contact (y = 0) and internal (y = ``inside_value``) points carry the shape: each
  event keeps one row per ``contact_voxel_m`` voxel of its samples (a 25 Hz press along a wall
  is tens of samples a few millimetres apart: one piece of evidence per voxel). Free-space
  points (y = +1) are thinned to one per ``free_voxel_m`` voxel (the first one seen, so a row
  never changes once chosen): the path flown is dense where the vehicle lingers, and a free
  point per voxel is all the potential needs.
- **Noise.** A contact or internal row's variance is ``contact_noise^2 + (slope * sigma_m)^2``
  (``sigma_m``: the detector's placement uncertainty in metres; ``slope``: the potential's change
  per metre, from 0 at the surface to ``inside_value`` at ``d_in`` behind it); a free row's is
  ``free_noise^2`` (a vehicle centre is 'outside' by an unknown distance).
- **Tangent planes.** A contact says the surface passes there with normal n; where touches are
  sparse the GP would otherwise draw a blob around each. Each event adds two rows at its contact
  centroid: the derivative of the potential along two tangents of n is 0, with noise
  ``tangent_slope_noise`` (label units per metre: 1 is a normal off by ~12 deg on a potential
  rising 5 per metre), so the surface goes on flat for about a length scale. A *lone* event
  (no other event's contact within ``plane_reach_m`` of its centroid) also adds four contact
  rows (y = 0) at ``plane_reach_m`` along +-each tangent, with variance ``contact_noise^2 +
  (plane_noise_per_m * plane_reach_m)^2``, in its own group: sparse touches on a face then
  join up instead of leaving holes between them, and dense ones (which need no help) draw no
  brims past edges. Only a touch whose prior ``P(false)`` is at most ``plane_max_p_false``
  gets them: the surface is carried on from touches the detector believes, not from a
  coin-flip event amid free space. A plane point that another touch nearby places outside its
  own surface (past an edge whose other face was touched), or that lies round a bend two
  touches show (a pillar touched at two sides), is left out (``_plane_points``).
- **Groups.** The rows of one contact event form a group (contacts without an event id are
  grouped into runs no more than ``event_gap_s`` apart in time). Its prior ``P(false)`` is the
  detector's ``p_false`` (mean over its rows) where known, else ``prior_false``.
- **Bursts.** Events within ``burst_radius_m`` of a burst's first event, each at most
  ``burst_gap_s`` after the previous one, form one burst, left out together when the mixture
  tests them (a gust that keeps pushing at one spot makes many consistent 'contacts'). A burst
  of ``burst_events_min`` or more events is itself evidence (``burst_llr`` nats for 'false'):
  a real surface is touched on separate visits, a gust cluster in one window, and a pilot
  tapping one spot three times in seconds is rare (in the SITL flights no touch burst of three
  occurred while 30 % of the gusts started clusters; the ratio is capped at e^3 = 20 so that
  other visits to the same patch can still vouch for it).
- **Settled events.** Events named in ``settled`` (a live mapper settles an event once it has
  been trusted for a while: ``MappingSettings.settle_p_false``) no longer form groups: their
  contact and internal rows are pooled per ``settled_voxel_m`` voxel and face (the axis
  their normal points along most: the two faces of an edge are not averaged) across events, each
  pooled row at the precision-weighted mean of the rows it replaces, with their summed
  precision (the same evidence, in rows bounded by the touched area). The tangent-plane rows
  of one settled event per voxel stay, trusted. Settled groups keep their bookkeeping (ids,
  time span) and no rows.
- **Swept volume.** The vehicle's body cannot have passed through a surface: a contact point
  that lies inside the body (``body_radius_m`` around a free-space centre, ``body_half_height_m``
  above and below) at a free-space sample taken at least ``sweep_exclude_s`` away from the event
  is refuted. It adds ``sweep_llr`` nats to the event's evidence for 'false' (a true contact is
  only ever inside the swept body by its placement error, kept out by ``sweep_tolerance_m``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from groundstation.contact.detector import Observation
from groundstation.mapping.mixture import Groups

#: A plane point another touch within this many plane reaches of it places outside that
#: touch's surface is dropped (``_plane_points``) ...
PLANE_GUARD_REACHES = 2.5
#: ... by more than this along the other touch's normal, metres (the detector's placement
#: error is a few centimetres).
PLANE_BEYOND_TOL_M = 0.02
#: ... or that lies ahead, behind this touch's tangent plane, with its normal turned towards
#: the plane point by more than this sine (~17 deg, above the detector's normal error).
PLANE_TURN_SIN = 0.3
#: ... and sits where a circle through both touches would put it: behind / ahead (along the
#: way the normal turns) within this factor of tan(turn / 2). The other face of a corner
#: touched nearer to or farther from the edge than this touch is no bend: the plane holds.
PLANE_BEND_RATIO = 1.25


@dataclasses.dataclass(frozen=True)
class TrainingPolicy:
    """How observations become rows (see the module docstring; lengths in metres)."""

    inside_value: float = -0.5
    internal_depth_m: float = 0.1
    contact_noise: float = 0.05
    free_noise: float = 0.3
    free_voxel_m: float = 0.1
    prior_false: float = 0.1
    burst_gap_s: float = 3.0
    burst_radius_m: float = 0.3
    body_radius_m: float = 0.2
    body_half_height_m: float = 0.05
    sweep_exclude_s: float = 0.5
    sweep_tolerance_m: float = 0.03
    sweep_llr: float = 4.6
    contact_voxel_m: float = 0.05
    event_gap_s: float = 0.2
    burst_events_min: int = 3
    burst_llr: float = 3.0
    tangent_slope_noise: float = 0.0
    plane_reach_m: float = 0.0
    plane_noise_per_m: float = 0.5
    plane_max_p_false: float = 1.0
    settled_voxel_m: float = 0.1


@dataclasses.dataclass(frozen=True)
class TrainingSet:
    """The fitted rows and their bookkeeping.

    Attributes
    ----------
    X : (n, d) float64
    directions : (n, d) float64
        Zero for value rows; a unit tangent for a contact's tangent-plane rows (the derivative
        of the potential along it is 0: the surface goes on flat around the contact).
    y : (n,) float64
        Potential values (0 contact, ``inside_value`` internal, +1 free), or 0 for a tangent.
    noise_var : (n,) float64
    row_members : tuple of (k,) int64 arrays
        Observation ids each row stands for (a group's samples in one voxel share a row;
        empty for tangent-plane rows).
    groups : Groups
    event_ids : (G,) int64
        Detector event id of each group (-1 for contacts without one).
    group_ids : tuple of (k,) int64 arrays
        Observation ids of each group (contacts and internal points).
    swept : (G,) bool
        The group's contact lies in the body's swept volume.
    keys : tuple of tuple
        Stable identity of each group (:func:`group_key`).
    t_end_ns : (G,) int64
        Time of each group's last observation.
    settled : (G,) bool
        The group was settled: its rows are in the trusted pool (row group -1).
    n_raw : int
        Observations given.
    """

    X: np.ndarray
    directions: np.ndarray
    y: np.ndarray
    noise_var: np.ndarray
    row_members: tuple[np.ndarray, ...]
    groups: Groups
    event_ids: np.ndarray
    group_ids: tuple[np.ndarray, ...]
    swept: np.ndarray
    keys: tuple[tuple, ...]
    t_end_ns: np.ndarray
    settled: np.ndarray
    n_raw: int

    def __len__(self) -> int:
        return int(self.X.shape[0])


def group_key(event_id: int, ids: Sequence[int]) -> tuple:
    """A group's identity across refits: its detector event, else its first observation."""
    return ("e", int(event_id)) if event_id >= 0 else ("o", int(min(ids)))


def _event_keys(obs: Sequence[Observation], gap_ns: int) -> dict[int, tuple]:
    """Group key of every contact and internal observation: its detector event, or, without
    one, the run of such observations no more than ``gap_ns`` apart in time."""
    keys: dict[int, tuple] = {}
    loose = sorted((o for o in obs if o.label <= 0 and o.event_id < 0), key=lambda o: o.t_ns)
    run, last = -1, None
    for o in loose:
        if last is None or o.t_ns - last > gap_ns:
            run += 1
        keys[o.id] = ("run", run)
        last = o.t_ns
    for o in obs:
        if o.label <= 0 and o.event_id >= 0:
            keys[o.id] = ("event", int(o.event_id))
    return keys


@dataclasses.dataclass
class _Group:
    event_id: int
    ids: list[int] = dataclasses.field(default_factory=list)
    priors: list[float] = dataclasses.field(default_factory=list)
    t: list[int] = dataclasses.field(default_factory=list)
    contacts: list[np.ndarray] = dataclasses.field(default_factory=list)
    normals: list[np.ndarray] = dataclasses.field(default_factory=list)
    cells: dict = dataclasses.field(default_factory=dict)  # (label, voxel) -> [ids, xs, s2s, ns]


def build_training_set(
    obs: Sequence[Observation], policy: TrainingPolicy, settled: frozenset = frozenset()
) -> TrainingSet:
    """Rows, groups, priors, bursts and swept-volume evidence of ``obs`` (any order);
    ``settled``: the :func:`group_key` of the groups to pool (module docstring)."""
    p = policy
    obs = sorted(obs, key=lambda o: o.id)
    slope = abs(p.inside_value) / p.internal_depth_m
    keys = _event_keys(obs, int(p.event_gap_s * 1e9))
    groups: dict[tuple, _Group] = {}
    rows_X, rows_y, rows_s2, rows_m, rows_g = [], [], [], [], []
    free_seen: set[tuple[int, ...]] = set()
    free_pts, free_t = [], []
    for o in obs:
        x = np.asarray(o.position, dtype=np.float64)
        if o.label > 0:
            free_pts.append(x)
            free_t.append(int(o.t_ns))
            key = tuple(np.floor(x / p.free_voxel_m).astype(np.int64).tolist())
            if key in free_seen:
                continue
            free_seen.add(key)
            rows_X.append(x)
            rows_y.append(1.0)
            rows_s2.append(p.free_noise**2)
            rows_m.append(np.array([o.id], dtype=np.int64))
            rows_g.append(-1)
            continue
        grp = groups.setdefault(keys[o.id], _Group(int(o.event_id)))
        grp.ids.append(o.id)
        grp.t.append(int(o.t_ns))
        if math.isfinite(o.p_false):
            grp.priors.append(float(o.p_false))
        if o.label == 0:
            grp.contacts.append(x)
            grp.normals.append(np.asarray(o.normal, dtype=np.float64))
        sig = o.sigma_m if math.isfinite(o.sigma_m) else 0.0
        cell = (int(o.label), *np.floor(x / p.contact_voxel_m).astype(np.int64).tolist())
        ids, xs, s2s, ns = grp.cells.setdefault(cell, ([], [], [], []))
        ids.append(o.id)
        xs.append(x)
        s2s.append(p.contact_noise**2 + (slope * sig) ** 2)
        ns.append(np.asarray(o.normal, dtype=np.float64))
    glist = list(groups.values())
    d = (
        len(rows_X[0])
        if rows_X
        else (len(glist[0].contacts[0]) if glist and glist[0].contacts else 3)
    )
    dirs = [np.zeros(d)] * len(rows_X)
    gkeys = tuple(group_key(grp.event_id, grp.ids) for grp in glist)
    is_settled = np.array([k in settled for k in gkeys], dtype=bool)
    pool: dict[tuple, list] = {}  # (label, coarse voxel) -> [ids, sum w x, sum w]
    for g, grp in enumerate(glist):
        for (label, *_), (ids, xs, s2s, ns) in grp.cells.items():
            x, s2 = np.mean(xs, axis=0), float(np.mean(s2s))  # a group's voxel: one row
            if is_settled[g]:  # pooled per voxel and face (two faces of an edge stay apart)
                cell = (label, _face(np.mean(ns, axis=0)),
                        *np.floor(x / p.settled_voxel_m).astype(np.int64).tolist())  # fmt: skip
                acc = pool.setdefault(cell, [[], np.zeros(d), 0.0])
                acc[0].extend(ids)
                acc[1] += x / s2
                acc[2] += 1.0 / s2
                continue
            rows_X.append(x)
            rows_y.append(0.0 if label == 0 else p.inside_value)
            rows_s2.append(s2)
            rows_m.append(np.asarray(ids, dtype=np.int64))
            rows_g.append(g)
            dirs.append(np.zeros(d))
    for (label, *_), (ids, wx, w) in sorted(pool.items()):
        rows_X.append(wx / w)
        rows_y.append(0.0 if label == 0 else p.inside_value)
        rows_s2.append(1.0 / w)
        rows_m.append(np.asarray(sorted(ids), dtype=np.int64))
        rows_g.append(-1)
        dirs.append(np.zeros(d))
    tangent_cells: set[tuple] = set()
    if p.tangent_slope_noise > 0 and d == 3:
        lone = _lone([grp.contacts for grp in glist], p.plane_reach_m)
        cen, nrm = _centres_normals(glist, d)
        for g, grp in enumerate(glist):
            n = nrm[g]  # zero without contacts or where their normals disagree
            if not n.any():
                continue
            a = np.cross(n, [0.0, 0.0, 1.0] if abs(n[2]) < 0.9 else [1.0, 0.0, 0.0])
            a /= np.linalg.norm(a)
            b = np.cross(n, a)
            centre = cen[g]
            if is_settled[g]:  # settled: one event's tangents per voxel (rows bounded by area)
                cell = tuple(np.floor(centre / p.settled_voxel_m).astype(np.int64).tolist())
                if cell in tangent_cells:
                    continue
                tangent_cells.add(cell)
            none = np.zeros(0, dtype=np.int64)
            for v in (a, b):
                rows_X.append(centre)
                rows_y.append(0.0)
                rows_s2.append(p.tangent_slope_noise**2)
                rows_m.append(none)
                rows_g.append(-1 if is_settled[g] else g)
                dirs.append(v)
            prior_g = float(np.mean(grp.priors)) if grp.priors else p.prior_false
            if p.plane_reach_m > 0 and lone[g] and prior_g <= p.plane_max_p_false:
                rho = p.plane_reach_m
                s2_plane = p.contact_noise**2 + (p.plane_noise_per_m * rho) ** 2
                for q in _plane_points(g, centre, (a, -a, b, -b), cen, nrm, rho):
                    rows_X.append(q)
                    rows_y.append(0.0)
                    rows_s2.append(s2_plane)
                    rows_m.append(none)
                    rows_g.append(-1 if is_settled[g] else g)
                    dirs.append(np.zeros(d))
    X = np.asarray(rows_X, dtype=np.float64).reshape(-1, d)
    prior = np.array(
        [float(np.mean(grp.priors)) if grp.priors else p.prior_false for grp in glist],
        dtype=np.float64,
    )
    t_span = [(min(grp.t), max(grp.t)) for grp in glist]
    centre = [
        np.mean(grp.contacts, axis=0) if grp.contacts else np.full(d, np.nan) for grp in glist
    ]
    burst = _bursts(t_span, centre, p)
    size = np.bincount(burst, minlength=int(burst.max(initial=-1)) + 1) if burst.size else burst
    clustered = size[burst] >= p.burst_events_min if burst.size else np.zeros(0, dtype=bool)
    contacts = [grp.contacts for grp in glist]
    swept = _swept(contacts, t_span, np.asarray(free_pts).reshape(-1, d),
                   np.asarray(free_t, dtype=np.int64), p)  # fmt: skip
    return TrainingSet(
        X=X,
        directions=np.asarray(dirs, dtype=np.float64).reshape(-1, d),
        y=np.asarray(rows_y, dtype=np.float64),
        noise_var=np.asarray(rows_s2, dtype=np.float64),
        row_members=tuple(rows_m),
        groups=Groups(
            row_group=np.asarray(rows_g, dtype=np.int64),
            prior_false=prior,
            burst=burst,
            extra_llr=np.where(swept, p.sweep_llr, 0.0) + np.where(clustered, p.burst_llr, 0.0),
        ),
        event_ids=np.asarray([grp.event_id for grp in glist], dtype=np.int64),
        group_ids=tuple(np.asarray(grp.ids, dtype=np.int64) for grp in glist),
        swept=swept,
        keys=gkeys,
        t_end_ns=np.asarray([hi for _, hi in t_span], dtype=np.int64),
        settled=is_settled,
        n_raw=len(obs),
    )


def _centres_normals(glist: list[_Group], d: int) -> tuple[np.ndarray, np.ndarray]:
    """(G, d) contact centroid (NaN without contacts) and unit mean normal (0 where the
    normals do not agree on one) of every group."""
    cen = np.full((len(glist), d), np.nan)
    nrm = np.zeros((len(glist), d))
    for g, grp in enumerate(glist):
        if grp.contacts:
            cen[g] = np.mean(grp.contacts, axis=0)
            n = np.mean(grp.normals, axis=0)
            if float(np.linalg.norm(n)) >= 0.5:
                nrm[g] = n / np.linalg.norm(n)
    return cen, nrm


def _plane_points(
    g: int, centre: np.ndarray, tangents: Sequence[np.ndarray], cen: np.ndarray,
    nrm: np.ndarray, reach: float,
) -> list[np.ndarray]:  # fmt: skip
    """Group ``g``'s plane points ``centre + reach * t``, leaving out the ones the touches
    within ``PLANE_GUARD_REACHES * reach`` say the surface does not go on flat to:

    - *past an edge*: another touch places the point outside its own surface (by more than
      ``PLANE_BEYOND_TOL_M`` along its normal), the other face of a corner was touched;
    - *round a bend*: another touch lies ahead along ``t``, behind this touch's tangent plane
      (by more than ``PLANE_BEYOND_TOL_M``), with its normal turned towards ``t`` (by more
      than ``PLANE_TURN_SIN``), where a circle through both touches would put it (within
      ``PLANE_BEND_RATIO``): the surface curves away, as on a pillar touched at two sides.
      A box touched on two faces equally far from their edge looks the same; there the
      plane is left out too, and the GP's own smooth interpolation decides.
    """
    n_g = nrm[g]
    others = (np.arange(len(cen)) != g) & np.isfinite(cen).all(axis=1) & nrm.any(axis=1)
    out = []
    for t in tangents:
        q = centre + reach * t
        near = others & (np.linalg.norm(np.nan_to_num(cen - q, nan=np.inf), axis=1)
                         <= PLANE_GUARD_REACHES * reach)  # fmt: skip
        off = cen[near] - centre
        past_edge = np.einsum("ij,ij->i", q - cen[near], nrm[near]) > PLANE_BEYOND_TOL_M
        behind = -(off @ n_g)  # h: how far behind the tangent plane
        cos = np.clip(nrm[near] @ n_g, -1.0, 1.0)
        turn = nrm[near] - np.outer(cos, n_g)  # the way the normal turns, in the plane
        turn /= np.maximum(np.linalg.norm(turn, axis=1, keepdims=True), 1e-12)
        ahead = np.einsum("ij,ij->i", off, turn)  # s: how far ahead that way
        # on a circle through both touches h / s = tan(theta / 2), theta the normals' turn
        half = np.tan(np.arccos(cos) / 2)
        bend = (
            (off @ t > 0)
            & (behind > PLANE_BEYOND_TOL_M)
            & (nrm[near] @ t > PLANE_TURN_SIN)
            & (behind < PLANE_BEND_RATIO * half * ahead)
            & (behind * PLANE_BEND_RATIO > half * ahead)
        )
        if not np.any(past_edge | bend):
            out.append(q)
    return out


def _lone(contacts: list[list[np.ndarray]], radius: float) -> np.ndarray:
    """(G,) bool: no other group's contact lies within ``radius`` of the group's contact
    centroid (groups without contacts count as lone; ``radius`` <= 0: every group)."""
    lone = np.ones(len(contacts), dtype=bool)
    pts = [x for cs in contacts for x in cs]
    if radius <= 0 or not pts:
        return lone
    from scipy.spatial import cKDTree

    owner = np.repeat(np.arange(len(contacts)), [len(cs) for cs in contacts])
    has = np.flatnonzero([len(cs) > 0 for cs in contacts])
    centres = np.array([np.mean(contacts[g], axis=0) for g in has])
    nears = cKDTree(np.asarray(pts)).query_ball_point(centres, radius)
    for g, near in zip(has, nears, strict=True):
        lone[g] = not np.any(owner[np.asarray(near, dtype=np.int64)] != g)
    return lone


def _face(n: np.ndarray) -> int:
    """The signed axis a normal points along most (+1..+d, -1..-d; 0 for none)."""
    if not np.all(np.isfinite(n)) or float(np.abs(n).max(initial=0.0)) == 0.0:
        return 0
    k = int(np.argmax(np.abs(n)))
    return (k + 1) * (1 if n[k] > 0 else -1)


def _bursts(
    t_span: list[tuple[int, int]], centre: list[np.ndarray], p: TrainingPolicy
) -> np.ndarray:
    """Bursts: in time order, an event joins the burst whose first event lies within
    ``burst_radius_m`` of it and whose last event ended at most ``burst_gap_s`` before it; else
    it starts one. (Chaining neighbours transitively would fuse a whole survey of quick touches
    into one burst, left out as a whole and judged against free space alone.)"""
    G = len(t_span)
    out = np.full(G, -1, dtype=np.int64)
    gap = int(p.burst_gap_s * 1e9)
    open_: list[list] = []  # [seed centre, last end, burst id]
    for g in sorted(range(G), key=lambda k: t_span[k][0]):
        c = centre[g]
        best = None
        if np.isfinite(c).all():
            for entry in open_:
                seed, last, _ = entry
                if (
                    t_span[g][0] - last <= gap
                    and float(np.linalg.norm(c - seed)) <= p.burst_radius_m
                ):
                    best = entry
                    break
        if best is None:
            best = [c, t_span[g][1], len(open_)]
            open_.append(best)
        best[1] = max(best[1], t_span[g][1])
        out[g] = best[2]
    return out


def _swept(
    contacts, t_span, free_pts: np.ndarray, free_t: np.ndarray, p: TrainingPolicy
) -> np.ndarray:
    """Which groups' contact points lie inside the body at a free-space sample away from them."""
    G = len(contacts)
    out = np.zeros(G, dtype=bool)
    if G == 0 or free_pts.shape[0] == 0 or free_pts.shape[1] != 3:
        return out
    from scipy.spatial import cKDTree

    tree = cKDTree(free_pts)
    r = p.body_radius_m - p.sweep_tolerance_m
    h = p.body_half_height_m - p.sweep_tolerance_m
    if r <= 0:
        return out
    excl = int(p.sweep_exclude_s * 1e9)
    for g in range(G):
        if not contacts[g]:
            continue
        lo, hi = t_span[g][0] - excl, t_span[g][1] + excl
        for c in contacts[g]:
            for j in tree.query_ball_point(c, math.hypot(r, max(h, 0.0))):
                if lo <= free_t[j] <= hi:
                    continue
                dx = free_pts[j] - c
                if math.hypot(dx[0], dx[1]) < r and abs(dx[2]) < h:
                    out[g] = True
                    break
            if out[g]:
                break
    return out
