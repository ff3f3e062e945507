"""From observations to the rows, groups and evidence the mixture GP fits (pure).

- **Rows.** Contact (y = 0) and internal (y = ``inside_value``) points carry the shape: each
  event keeps one row per ``contact_voxel_m`` voxel of its samples (a 25 Hz press along a wall
  is tens of samples a few millimetres apart: one piece of evidence per voxel). Free-space
  points (y = +1) are thinned to one per ``free_voxel_m`` voxel (the first one seen, so a row
  never changes once chosen): the path flown is dense where the vehicle lingers, and a free
  point per voxel is all the potential needs.
- **The vehicle at a contact.** A free sample is the vehicle's centre, +1 a clearance of
  about ``1 / slope`` (0.2 m at the default slope of 5 per metre). The centre of a body in
  contact is only the body's extent from the contact: 0.05 m above the top of a box the
  vehicle sits on. The detector's geometry puts such a sample in front of *any* contact it
  places, true or false; as +1 a few centimetres from a 0 it bent the field so steeply that
  the rest of the data took real touches on horizontal faces for outliers. A free sample
  taken within ``companion_s`` of an event, in front of its contact plane by less than
  ``COMPANION_CLEARANCE`` of that clearance and within the body's reach (``body_reach_m``) of
  its contacts, is that event's *companion*: left out with the event's burst when the mixture
  tests it (``Groups.companion``), kept in the fit (it is true free space either way). Samples
  behind the plane are not companions: they are evidence against the contact; nor are samples
  as far in front as +1 says (a contact on the vehicle's side). Within 0.5 s by default
  (``MappingSettings.companion_s``). Nor is a sample nearer the plane than the body itself
  keeps its centre from a surface it touches (``body_clearance``: the least support distance
  of the body's level inner cylinder over the normals within ``NORMAL_ERROR_DEG`` of the
  contact's, less ``sweep_tolerance_m``; 0.17 m for the cylinder's side touch, 0.02 m for its
  top touch): the body there reached past the plane within its own reach of the contact, which
  the body of a true touch cannot. That *crosses* the event, with the swept volume's evidence
  (below), inside the time the swept test skips; unless a touch of another event that the
  detector believes shows the same plane within twice ``sweep_disc_m`` (then the surface is
  there, and the body was not level: a vehicle tumbling along a deck's side after a hard hit).
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
  coin-flip event amid free space. A plane point that another touch within ``plane_guard_m``
  places outside its own surface (past an edge whose other face was touched), or a face of
  the same solid within ``plane_guard_solid_m``, or that lies round a bend two touches show (a
  pillar touched at two sides), is left out (``_plane_keep``).
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
  other visits to the same patch can still vouch for it). An event whose prior ``P(false)`` is
  below ``burst_min_p_false`` gets no burst evidence: impacts the detector vouches for are a
  pilot tapping a spot (no detected gust of the tuning flights had ``p_false`` below 0.06).
- **Settled events.** Events named in ``settled`` (a live mapper settles an event once it has
  been trusted for a while: ``MappingSettings.settle_p_false``) no longer form groups: their
  contact and internal rows are pooled per ``settled_voxel_m`` voxel and face (the axis
  their normal points along most: the two faces of an edge are not averaged) across events, each
  pooled row at the precision-weighted mean of the rows it replaces, with their summed
  precision (the same evidence, in rows bounded by the touched area). The tangent-plane rows
  of one settled event per voxel stay, trusted. Settled groups keep their bookkeeping (ids,
  time span) and no rows.
- **Swept volume.** The vehicle's body cannot have passed through a surface: an event whose
  contact, or a point on the rim of its tangent disc of radius ``sweep_disc_m`` round its
  contacts' centroid (the surface a touch shows goes on round it), lies inside the body
  (``body_radius_m`` round a free-space centre, the disc it fills whatever its yaw, and
  ``body_half_height_m`` above and below) at a free-space sample taken at least
  ``sweep_exclude_s`` away from the event is refuted. It adds ``sweep_llr`` nats to the
  event's evidence for 'false' (a true contact is only ever inside the swept body by its
  placement error, or where its surface ends within the disc: an edge the vehicle later flew
  round at the height of the touch). Where a contact really was depends on what touched. A
  cylinder's flat side wall (0.1 m high) or top (a 0.4 m disc) may have met the surface
  anywhere on it: its probes keep ``sweep_tolerance_m`` all round (the body shrunk by it;
  with the tolerance along the normal alone, the side wall's full height refuted true side
  touches whose disc reached past a top edge the vehicle then flew over). A guarded
  quadrotor touches with a thin guard ring or its small central body: its error lies along
  the contact's normal (``tolerance_along_normal``), so a probe counts if it is inside the
  body wherever within the tolerance along its normal it was, and the body keeps its own
  extent across the normal (shrunk all round, a body 0.05 m thick keeps none). Along the
  normal, a body thinner than twice the tolerance then refutes nothing from one sample: a
  vehicle resting on a deck top is as near the deck as a body can be. (With the guarded body
  assumed 0.1 m thick and 0.255 m wide, a MuJoCo vehicle resting on a pier deck refuted top
  touches placed 1-4 cm high.) A rim point that a touch of another event places outside its
  own surface (the ``_plane_keep`` guard: the other face of an edge) is no probe, where the
  detector vouches
  for that touch (prior ``P(false)`` at most ``plane_max_p_false``; gusts guarding each other
  would clear a cluster) and the two are faces of one solid (each on or behind the other's
  plane; a gust in front of a touched wall is no edge of it).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from groundstation.contact.detector import Observation
from groundstation.mapping.mixture import Groups

#: A touch within this many plane reaches of a plane point can show a bend there
#: (``_plane_keep``); a sweep probe is past an edge a touch within this many disc radii of it
#: shows (``_past_edge``; plane points: ``mapping.plane_guard_m``).
PLANE_GUARD_REACHES = 2.5
#: A point lies outside a touch's surface when in front of its tangent plane by more than
#: this, metres (the detector's placement error is a few centimetres).
PLANE_BEYOND_TOL_M = 0.02
#: A bend: the other touch lies ahead, behind this touch's tangent plane, with its normal
#: turned towards the plane point by more than this sine (~17 deg, above the detector's
#: normal error) ...
PLANE_TURN_SIN = 0.3
#: ... and sits where a circle through both touches would put it: behind / ahead (along the
#: way the normal turns) within this factor of tan(turn / 2). The other face of a corner
#: touched nearer to or farther from the edge than this touch is no bend: the plane holds.
PLANE_BEND_RATIO = 1.25


#: A free sample is a contact's companion only while it lies nearer the contact's plane than
#: this share of the clearance +1 stands for (``1 / slope``, 0.2 m at the default slope): a
#: sample 0.2 m in front of a contact made on the vehicle's side agrees with the label's own
#: scale, and on the paper-like 3D set it was what flagged an isolated gust there (as a
#: companion: that gust kept, largest phantom patch 0.19 -> 0.53 m²).
COMPANION_CLEARANCE = 0.75
#: How far a contact's normal may lie off the true one, degrees (the detector averages the
#: body's support points over 20 degrees round it: ``contact.normal_spread_deg``).
NORMAL_ERROR_DEG = 20.0


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
    body_reach_m: float = math.hypot(0.2, 0.05)  # the default cylinder's
    tolerance_along_normal: bool = False
    sweep_exclude_s: float = 0.5
    sweep_tolerance_m: float = 0.03
    sweep_llr: float = 4.6
    sweep_disc_m: float = 0.0
    contact_voxel_m: float = 0.05
    event_gap_s: float = 0.2
    burst_events_min: int = 3
    burst_llr: float = 3.0
    burst_min_p_false: float = 0.05
    tangent_slope_noise: float = 0.0
    plane_reach_m: float = 0.0
    plane_noise_per_m: float = 0.5
    plane_max_p_false: float = 1.0
    plane_guard_m: float = 0.5
    plane_guard_solid_m: float = 0.5
    internal_guard_m: float = 0.0
    settled_voxel_m: float = 0.1
    companion_s: float = 0.0
    body_clearance: bool = False
    lone_reach_m: float = 0.0
    internal_guard_tilt_deg: float = 0.0


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
    normals : (n, d) float64
        Mean outward normal of the observations a contact or internal row stands for (not unit
        length); zero for free-space, tangent and plane rows.
    row_members : tuple of (k,) int64 arrays
        Observation ids each row stands for (a group's samples in one voxel share a row;
        empty for tangent-plane rows).
    groups : Groups
    event_ids : (G,) int64
        Detector event id of each group (-1 for contacts without one).
    group_ids : tuple of (k,) int64 arrays
        Observation ids of each group (contacts and internal points).
    swept : (G,) bool
        The group's contact, or its tangent disc, lies in the body's swept volume.
    keys : tuple of tuple
        Stable identity of each group (:func:`group_key`).
    t_end_ns : (G,) int64
        Time of each group's last observation.
    settled : (G,) bool
        The group was settled: its rows are in the trusted pool (row group -1).
    n_raw : int
        Observations given.
    corroborators : tuple of (k,) int64 arrays or None
        For each group with contacts, the other groups with a contact within ``lone_reach_m``
        of its contact centroid: those that may corroborate it (None: a group without
        contacts, or every group with ``lone_reach_m`` 0). :meth:`uncorroborated` reads it.
    """

    X: np.ndarray
    directions: np.ndarray
    y: np.ndarray
    noise_var: np.ndarray
    normals: np.ndarray
    row_members: tuple[np.ndarray, ...]
    groups: Groups
    event_ids: np.ndarray
    group_ids: tuple[np.ndarray, ...]
    swept: np.ndarray
    keys: tuple[tuple, ...]
    t_end_ns: np.ndarray
    settled: np.ndarray
    n_raw: int
    corroborators: tuple[np.ndarray | None, ...]

    def __len__(self) -> int:
        return int(self.X.shape[0])

    def uncorroborated(self, vouch: np.ndarray | None = None) -> np.ndarray:
        """(G,) bool: the group has contacts and none of its corroborators vouches for it
        (``vouch[h]``: group ``h`` may corroborate another; default every group).

        An event the map believes false corroborates nothing: two gusts of one cluster pushed
        the drone to the same place, and a doubted one beside a flagged one was kept because
        of it (tuning flights: the unflagged gust under four of the ten largest phantom
        patches had only flagged gusts within 0.5 m)."""
        ok = np.ones(len(self.corroborators), dtype=bool) if vouch is None else vouch
        return np.array([c is not None and not ok[c].any() for c in self.corroborators], dtype=bool)


def group_key(event_id: int, ids: Sequence[int]) -> tuple:
    """A group's identity across refits: its detector event, else its first observation."""
    return ("e", int(event_id)) if event_id >= 0 else ("o", int(min(ids)))


@dataclasses.dataclass(frozen=True)
class _Columns:
    """The observations as arrays, in id order (one Python pass over them, then numpy)."""

    ids: np.ndarray  # (n,) int64, increasing
    t: np.ndarray  # (n,) int64
    label: np.ndarray  # (n,) float64
    X: np.ndarray  # (n, d) float64
    N: np.ndarray  # (n, d) float64, normals
    event: np.ndarray  # (n,) int64
    p_false: np.ndarray  # (n,) float64
    sigma: np.ndarray  # (n,) float64

    @classmethod
    def of(cls, obs: Sequence[Observation]) -> _Columns:
        obs = sorted(obs, key=lambda o: o.id)
        n = len(obs)
        X = np.array([o.position for o in obs], dtype=np.float64).reshape(n, -1 if n else 3)
        return cls(
            ids=np.fromiter((o.id for o in obs), np.int64, n),
            t=np.fromiter((o.t_ns for o in obs), np.int64, n),
            label=np.fromiter((o.label for o in obs), np.float64, n),
            X=X,
            N=np.array([o.normal for o in obs], dtype=np.float64).reshape(X.shape),
            event=np.fromiter((o.event_id for o in obs), np.int64, n),
            p_false=np.fromiter((o.p_false for o in obs), np.float64, n),
            sigma=np.fromiter((o.sigma_m for o in obs), np.float64, n),
        )


def _group_of(col: _Columns, rows: np.ndarray, gap_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Group of each contact or internal observation ``rows`` (indices into ``col``, in id
    order): its detector event, or, without one, the run of such observations no more than
    ``gap_ns`` apart in time. Groups are numbered in the order of their first observation.
    Returns (group of each row, event id of each group (-1 for a run))."""
    ev = col.event[rows]
    code = ev.copy()
    loose = np.flatnonzero(ev < 0)
    if loose.size:
        order = np.argsort(col.t[rows[loose]], kind="stable")
        t_sorted = col.t[rows[loose]][order]
        new = np.ones(loose.size, dtype=bool)
        new[1:] = np.diff(t_sorted) > gap_ns
        run = np.empty(loose.size, dtype=np.int64)
        run[order] = np.cumsum(new) - 1
        code[loose] = -1 - run  # runs below every event id
    codes, first, inv = np.unique(code, return_index=True, return_inverse=True)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    event_ids = np.where(codes[order] >= 0, codes[order], -1)
    return rank[inv.reshape(-1)], event_ids


def _sums(index: np.ndarray, values: np.ndarray, size: int) -> np.ndarray:
    """Per-``index`` sums of ``values`` ((n,) or (n, d)), in input order."""
    if values.ndim == 1:
        return np.bincount(index, weights=values, minlength=size)
    return np.stack(
        [np.bincount(index, weights=values[:, k], minlength=size) for k in range(values.shape[1])],
        axis=1,
    ).reshape(size, values.shape[1])


def _split(values: np.ndarray, index: np.ndarray, size: int) -> list[np.ndarray]:
    """``values`` split by ``index`` (0..size-1), each part in input order."""
    if size == 0:
        return []
    order = np.argsort(index, kind="stable")
    cuts = np.cumsum(np.bincount(index, minlength=size))[:-1]
    return np.split(values[order], cuts)


def build_training_set(
    obs: Sequence[Observation], policy: TrainingPolicy, settled: frozenset = frozenset()
) -> TrainingSet:
    """Rows, groups, priors, bursts and swept-volume evidence of ``obs`` (any order);
    ``settled``: the :func:`group_key` of the groups to pool (module docstring).

    Rows come in this order: free space (by id), each group's voxels (groups by their first
    observation, voxels by theirs), the settled pool (by voxel), tangent and plane rows."""
    p = policy
    col = _Columns.of(obs)
    d = col.X.shape[1]
    slope = abs(p.inside_value) / p.internal_depth_m
    free = np.flatnonzero(col.label > 0)
    _, first = np.unique(
        np.floor(col.X[free] / p.free_voxel_m).astype(np.int64), axis=0, return_index=True
    )
    free_rows = free[np.sort(first)]  # the first sample of each free voxel
    rows_X = [col.X[free_rows]]
    rows_y = [np.ones(free_rows.size)]
    rows_s2 = [np.full(free_rows.size, p.free_noise**2)]
    rows_n = [np.zeros((free_rows.size, d))]
    rows_m: list[np.ndarray] = [col.ids[i : i + 1] for i in free_rows]
    rows_g = [np.full(free_rows.size, -1, dtype=np.int64)]

    # groups: contact and internal observations by event (or run)
    shape = np.flatnonzero(col.label <= 0)
    g_of, event_ids = _group_of(col, shape, int(p.event_gap_s * 1e9))
    G = event_ids.size
    ids_of = _split(col.ids[shape], g_of, G)
    gkeys = tuple(group_key(int(e), ids) for e, ids in zip(event_ids, ids_of, strict=True))
    is_settled = np.array([k in settled for k in gkeys], dtype=bool)
    normals = col.N[shape]
    is_contact = col.label[shape] == 0
    contacts = _split(col.X[shape][is_contact], g_of[is_contact], G)
    cen, nrm = _centres_normals(col.X[shape][is_contact], normals[is_contact], g_of[is_contact], G)
    pf = col.p_false[shape]
    known = np.isfinite(pf)
    n_known = np.bincount(g_of[known], minlength=G)
    prior = np.where(
        n_known > 0,
        _sums(g_of[known], pf[known], G) / np.maximum(n_known, 1),
        p.prior_false,
    )

    # one row per group and voxel (label, contact_voxel_m) at the mean of its samples
    lab = col.label[shape].astype(np.int64)
    vox = np.floor(col.X[shape] / p.contact_voxel_m).astype(np.int64)
    _, cfirst, cinv = np.unique(
        np.column_stack([g_of, lab, vox]), axis=0, return_index=True, return_inverse=True
    )
    corder = np.lexsort((cfirst, g_of[cfirst]))  # by group, then by first sample
    crank = np.empty_like(corder)
    crank[corder] = np.arange(corder.size)
    cell = crank[cinv.reshape(-1)]
    C = corder.size
    n_cell = np.bincount(cell, minlength=C).astype(np.float64)
    sig = col.sigma[shape]
    s2 = p.contact_noise**2 + (slope * np.where(np.isfinite(sig), sig, 0.0)) ** 2
    cell_x = _sums(cell, col.X[shape], C) / n_cell[:, None]
    cell_s2 = _sums(cell, s2, C) / n_cell
    cell_n = _sums(cell, normals, C) / n_cell[:, None]
    cell_g = g_of[cfirst[corder]]
    cell_lab = lab[cfirst[corder]]
    cell_ids = _split(col.ids[shape], cell, C)
    guard = prior <= p.plane_max_p_false  # touches whose plane may say where a surface ends
    outside = np.zeros(C, dtype=bool)  # internal rows another touch places outside its surface
    if p.internal_guard_m > 0 and d == 3:
        inner = np.flatnonzero(cell_lab < 0)
        outside[inner] = _past_edge(cell_x[inner], cell_g[inner], cen, nrm, guard,
                                    p.internal_guard_m, p.internal_guard_tilt_deg)  # fmt: skip
    kept = np.flatnonzero(~is_settled[cell_g] & ~outside)
    rows_X.append(cell_x[kept])
    rows_y.append(np.where(cell_lab[kept] == 0, 0.0, p.inside_value))
    rows_s2.append(cell_s2[kept])
    rows_n.append(cell_n[kept])
    rows_m.extend(cell_ids[c] for c in kept)
    rows_g.append(cell_g[kept])

    # settled groups: their voxels pooled per settled voxel and face, precision-weighted
    pooled = np.flatnonzero(is_settled[cell_g] & ~outside)
    if pooled.size:
        face = _faces(cell_n[pooled])
        pkey = np.column_stack([
            cell_lab[pooled], face,
            np.floor(cell_x[pooled] / p.settled_voxel_m).astype(np.int64),
        ])  # fmt: skip
        _, pinv = np.unique(pkey, axis=0, return_inverse=True)
        pinv = pinv.reshape(-1)
        P = int(pinv.max()) + 1
        w = _sums(pinv, 1.0 / cell_s2[pooled], P)
        rows_X.append(_sums(pinv, cell_x[pooled] / cell_s2[pooled, None], P) / w[:, None])
        plab = np.zeros(P, dtype=np.int64)
        plab[pinv] = cell_lab[pooled]
        rows_y.append(np.where(plab == 0, 0.0, p.inside_value))
        rows_s2.append(1.0 / w)
        rows_n.append(_sums(pinv, cell_n[pooled], P) / np.bincount(pinv, minlength=P)[:, None])
        members = _split(np.arange(pooled.size), pinv, P)
        rows_m.extend(np.sort(np.concatenate([cell_ids[pooled[k]] for k in m])) for m in members)
        rows_g.append(np.full(P, -1, dtype=np.int64))
    n_value = sum(len(x) for x in rows_X)
    dirs = [np.zeros((n_value, d))]

    # tangent-plane rows (and a lone touch's plane points)
    tangent_cells: set[tuple] = set()
    if p.tangent_slope_noise > 0 and d == 3:
        lone = _lone(contacts, cen, p.plane_reach_m)
        none = np.zeros(0, dtype=np.int64)
        rho = p.plane_reach_m
        todo = []  # (group, its two tangents, whether it carries plane points)
        tan_a, tan_b = _tangents(nrm)
        for g in np.flatnonzero(np.any(nrm != 0.0, axis=1)).tolist():
            # (nrm is zero without contacts or where their normals disagree)
            a, b = tan_a[g], tan_b[g]
            if is_settled[g]:  # settled: one event's tangents per voxel (rows bounded by area)
                key = tuple(np.floor(cen[g] / p.settled_voxel_m).astype(np.int64).tolist())
                if key in tangent_cells:
                    continue
                tangent_cells.add(key)
            todo.append((g, a, b, rho > 0 and lone[g] and prior[g] <= p.plane_max_p_false))
        planar = [(g, np.array([a, -a, b, -b])) for g, a, b, on in todo if on]
        keep = _plane_keep(
            np.array([g for g, _ in planar], dtype=np.int64),
            np.array([t for _, t in planar]).reshape(-1, 4, 3),
            cen, nrm, rho, p.plane_guard_m, p.plane_guard_solid_m,
        )  # fmt: skip
        kept = dict(zip([g for g, _ in planar], keep, strict=True))
        for g, a, b, on in todo:
            centre = cen[g]
            owner = -1 if is_settled[g] else g
            extra = [centre, centre]
            dirs.append(np.array([a, b]))
            s2_extra = [p.tangent_slope_noise**2] * 2
            if on:
                qs = [centre + rho * t for t, k in zip((a, -a, b, -b), kept[g], strict=True) if k]
                extra += qs
                dirs.append(np.zeros((len(qs), 3)))
                s2_extra += [p.contact_noise**2 + (p.plane_noise_per_m * rho) ** 2] * len(qs)
            rows_X.append(np.array(extra))
            rows_y.append(np.zeros(len(extra)))
            rows_s2.append(np.array(s2_extra))
            rows_n.append(np.zeros((len(extra), d)))
            rows_m.extend([none] * len(extra))
            rows_g.append(np.full(len(extra), owner, dtype=np.int64))

    t_lo = np.full(G, np.iinfo(np.int64).max)
    t_hi = np.full(G, np.iinfo(np.int64).min)
    np.minimum.at(t_lo, g_of, col.t[shape])
    np.maximum.at(t_hi, g_of, col.t[shape])
    t_span = list(zip(t_lo.tolist(), t_hi.tolist(), strict=True))
    n_rows = sum(len(x) for x in rows_X)
    companion = None
    crossed = np.zeros(G, dtype=bool)
    if p.companion_s > 0:
        companion = np.full(n_rows, -1, dtype=np.int64)
        companion[: free_rows.size], crossed = _companions(
            col.X[free_rows], col.t[free_rows], cen, nrm, t_lo, t_hi, is_settled,
            p.body_reach_m, COMPANION_CLEARANCE / slope, p.companion_s,
            _body_extent(nrm, p) if p.body_clearance and d == 3 else None,
        )  # fmt: skip
        crossed &= ~_coplanar_vouched(cen, nrm, guard, 2.0 * p.sweep_disc_m)
    burst = _bursts(t_span, list(cen), p)
    size = np.bincount(burst, minlength=int(burst.max(initial=-1)) + 1) if burst.size else burst
    clustered = size[burst] >= p.burst_events_min if burst.size else np.zeros(0, dtype=bool)
    clustered &= prior >= p.burst_min_p_false  # impacts the detector vouches for: a pilot tapping
    is_free = col.label > 0
    swept = _swept(contacts, cen, nrm, t_span, col.X[is_free], col.t[is_free], guard, p)
    swept |= crossed
    return TrainingSet(
        X=np.concatenate(rows_X).reshape(-1, d),
        directions=np.concatenate(dirs).reshape(-1, d),
        y=np.concatenate(rows_y).astype(np.float64),
        noise_var=np.concatenate(rows_s2).astype(np.float64),
        normals=np.concatenate(rows_n).reshape(-1, d),
        row_members=tuple(np.asarray(m, dtype=np.int64) for m in rows_m),
        groups=Groups(
            row_group=np.concatenate(rows_g).astype(np.int64),
            prior_false=prior.astype(np.float64),
            burst=burst,
            extra_llr=np.where(swept, p.sweep_llr, 0.0) + np.where(clustered, p.burst_llr, 0.0),
            companion=companion,
        ),
        event_ids=event_ids.astype(np.int64),
        group_ids=tuple(ids_of),
        swept=swept,
        keys=gkeys,
        t_end_ns=t_hi,
        settled=is_settled,
        n_raw=len(obs),
        corroborators=_corroborators(contacts, cen, p.lone_reach_m),
    )


def _centres_normals(
    X: np.ndarray, N: np.ndarray, g: np.ndarray, G: int
) -> tuple[np.ndarray, np.ndarray]:
    """(G, d) contact centroid (NaN without contacts) and unit mean normal (0 where the
    normals do not agree on one) of every group, from its contacts ``X``, normals ``N``."""
    d = X.shape[1]
    cnt = np.bincount(g, minlength=G).astype(np.float64)
    has = cnt > 0
    cen = np.full((G, d), np.nan)
    cen[has] = _sums(g, X, G)[has] / cnt[has, None]
    mean_n = _sums(g, N, G) / np.maximum(cnt, 1.0)[:, None]
    norm = np.linalg.norm(mean_n, axis=1)
    nrm = np.zeros((G, d))
    ok = has & (norm >= 0.5)
    nrm[ok] = mean_n[ok] / norm[ok, None]
    return cen, nrm


def _plane_keep(
    groups: np.ndarray, tangents: np.ndarray, cen: np.ndarray, nrm: np.ndarray, reach: float,
    guard_m: float, solid_m: float,
) -> np.ndarray:  # fmt: skip
    """(m, k) bool: which plane points ``cen[groups[i]] + reach * tangents[i, j]`` are kept,
    for every group at once (the touches near each point found in one k-d tree query). A
    plane point is left out where the touches near it say the surface does not go on flat
    to it:

    - *past an edge*: another touch places the point outside its own surface (by more than
      ``PLANE_BEYOND_TOL_M`` along its normal): any touch within ``guard_m`` (a believed gust
      in front of a touched face loses its points in front of it), or within ``solid_m`` a
      face of the same solid (each touch on or behind the other's tangent plane). A deck's
      side touched 7 cm above its lower edge puts a plane point 13 cm below the deck; the
      underside touched 0.8 m along says the side stops there;
    - *round a bend*: another touch within ``PLANE_GUARD_REACHES * reach`` lies ahead along
      ``t``, behind this touch's tangent plane (by more than ``PLANE_BEYOND_TOL_M``), with its
      normal turned towards ``t`` (by more than ``PLANE_TURN_SIN``), where a circle through
      both touches would put it (within ``PLANE_BEND_RATIO``): the surface curves away, as on
      a pillar touched at two sides. A box touched on two faces equally far from their edge
      looks the same; there the plane is left out too, and the GP's own smooth
      interpolation decides.
    """
    m, k = tangents.shape[:2]
    keep = np.ones((m, k), dtype=bool)
    valid = np.flatnonzero(np.isfinite(cen).all(axis=1) & nrm.any(axis=1))
    if m == 0 or valid.size == 0:
        return keep
    from scipy.spatial import cKDTree

    bend_reach = PLANE_GUARD_REACHES * reach
    centre = cen[groups]  # (m, 3)
    Q = (centre[:, None, :] + reach * tangents).reshape(-1, 3)  # (m k, 3)
    near = cKDTree(cen[valid]).query_ball_point(Q, max(guard_m, solid_m, bend_reach))
    counts = np.fromiter((len(x) for x in near), dtype=np.int64, count=len(near))
    qi = np.repeat(np.arange(Q.shape[0]), counts)
    j = valid[np.fromiter((v for x in near for v in x), dtype=np.int64, count=int(counts.sum()))]
    gi = qi // k
    mine = j != groups[gi]
    qi, j, gi = qi[mine], j[mine], gi[mine]
    t = tangents.reshape(-1, 3)[qi]
    n_g = nrm[groups[gi]]
    n_j = nrm[j]
    dist = np.linalg.norm(Q[qi] - cen[j], axis=1)
    off = cen[j] - centre[gi]  # from the touch to its neighbour
    behind = -np.einsum("ij,ij->i", off, n_g)  # h: how far behind the tangent plane
    solid = one_solid(centre[gi], n_g, cen[j], n_j)
    past_edge = ((dist <= guard_m) | (solid & (dist <= solid_m))) & (
        np.einsum("ij,ij->i", Q[qi] - cen[j], n_j) > PLANE_BEYOND_TOL_M
    )
    cos = np.clip(np.einsum("ij,ij->i", n_j, n_g), -1.0, 1.0)
    turn = n_j - cos[:, None] * n_g  # the way the normal turns, in the plane
    turn /= np.maximum(np.linalg.norm(turn, axis=1, keepdims=True), 1e-12)
    ahead = np.einsum("ij,ij->i", off, turn)  # s: how far ahead that way
    # on a circle through both touches h / s = tan(theta / 2), theta the normals' turn
    half = np.tan(np.arccos(cos) / 2)
    bend = (
        (dist <= bend_reach)
        & (np.einsum("ij,ij->i", off, t) > 0)
        & (behind > PLANE_BEYOND_TOL_M)
        & (np.einsum("ij,ij->i", n_j, t) > PLANE_TURN_SIN)
        & (behind < PLANE_BEND_RATIO * half * ahead)
        & (behind * PLANE_BEND_RATIO > half * ahead)
    )
    bad = np.bincount(qi[past_edge | bend], minlength=Q.shape[0]) > 0
    return keep & ~bad.reshape(m, k)


def _corroborators(
    contacts: list[np.ndarray], centres: np.ndarray, radius: float
) -> tuple[np.ndarray | None, ...]:
    """For each group with contacts and a finite centroid ``centres[g]``, the other groups
    with a contact within ``radius`` of it, sorted (None for the others, and for every group
    with ``radius`` <= 0)."""
    out: list[np.ndarray | None] = [None] * len(contacts)
    sizes = [len(cs) for cs in contacts]
    if radius <= 0 or not sum(sizes):
        return tuple(out)
    from scipy.spatial import cKDTree

    owner = np.repeat(np.arange(len(contacts)), sizes)
    has = np.flatnonzero((np.asarray(sizes) > 0) & np.all(np.isfinite(centres), axis=1))
    if not has.size:
        return tuple(out)
    i, j = _pairs_within(cKDTree(centres[has]), cKDTree(np.concatenate(contacts)), radius)
    G = len(contacts)
    g, who = has[i], owner[j]
    pair = np.unique((g * G + who)[who != g])  # by group, then the other group
    first, other = pair // G, pair % G
    cuts = np.searchsorted(first, has)
    ends = np.searchsorted(first, has, side="right")
    for k, gk in enumerate(has.tolist()):
        out[gk] = other[cuts[k] : ends[k]]
    return tuple(out)


def _lone(contacts: list[np.ndarray], centres: np.ndarray, radius: float) -> np.ndarray:
    """(G,) bool: no other group's contact lies within ``radius`` of the group's contact
    centroid ``centres[g]`` (groups without contacts or a finite centroid count as lone;
    ``radius`` <= 0: every group)."""
    near = _corroborators(contacts, centres, radius)
    return np.array([c is None or c.size == 0 for c in near], dtype=bool)


def _faces(n: np.ndarray) -> np.ndarray:
    """(k,) int64: the signed axis each normal (row of ``n``) points along most (+1..+d,
    -1..-d; 0 for none)."""
    n = np.asarray(n, dtype=np.float64).reshape(len(n), -1)
    k = np.argmax(np.abs(n), axis=1) if n.shape[1] else np.zeros(len(n), dtype=np.int64)
    lead = n[np.arange(len(n)), k] if n.shape[1] else np.zeros(len(n))
    out = (k + 1) * np.where(lead > 0, 1, -1)
    none = ~np.all(np.isfinite(n), axis=1) | (np.abs(lead) == 0.0)
    return np.where(none, 0, out).astype(np.int64)


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


def _companions(
    X: np.ndarray, t: np.ndarray, centres: np.ndarray, normals: np.ndarray,
    t_lo: np.ndarray, t_hi: np.ndarray, settled: np.ndarray, reach: float, clearance: float,
    window_s: float, extent: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The group each free row ``X`` (taken at ``t``) is a companion of, -1 for none: the
    nearest in time of the unsettled groups with a contact plane whose time span it lies
    within ``window_s`` of, in front of that plane by less than ``clearance`` and within
    ``reach`` (the body's) of its contacts' centroid (module docstring); and (G,) bool, the
    groups whose plane the body *crossed* there.

    With ``extent`` ((G,) metres: :func:`_body_extent`, the least distance the body's centre
    keeps in front of a plane it touches, less the tolerance), a row nearer a group's plane
    than that is no companion of it: the body at that row reached past the plane within its
    own reach of the contact, which the body of a true touch cannot, and the group is crossed.
    """
    out = np.full(X.shape[0], -1, dtype=np.int64)
    crossed = np.zeros(len(centres), dtype=bool)
    if X.shape[0] == 0:
        return out, crossed
    best = np.full(X.shape[0], np.inf)
    w = int(window_s * 1e9)
    ok = np.any(normals != 0.0, axis=1) & np.all(np.isfinite(centres), axis=1) & ~settled
    for g in np.flatnonzero(ok):
        near = np.flatnonzero((t >= t_lo[g] - w) & (t <= t_hi[g] + w))
        if near.size == 0:
            continue
        dx = X[near] - centres[g]
        ahead = dx @ normals[g]
        mine = (ahead > 0.0) & (ahead < clearance) & (np.linalg.norm(dx, axis=1) <= reach)
        if extent is not None:
            past = mine & (ahead < extent[g])
            crossed[g] = bool(past.any())
            mine &= ~past
        gap = np.maximum(t_lo[g] - t[near], t[near] - t_hi[g]).astype(np.float64)
        take = mine & (gap < best[near])
        out[near[take]] = g
        best[near[take]] = gap[take]
    return out, crossed


def _body_extent(normals: np.ndarray, p: TrainingPolicy) -> np.ndarray:
    """(G,) metres: how far in front of a contact's tangent plane (unit outward ``normals``,
    (G, 3); zero rows: none) the vehicle's centre at least stays while its body touches
    there, less ``sweep_tolerance_m`` (the contact's placement error): the support distance of
    the body's inner cylinder (``body_radius_m`` across, ``body_half_height_m`` up and down,
    level), which the body fills whatever its yaw, least over the directions within
    ``NORMAL_ERROR_DEG`` of the normal (a contact under a deck whose normal the detector tilts
    by 10 degrees would otherwise ask for its centre 3 cm lower). The cylinder's side touch
    keeps its centre 0.2 m in front; its top or bottom touch, 0.05 m."""
    n = np.asarray(normals, dtype=np.float64)
    phi = np.arccos(np.clip(np.abs(n[:, 2]), 0.0, 1.0))  # from the vertical, in [0, pi/2]
    err = math.radians(NORMAL_ERROR_DEG)
    psi = np.clip(phi[:, None] + np.linspace(-err, err, 9)[None, :], 0.0, math.pi / 2)
    support = p.body_radius_m * np.sin(psi) + p.body_half_height_m * np.cos(psi)
    return np.where(n.any(axis=1), support.min(axis=1) - p.sweep_tolerance_m, -np.inf)


def _coplanar_vouched(
    centres: np.ndarray, normals: np.ndarray, guard: np.ndarray, radius: float
) -> np.ndarray:
    """(G,) bool: groups another ``guard`` group vouches for: a contact centroid within
    ``radius`` of theirs, each within twice ``PLANE_BEYOND_TOL_M`` of the other's plane and
    with a normal within ``NORMAL_ERROR_DEG`` of theirs (the same face). Where two touches
    the detector believes show one plane, the surface is there, and a body sampled nearer it
    than the level body can be was not level (a vehicle tumbling along a deck's side after a
    hard hit)."""
    G = len(centres)
    out = np.zeros(G, dtype=bool)
    ok = np.flatnonzero(np.all(np.isfinite(centres), axis=1) & np.any(normals != 0.0, axis=1))
    if ok.size < 2 or radius <= 0:
        return out
    from scipy.spatial import cKDTree

    pairs = cKDTree(centres[ok]).query_pairs(radius, output_type="ndarray")
    if not len(pairs):
        return out
    a, b = ok[pairs[:, 0]], ok[pairs[:, 1]]
    off = centres[b] - centres[a]
    same = (
        (np.einsum("ij,ij->i", normals[a], normals[b]) >= math.cos(math.radians(NORMAL_ERROR_DEG)))
        & (np.abs(np.einsum("ij,ij->i", off, normals[a])) <= 2.0 * PLANE_BEYOND_TOL_M)
        & (np.abs(np.einsum("ij,ij->i", off, normals[b])) <= 2.0 * PLANE_BEYOND_TOL_M)
    )
    out[a[same & guard[b]]] = True
    out[b[same & guard[a]]] = True
    return out


def _swept(
    contacts, centres, normals, t_span, free_pts: np.ndarray, free_t: np.ndarray,
    guard: np.ndarray, p: TrainingPolicy,
) -> np.ndarray:  # fmt: skip
    """Which groups' contact points, or the rim of their tangent disc (``sweep_disc_m`` round
    the contacts' centroid, across their mean normal), lie inside the body at a free-space
    sample away from them. A rim point past an edge (``_past_edge``: a ``guard`` touch of
    another event places it outside its own surface) is no probe: the surface ends before it."""
    G = len(contacts)
    out = np.zeros(G, dtype=bool)
    if G == 0 or free_pts.shape[0] == 0 or free_pts.shape[1] != 3:
        return out
    if p.body_radius_m <= 0 or p.body_half_height_m <= 0:
        return out
    sizes = [len(cs) for cs in contacts]
    if not sum(sizes):
        return out
    free = _Sweep.of(free_pts, free_t, p)
    pts = np.concatenate([cs for cs in contacts if len(cs)])
    owner = np.repeat(np.arange(G), sizes)
    _inside_body(free, pts, normals[owner], owner, t_span, p, out)
    rim_of = np.flatnonzero((np.asarray(sizes) > 0) & ~out & np.any(normals != 0.0, axis=1))
    if p.sweep_disc_m > 0 and rim_of.size:  # only the groups the points left standing
        rims = _rims(centres[rim_of], normals[rim_of], p.sweep_disc_m).reshape(-1, 3)
        owner = np.repeat(rim_of, DISC_POINTS)
        keep = ~_past_edge(
            rims, owner, centres, normals, guard, PLANE_GUARD_REACHES * p.sweep_disc_m
        )
        _inside_body(free, rims[keep], normals[owner[keep]], owner[keep], t_span, p, out)
    return out


def _past_edge(
    pts: np.ndarray, owner: np.ndarray, centres: np.ndarray, normals: np.ndarray,
    guard: np.ndarray, radius: float, tilt_deg: float = 0.0,
) -> np.ndarray:  # fmt: skip
    """(k,) bool: point ``pts[k]`` of group ``owner[k]`` lies past an edge: a ``guard`` group
    other than its own, with a contact plane and its centroid within ``radius`` of the point,
    places it outside its surface (by more than ``PLANE_BEYOND_TOL_M`` along its normal), as
    ``_plane_keep`` does, where the two touches are faces of one solid (each lies on or behind
    the other's tangent plane). The deck's end face touched near its lower edge has half its
    sweep disc below the deck, where the vehicle flies later; the underside's touches say that
    the end face stops there. A touch near an edge with its normal tilted across it has its
    internal row (behind the contact along that normal) past the other face."""
    out = np.zeros(len(pts), dtype=bool)
    ok = guard & np.all(np.isfinite(centres), axis=1) & np.any(normals != 0.0, axis=1)
    by = np.flatnonzero(ok)
    if not by.size or not len(pts):
        return out
    from scipy.spatial import cKDTree

    i, j = _pairs_within(cKDTree(pts), cKDTree(centres[by]), radius)  # (probe, guard) pairs
    j = by[j]
    g = owner[i]
    beyond = np.einsum("ij,ij->i", pts[i] - centres[j], normals[j]) > PLANE_BEYOND_TOL_M
    # a gust in the free space in front of a touched wall is not behind that wall
    pair = one_solid(centres[g], normals[g], centres[j], normals[j], tilt_deg)
    out[i[beyond & pair & (j != g)]] = True
    return out


def one_solid(
    a: np.ndarray, na: np.ndarray, b: np.ndarray, nb: np.ndarray, tilt_deg: float = 0.0
) -> np.ndarray:
    """(k,) bool: touches ``a[k]`` and ``b[k]`` (outward normals ``na``, ``nb``) may be faces
    of one solid: each lies on or behind the other's tangent plane, within
    ``PLANE_BEYOND_TOL_M`` plus their distance times ``sin(tilt_deg)`` (``mapping.
    internal_guard_tilt_deg``): a normal the detector tilts by that much moves the other
    touch that far in front of its plane, 6 cm for 8 deg across a 0.42 m box corner."""
    tol = PLANE_BEYOND_TOL_M
    if tilt_deg > 0.0:
        tol = tol + np.linalg.norm(a - b, axis=1) * math.sin(math.radians(tilt_deg))
    return (np.einsum("ij,ij->i", a - b, nb) <= tol) & (np.einsum("ij,ij->i", b - a, na) <= tol)


def _inside_body(
    free: _Sweep, pts, normals, owner, t_span, p: TrainingPolicy, out: np.ndarray
) -> None:
    """Set ``out[owner[k]]`` where probe ``pts[k]`` lies inside the body at a free-space sample
    of ``free`` taken ``sweep_exclude_s`` or more away from its group's time span, wherever
    it really was: within ``sweep_tolerance_m`` along its unit normal ``normals[k]`` (both ends
    of that segment inside the body) with ``tolerance_along_normal``, else (or without a
    normal: zero) anywhere within the tolerance (the body shrunk by it all round).

    A probe inside the body (either way) lies in the box of half-widths (R, R, H) round the
    sample, so the candidate pairs come from a box query on z scaled by R / H (a sphere round
    the cylinder holds twice as many); the test then runs on coordinate columns. A pass over
    ``free.coarse`` (every ``SWEEP_COARSE``-th sample) comes first: a group needs one sample
    inside, and one where the vehicle lingered has hundreds, so the full pass is left with
    the probes of the groups the coarse one did not settle."""
    for sub in (free.coarse, free):
        todo = ~out[owner]
        if sub is not None and todo.any():
            _inside_body_pass(sub, pts[todo], normals[todo], owner[todo], t_span, p, out)


def _inside_body_pass(
    free: _Sweep, pts, normals, owner, t_span, p: TrainingPolicy, out: np.ndarray
) -> None:
    """One pass of :func:`_inside_body` over the samples of ``free``."""
    if not len(pts):
        return
    R, H, tol = p.body_radius_m, p.body_half_height_m, p.sweep_tolerance_m
    from scipy.spatial import cKDTree

    probes = cKDTree(pts * free.scale)
    i, j = _pairs_within(probes, free.tree, R * (1.0 + 1e-9), np.inf)  # the box, rounding kept in
    if not i.size:
        return
    excl = int(p.sweep_exclude_s * 1e9)
    lo = np.array([s[0] for s in t_span], dtype=np.int64)[owner] - excl
    hi = np.array([s[1] for s in t_span], dtype=np.int64)[owner] + excl
    tj = free.t[j]
    away = (tj < lo[i]) | (tj > hi[i])  # a sample away from the event
    i, j = i[away], j[away]
    has_n = np.any(normals != 0.0, axis=1) & p.tolerance_along_normal  # per probe
    fx, fy, fz = free.X[:, 0][j], free.X[:, 1][j], free.X[:, 2][j]
    inside = has_n[i]
    for sign in (-1.0, 1.0):  # both ends of the probe's tolerance segment
        q = pts - sign * tol * normals  # (sample - end) = (sample - probe) + sign * tol * n
        ex, ey, ez = fx - q[:, 0][i], fy - q[:, 1][i], fz - q[:, 2][i]
        inside &= (np.hypot(ex, ey) < R) & (np.abs(ez) < H)
    ex, ey, ez = fx - pts[:, 0][i], fy - pts[:, 1][i], fz - pts[:, 2][i]
    inside |= ~has_n[i] & (np.hypot(ex, ey) < R - tol) & (np.abs(ez) < H - tol)
    out[owner[i[inside]]] = True


@dataclasses.dataclass(frozen=True)
class _Sweep:
    """The free-space samples the body's swept volume is tested at: positions ``X`` (n, 3),
    times ``t`` (n,) and a ``tree`` of the positions with z scaled by ``scale[2]`` = R / H
    (``_inside_body``'s box query)."""

    X: np.ndarray
    t: np.ndarray
    tree: object
    scale: np.ndarray
    coarse: _Sweep | None = None  # every SWEEP_COARSE-th sample

    @classmethod
    def of(cls, X: np.ndarray, t: np.ndarray, p: TrainingPolicy, stride: int = 1) -> _Sweep:
        from scipy.spatial import cKDTree

        scale = np.array([1.0, 1.0, p.body_radius_m / p.body_half_height_m])
        coarse = None
        if stride == 1 and len(X) > SWEEP_COARSE:
            coarse = cls.of(X[::SWEEP_COARSE], t[::SWEEP_COARSE], p, SWEEP_COARSE)
        return cls(X=X, t=t, tree=cKDTree(X * scale), scale=scale, coarse=coarse)


def _pairs_within(a, b, radius: float, norm: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """Every (index in ``a``, index in ``b``) pair of points of the two ``cKDTree`` within
    ``radius`` of each other in the Minkowski ``norm`` (in no particular order), as two int64
    arrays: built in C (``sparse_distance_matrix``), not from per-point Python lists."""
    pairs = a.sparse_distance_matrix(b, radius, p=norm, output_type="ndarray")
    return pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)


#: ``_inside_body`` tests every this many free-space samples first (the full set after).
SWEEP_COARSE = 8

#: Points on the rim of a contact's tangent disc (``_rims``).
DISC_POINTS = 12


def _tangents(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit tangents (k, 3) across each unit normal (k, 3): ``a`` = n x z (n x x for a
    normal within ~25 deg of vertical), ``b`` = n x a (zero rows give NaN)."""
    ref = np.where((np.abs(normals[:, 2]) < 0.9)[:, None], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    a = np.cross(normals, ref)
    with np.errstate(invalid="ignore", divide="ignore"):
        a /= np.linalg.norm(a, axis=1, keepdims=True)
    return a, np.cross(normals, a)


def _rims(centres: np.ndarray, normals: np.ndarray, radius: float) -> np.ndarray:
    """(k, DISC_POINTS, 3): the rim of the disc of ``radius`` round each centre (k, 3), in
    the plane across its unit normal (k, 3)."""
    a, b = _tangents(normals)
    ang = np.linspace(0.0, 2.0 * np.pi, DISC_POINTS, endpoint=False)
    c, s = np.cos(ang)[None, :, None], np.sin(ang)[None, :, None]
    return centres[:, None, :] + radius * (c * a[:, None, :] + s * b[:, None, :])
