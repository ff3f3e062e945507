"""Score a pipeline run against the recording's ground truth (pure; truth = ``sitl-truth/1``).

Metrics (all distances in metres)
---------------------------------
``chamfer_m``
    Symmetric Chamfer distance (``mapping.metrics.chamfer_distance``) between the mesh and the
    true surface, both restricted to the part of the structure the flight *touched*: points
    within ``touched_radius_m`` (0.5 m, about two length scales) of a true touch contact point
    (kinds ``touch`` and ``slow_touch``). A touch-built map can only know the surface near its
    touches; elsewhere it is the GP prior, which no flight could have corrected.
``chamfer_full_m``
    The same, unrestricted: the whole mesh against the whole true surface inside the region.
``shape_error_m``
    The paper's band metric: mean distance to the true surface of the points where the
    estimate puts its surface. The mesh vertices are the points with mu = 0 on the grid (the
    band |mu| < 0.01 in the limit of a fine grid), so it is their mean distance.
``mesh_to_truth_median_m``
    Median distance of the mesh (area-uniform samples) to the true surface.
``truth_to_mesh_median_m``, ``missing_share``
    Over the touched true surface (within ``touched_radius_m`` of a true touch): median distance
    to the mesh, and the share farther than ``missing_m`` (0.1 m) from it: surface the map lacks.
    The true surface sampled here and in both Chamfer distances is the surface that exists
    (``Scene.sample_surface``): faces resting on the floor or lying inside or against another
    structure (a pillar's top under a deck) are left out, and structures count by area.
``missing_share_near``
    The same share within ``near_radius_m`` (0.2 m) of a true touch: the surface the touches
    themselves lie on. The gap between the two is surface the map would have to extrapolate
    from 0.2 to 0.5 m beyond a touch (round a corner, down a face no touch reached).
``touched_area_near_m2``, ``missing_area_near_m2``
    The area of that true surface within ``near_radius_m`` of a true touch, and the part of
    it that is missing (``missing_share_near`` times it), m². A bench pools them into the share
    of all the touched surface of many flights that is missing (``pipeline.pooling``): the
    mean of ``missing_share_near`` over flights weighs a flight with one touch as much as one
    with fifty.
``missing_share_near_detected``, ``touched_area_near_detected_m2``,
``missing_area_near_detected_m2``
    The same three over the surface within ``near_radius_m`` of the true touches the detector
    reported (a detected event matched to the touch, flagged or not): what the map lost of
    what it was told. The rest of ``missing_area_near_m2`` lies near touches no detected
    event matched (a slow touch the detector missed, a touch inside another's event, a vehicle
    lying against a structure after a crash), which no map can draw. On a flight with one or
    two touches one such miss is most of ``missing_share_near``. NaN when no detected event
    matched a touch.
``phantom_area_m2``, ``phantom_max_patch_m2``
    Mesh faces farther than ``phantom_m`` (0.15 m) from the true surface, joined into patches
    by shared vertices: their total area and the largest patch's (surface the map invents).
    Here, in ``mesh_to_truth_median_m`` and in ``shape_error_m`` the true surface includes the
    floor (:func:`distance_to_world`): a drone pushed onto it has touched real surface.
``phantom_patches``
    The three largest of those patches, largest first, each with its area, centre, bounding
    box and farthest distance to the truth (``mapping.metrics.PhantomPatch``): where the map
    invents surface, to look at in the viewer. Each also says what drew it
    (:func:`patch_sources`): ``events``, the detected events with a contact point within
    ``PATCH_REACH_M`` of its bounding box (id, truth kind, flagged), and ``cause``, from the
    ones the map kept: ``false contact`` (a gust, a floor impact or a detector false alarm),
    else ``touch placed off the surface`` (a true touch whose contacts lie more than 0.1 m from
    any real surface), else ``touches`` (true touches on the surface: the shape the map drew
    between or behind them), else ``no kept contact``. ``phantom_max_patch_cause`` is the
    largest patch's cause (None without a patch).
``mask_curve``
    The same surface metrics (:data:`CURVE_KEYS`) of the final mesh kept at each stricter
    confidence mask of :data:`MASK_CURVE` (``surface.max_std_fraction``: faces whose vertices'
    predictive std is at most that fraction of the prior std), one row per mask below the
    configured one (:func:`mask_curve`). The mask is the one knob between surface missing and
    phantom surface: a map that meets the phantom line only at a stricter mask pays for it in
    missing surface, and the row says how much, from the same run.
``gust_events_flagged``, ``touch_events_flagged``
    Shares of detected events matched to truth gusts / touches that the map flags false.
``events_touch_mislocated``, ``touch_events_flagged_on_surface``, ``mislocated_touches_flagged``
    A touch event is *mislocated* when the contact points the detector placed for it lie
    farther than ``missing_m`` (0.1 m, their median distance) from any real surface: the
    vehicle touched something, but not where the map was told (a tilted normal, a tumble, a
    touch on a guard's far side). Drawing such a contact draws phantom surface, so flagging it
    is right for the map, and ``touch_events_flagged`` counts it as a loss all the same. These
    keys split it: the number of mislocated touch events, the share of the other touches
    (contacts on the surface) that the map flags, and the share of the mislocated ones it
    flags. Events whose contact points are unknown count as on the surface.
``slow_touch_events_flagged``, ``events_slow_touch``
    The share of detected events matched to truth slow touches (under 0.2 m/s) that the map
    flags, and their number. They are real contacts and their surface is touched surface, but
    ``touch_events_flagged`` counts only ``touch`` events.
``fp_precision``, ``fp_recall``
    Detected contact events are matched to truth events by time: a detected event whose start
    lies in ``[start - 0.1 s, end + 0.3 s]`` of a truth event matches it (nearest start wins).
    Events matched to a truth ``gust`` are the false contacts. Precision = flagged false /
    flagged; recall = flagged false / detected false. NaN (``null`` in JSON) when undefined.
``events_echo``, ``echo_events_flagged``
    A touch's *echo* is a later detected event matched to the same truth touch that starts
    more than ``ECHO_AFTER_S`` (0.05 s) after the touch ended: the vehicle's own reaction to
    the touch (its controller swinging the thrust back, 0.15-0.3 s later on the MuJoCo
    airframe's guard touches, an impulse along the body axis), not a contact. Its contact
    points lie where the vehicle was then, up to 0.45 m from any surface, so flagging it is
    right; it counts as a false contact (for ``patch_sources`` too), not as a touch, and these
    keys give how many there were and the share the map flags. Before this rule an echo
    counted as a flagged touch placed off the surface. An event that starts while the touch
    lasts (a long slide detected twice) stays a touch.
``detection_recall``
    Truth ``touch`` events matched by at least one detected event / truth touches.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from groundstation.errors import InputDataError
from groundstation.mapping.metrics import chamfer_distance, phantom_patches, sample_mesh_faces
from groundstation.mapping.surface import SurfaceMesh, confident_part

MATCH_BEFORE_S = 0.1
MATCH_AFTER_S = 0.3
#: A later event matched to a touch that started this long after the touch ended is its echo.
ECHO_AFTER_S = 0.05
ECHO_KINDS = ("touch", "slow_touch")
PHANTOM_LISTED = 3  # largest phantom patches listed by where they lie
#: A detected event drew a phantom patch when one of its contact points lies within this of
#: the patch's bounding box: the patch is surface over 0.15 m from the truth, and the blob a
#: contact draws reaches a length scale or two (0.2-0.5 m) from it.
PATCH_REACH_M = 0.3
#: What drew a patch, in the order :func:`patch_sources` decides it.
PATCH_CAUSES = ("false contact", "touch placed off the surface", "touches", "no kept contact")


@dataclasses.dataclass(frozen=True)
class DetectedEvent:
    """A detected contact event: id, start time on the log axis (ns), flagged or not, and the
    contact points the detector placed for it (world metres; empty when unknown)."""

    id: int
    t_start_ns: int
    flagged: bool = False
    points: tuple[tuple[float, float, float], ...] = ()


def match_events(events: Sequence[DetectedEvent], truth: dict) -> dict[int, tuple[int, str] | None]:
    """Detected event id -> (truth contact index, kind), or None when nothing matches.

    An event matched to a touch (``touch``, ``slow_touch``) that starts more than
    ``ECHO_AFTER_S`` after that touch ended, when an earlier event already matched it, is the
    touch's *echo*, kind ``"echo"`` (module docstring)."""
    offset = int(truth.get("clock", {}).get("station_offset_ns", 0))
    contacts = truth.get("contacts", [])
    out: dict[int, tuple[int, str] | None] = {}
    starts: dict[int, float] = {}
    for ev in events:
        t = (ev.t_start_ns - offset) / 1e9
        starts[ev.id] = t
        best: tuple[float, int] | None = None
        for k, c in enumerate(contacts):
            if c["start"] - MATCH_BEFORE_S <= t <= c["end"] + MATCH_AFTER_S:
                d = abs(t - c["start"])
                if best is None or d < best[0]:
                    best = (d, k)
        out[ev.id] = None if best is None else (best[1], contacts[best[1]]["kind"])
    first: dict[int, float] = {}
    for eid, m in out.items():
        if m is not None:
            first[m[0]] = min(first.get(m[0], math.inf), starts[eid])
    for eid, m in out.items():
        if m is None or m[1] not in ECHO_KINDS:
            continue
        end = float(contacts[m[0]]["end"])
        if first[m[0]] < starts[eid] and starts[eid] > end + ECHO_AFTER_S:
            out[eid] = (m[0], "echo")
    return out


def false_positive_scores(
    events: Sequence[DetectedEvent], truth: dict, *, mislocated_m: float = 0.1
) -> dict[str, float]:
    """``mesh_to_truth_median_m``
        Median distance of the mesh (area-uniform samples) to the true surface.
    ``truth_to_mesh_median_m``, ``missing_share``
        Over the touched true surface (within ``touched_radius_m`` of a true touch): median
        distance to the mesh, and the share farther than ``missing_m`` (0.1 m) from it: surface
        the map lacks.
    ``phantom_area_m2``, ``phantom_max_patch_m2``
        Mesh faces farther than ``phantom_m`` (0.15 m) from the true surface, joined into patches
        by shared vertices: their total area and the largest patch's (surface the map invents).
    ``gust_events_flagged``, ``touch_events_flagged``
        Shares of detected events matched to truth gusts / touches that the map flags false.
    ``events_touch_mislocated``, ``touch_events_flagged_on_surface``,
    ``mislocated_touches_flagged``
        Touch events whose contact points lie (median) more than ``mislocated_m`` from any real
        surface, the share of the other touch events flagged, and of the mislocated ones.
    ``slow_touch_events_flagged``, ``events_slow_touch``
        Share of detected events matched to truth slow touches that the map flags, and their
        number.
    ``echo_events_flagged``, ``events_echo``
        Share of the touches' echoes (:func:`match_events`) that the map flags, and their number.
    ``fp_precision``, ``fp_recall``, ``detection_recall`` and the counts behind them."""
    m = match_events(events, truth)
    false = {e.id for e in events if m[e.id] is not None and m[e.id][1] == "gust"}
    flagged = {e.id for e in events if e.flagged}
    touches = [k for k, c in enumerate(truth.get("contacts", [])) if c["kind"] == "touch"]
    found = {v[0] for v in m.values() if v is not None and v[1] == "touch"}
    tp = len(false & flagged)
    gusts = {e.id for e in events if m[e.id] is not None and m[e.id][1] == "gust"}
    touched = {e.id for e in events if m[e.id] is not None and m[e.id][1] == "touch"}
    slow = {e.id for e in events if m[e.id] is not None and m[e.id][1] == "slow_touch"}
    echoes = {e.id for e in events if m[e.id] is not None and m[e.id][1] == "echo"}
    off = _mislocated([e for e in events if e.id in touched], truth, mislocated_m)
    on = touched - off
    return {
        "gust_events_flagged": len(gusts & flagged) / len(gusts) if gusts else math.nan,
        "touch_events_flagged": len(touched & flagged) / len(touched) if touched else math.nan,
        "events_touch": len(touched),
        "events_touch_mislocated": len(off),
        "touch_events_flagged_on_surface": len(on & flagged) / len(on) if on else math.nan,
        "mislocated_touches_flagged": len(off & flagged) / len(off) if off else math.nan,
        "slow_touch_events_flagged": len(slow & flagged) / len(slow) if slow else math.nan,
        "events_slow_touch": len(slow),
        "echo_events_flagged": len(echoes & flagged) / len(echoes) if echoes else math.nan,
        "events_echo": len(echoes),
        "fp_precision": tp / len(flagged) if flagged else math.nan,
        "fp_recall": tp / len(false) if false else math.nan,
        "detection_recall": len(found & set(touches)) / len(touches) if touches else math.nan,
        "events_false": len(false),
        "events_flagged": len(flagged),
        "events_flagged_false": tp,
        "events_unmatched": sum(v is None for v in m.values()),
        "truth_gusts": sum(c["kind"] == "gust" for c in truth.get("contacts", [])),
        "truth_touches": len(touches),
    }


#: Stricter confidence masks (fractions of the prior std) at which a report also scores the
#: final mesh (:func:`mask_curve`).
MASK_CURVE = (0.55, 0.5, 0.45, 0.4)
#: The surface metrics a row of the mask curve holds.
CURVE_KEYS = (
    "missing_share", "missing_share_near", "touched_area_near_m2", "missing_area_near_m2",
    "phantom_area_m2", "phantom_max_patch_m2", "mesh_to_truth_median_m", "chamfer_m",
)  # fmt: skip


def mask_curve(
    mesh: SurfaceMesh | None, truth: dict, sigma_f: float, fractions: Sequence[float]
) -> list[dict[str, float]]:
    """The :data:`CURVE_KEYS` of ``mesh`` kept at each confidence mask of ``fractions``
    (``surface.confident_part`` at ``fraction * sigma_f``), one dict per fraction with its
    ``max_std_fraction``. ``mesh`` must carry its vertex std and have been masked at no
    stricter a fraction than these (a stricter mask keeps a subset of its faces; a looser one
    would need faces it no longer has). Empty without a mesh with std, or without truth.

    The true surface and the mesh are sampled once (the samples of the whole mesh that lie on
    the kept faces are an area-uniform sample of the kept part), so the rows cost a k-d tree
    and the phantom patches each: scoring each kept mesh afresh took about a second a row."""
    if mesh is None or mesh.std is None or not truth or not truth.get("scene"):
        return []
    if not (math.isfinite(sigma_f) and sigma_f > 0):
        raise InputDataError(f"mask_curve: sigma_f must be a positive number, got {sigma_f!r}")
    ts = _sample_truth(_scene(truth), truth, np.zeros((0, 3)), np.random.default_rng(0))
    ms = None if mesh.is_empty else _sample_mesh(mesh, ts)
    rows = []
    for frac in fractions:
        if ms is None:
            scores = _mesh_free_scores(ts, touched=len(ts.touched) > 0, told=False)
        else:
            keep = np.all(mesh.std[mesh.faces] <= float(frac) * sigma_f, axis=1)
            kept = confident_part(mesh, float(frac) * sigma_f)
            scores = _mesh_scores(kept, ms.restrict(keep), ts)
        rows.append({"max_std_fraction": float(frac), **{k: scores[k] for k in CURVE_KEYS}})
    return rows


def patch_sources(
    patches: Sequence[dict],
    events: Sequence[DetectedEvent],
    truth: dict,
    *,
    reach_m: float = PATCH_REACH_M,
    mislocated_m: float = 0.1,
) -> list[dict]:
    """The ``phantom_patches`` dicts, each with ``events`` and ``cause`` (module docstring).

    An event near a patch that the map flagged drew nothing (it is left out of the map), so it
    is listed and does not decide the cause. A detected event matched to no truth contact is a
    detector false alarm; one matched to a ``ground`` contact hit the floor, which is real
    surface, so a patch beside it is a floor impact placed off the floor: both count as false
    contacts here, as gusts do."""
    m = match_events(events, truth)
    placed = [e for e in events if e.points]
    touch_kinds = ("touch", "slow_touch")
    off = _mislocated(
        [e for e in placed if m[e.id] is not None and m[e.id][1] in touch_kinds],
        truth,
        mislocated_m,
    )
    out = []
    for p in patches:
        lo, hi = np.asarray(p["lo"], dtype=np.float64), np.asarray(p["hi"], dtype=np.float64)
        near = []
        for e in placed:
            pts = np.asarray(e.points, dtype=np.float64).reshape(-1, 3)
            gap = np.maximum(np.maximum(lo - pts, pts - hi), 0.0)
            if float(np.min(np.linalg.norm(gap, axis=1))) <= reach_m:
                near.append(e)
        kind = {e.id: (None if m[e.id] is None else m[e.id][1]) for e in near}
        kept = [e for e in near if not e.flagged]
        if any(kind[e.id] not in touch_kinds for e in kept):
            cause = PATCH_CAUSES[0]
        elif any(e.id in off for e in kept):
            cause = PATCH_CAUSES[1]
        elif kept:
            cause = PATCH_CAUSES[2]
        else:
            cause = PATCH_CAUSES[3]
        listed = [{"id": e.id, "kind": kind[e.id], "flagged": e.flagged} for e in near]
        out.append({**p, "cause": cause, "events": listed})
    return out


def reported_touches(events: Sequence[DetectedEvent], truth: dict) -> np.ndarray:
    """(k, 3) contact points of the true touches (kinds touch/slow_touch) that a detected event
    matched (:func:`match_events`)."""
    contacts = truth.get("contacts", [])
    hit = sorted({v[0] for v in match_events(events, truth).values() if v is not None})
    pts = [
        contacts[k]["point"]
        for k in hit
        if contacts[k]["kind"] in ("touch", "slow_touch") and contacts[k].get("point") is not None
    ]
    return np.asarray(pts, dtype=np.float64).reshape(-1, 3)


def _mislocated(events: Sequence[DetectedEvent], truth: dict, limit_m: float) -> set[int]:
    """Ids of ``events`` whose contact points lie (median) farther than ``limit_m`` from any
    real surface; none without a scene or without points."""
    placed = [e for e in events if e.points]
    if not placed or not truth.get("scene"):
        return set()
    scene = _scene(truth)
    return {
        e.id
        for e in placed
        if float(np.median(distance_to_world(scene, np.asarray(e.points)))) > limit_m
    }


def _scene(truth: dict):
    from firmware_bridge.sitl.scene import parse_scene

    return parse_scene(truth["scene"], truth["scene"].get("name", "scene"))


def distance_to_world(scene, points: np.ndarray) -> np.ndarray:
    """(n,) distance, metres, of ``points`` to the nearest real surface: the structures or the
    floor. Both engines have a floor plane at the region's bottom that the drone touches (truth
    kind ``ground``, e.g. a gust pushing it down); a mesh drawn there is surface that exists,
    not surface the map invents. The floor is not *touched* surface: what the map must cover
    (``missing_share``, Chamfer) stays the structures near true touches."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    d = np.abs(scene.signed_distance(pts))
    return np.minimum(d, np.abs(pts[:, 2] - float(scene.region_min[2])))


def touched_points(truth: dict) -> np.ndarray:
    """(k, 3) true contact points of touches (kinds touch/slow_touch)."""
    pts = [
        c["point"]
        for c in truth.get("contacts", [])
        if c["kind"] in ("touch", "slow_touch") and c.get("point") is not None
    ]
    return np.asarray(pts, dtype=np.float64).reshape(-1, 3)


def _near(points: np.ndarray, centres: np.ndarray, radius: float) -> np.ndarray:
    if points.size == 0 or centres.size == 0:
        return np.zeros(len(points), dtype=bool)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(centres).query(points)
    return d <= radius


@dataclasses.dataclass(frozen=True)
class _TruthSample:
    """The true surface of a scene sampled once, for scoring one mesh or many parts of one.

    ``near_touch``: the samples within the touched radius of a true touch (the surface a
    touch-built map is asked for); ``near`` and ``told``: which of those lie within the near
    radius of a true touch / of a reported one."""

    scene: Any
    touched: np.ndarray
    true_pts: np.ndarray
    near_touch: np.ndarray
    near: np.ndarray
    told: np.ndarray
    touched_near_m2: float
    told_near_m2: float
    touched_radius_m: float
    missing_m: float
    phantom_m: float


@dataclasses.dataclass(frozen=True)
class _MeshSample:
    """Area-uniform samples of a mesh: points, the face each lies on, their distance to the
    world, and which lie within the touched radius of a true touch."""

    points: np.ndarray
    face: np.ndarray
    to_world: np.ndarray
    near_touch: np.ndarray

    def restrict(self, keep_faces: np.ndarray) -> _MeshSample:
        """The samples on the faces ``keep_faces`` (bool per face) keeps."""
        sel = keep_faces[self.face]
        return _MeshSample(self.points[sel], self.face[sel], self.to_world[sel],
                           self.near_touch[sel])  # fmt: skip


def _sample_truth(
    scene,
    truth: dict,
    reported: np.ndarray,
    rng: np.random.Generator,
    *,
    touched_radius_m: float = 0.5,
    near_radius_m: float = 0.2,
    spacing_m: float = 0.02,
    seed: int = 0,
    missing_m: float = 0.1,
    phantom_m: float = 0.15,
) -> _TruthSample:
    touched = touched_points(truth)
    area = _true_area(scene)
    true_pts = scene.sample_surface(rng, int(min(50_000, max(2000, area / spacing_m**2))))
    lo, hi = np.asarray(scene.region_min), np.asarray(scene.region_max)
    true_pts = true_pts[np.all((true_pts >= lo) & (true_pts <= hi), axis=1)]
    near_touch = _near(true_pts, touched, touched_radius_m)
    b = true_pts[near_touch]
    return _TruthSample(
        scene=scene,
        touched=touched,
        true_pts=true_pts,
        near_touch=near_touch,
        near=_near(b, touched, near_radius_m),
        told=_near(b, reported, near_radius_m),
        touched_near_m2=touched_area(scene, touched, near_radius_m, seed=seed),
        told_near_m2=touched_area(scene, reported, near_radius_m, seed=seed),
        touched_radius_m=touched_radius_m,
        missing_m=missing_m,
        phantom_m=phantom_m,
    )


def _sample_mesh(mesh: SurfaceMesh, ts: _TruthSample, *, spacing_m: float = 0.02,
                 seed: int = 0) -> _MeshSample:  # fmt: skip
    v, f = mesh.vertices, mesh.faces
    mesh_area = 0.5 * np.linalg.norm(
        np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1
    )
    n_mesh = int(min(50_000, max(2000, mesh_area.sum() / spacing_m**2)))
    pts, face = sample_mesh_faces(v, f, n_mesh, seed=seed)
    return _MeshSample(
        pts, face, distance_to_world(ts.scene, pts), _near(pts, ts.touched, ts.touched_radius_m)
    )


def _mesh_free_scores(ts: _TruthSample | None, *, touched: bool, told: bool) -> dict[str, Any]:
    """The scores of no mesh: nothing drawn, so all the touched surface is missing."""
    nan: dict[str, Any] = {
        k: math.nan
        for k in (
            "chamfer_m", "chamfer_full_m", "shape_error_m", "mesh_to_truth_median_m",
            "truth_to_mesh_median_m", "phantom_area_m2", "phantom_max_patch_m2",
        )
    }  # fmt: skip
    nan["missing_share"] = 1.0 if touched else math.nan
    nan["missing_share_near"] = nan["missing_share"]
    nan["phantom_patches"] = []
    touched_near = math.nan if ts is None else ts.touched_near_m2
    told_near = math.nan if ts is None else ts.told_near_m2
    nan["touched_area_near_m2"] = touched_near
    nan["missing_area_near_m2"] = touched_near if touched else math.nan
    nan["missing_share_near_detected"] = 1.0 if told else math.nan
    nan["touched_area_near_detected_m2"] = told_near
    nan["missing_area_near_detected_m2"] = told_near if told else math.nan
    return nan


def _mesh_scores(mesh: SurfaceMesh, ms: _MeshSample, ts: _TruthSample) -> dict[str, Any]:
    """The surface metrics of ``mesh`` (samples ``ms``) but the whole-mesh ones
    (``chamfer_full_m``, ``shape_error_m``)."""
    from scipy.spatial import cKDTree

    b = ts.true_pts[ts.near_touch]
    if b.size and len(ms.points):
        d_b, _ = cKDTree(ms.points).query(b)
    else:
        d_b = np.full(len(b), np.inf)
    if b.size:
        t2m, missing = float(np.median(d_b)), float(np.mean(d_b > ts.missing_m))
        missing_near = float(np.mean(d_b[ts.near] > ts.missing_m)) if ts.near.any() else math.nan
        missing_told = float(np.mean(d_b[ts.told] > ts.missing_m)) if ts.told.any() else math.nan
    else:
        t2m, missing, missing_near, missing_told = math.nan, math.nan, math.nan, math.nan
    patches = phantom_patches(
        mesh.vertices, mesh.faces, lambda p: distance_to_world(ts.scene, p),
        threshold=ts.phantom_m,
    )  # fmt: skip
    return {
        "chamfer_m": chamfer_distance(ms.points[ms.near_touch], b),
        "mesh_to_truth_median_m": float(np.median(ms.to_world)) if len(ms.points) else math.nan,
        "truth_to_mesh_median_m": t2m,
        "missing_share": missing,
        "missing_share_near": missing_near,
        "touched_area_near_m2": ts.touched_near_m2,
        "missing_area_near_m2": missing_near * ts.touched_near_m2,
        "missing_share_near_detected": missing_told,
        "touched_area_near_detected_m2": ts.told_near_m2,
        "missing_area_near_detected_m2": missing_told * ts.told_near_m2,
        "phantom_area_m2": float(sum(p.area_m2 for p in patches)),
        "phantom_max_patch_m2": patches[0].area_m2 if patches else 0.0,
        "phantom_patches": [p.as_dict() for p in patches[:PHANTOM_LISTED]],
    }


def surface_scores(
    mesh: SurfaceMesh | None,
    truth: dict,
    *,
    touched_radius_m: float = 0.5,
    near_radius_m: float = 0.2,
    spacing_m: float = 0.02,
    seed: int = 0,
    missing_m: float = 0.1,
    phantom_m: float = 0.15,
    detected: np.ndarray | None = None,
) -> dict[str, Any]:
    """The surface metrics of the module docstring (floats, and ``phantom_patches``); NaN when
    there is no mesh, and then ``missing_share`` 1 (all the touched surface is missing) or NaN
    when nothing was touched (a contact-free flight has no surface to miss). ``detected``:
    (k, 3) contact points of the true touches the detector reported (None: none)."""
    reported = np.zeros((0, 3)) if detected is None else np.asarray(detected, float).reshape(-1, 3)
    has_touch = len(touched_points(truth)) > 0
    if "scene" not in truth:
        return _mesh_free_scores(None, touched=has_touch, told=len(reported) > 0)
    rng = np.random.default_rng(seed)
    ts = _sample_truth(
        _scene(truth), truth, reported, rng, touched_radius_m=touched_radius_m,
        near_radius_m=near_radius_m, spacing_m=spacing_m, seed=seed, missing_m=missing_m,
        phantom_m=phantom_m,
    )  # fmt: skip
    if mesh is None or mesh.is_empty:
        return _mesh_free_scores(ts, touched=has_touch, told=len(reported) > 0)
    ms = _sample_mesh(mesh, ts, spacing_m=spacing_m, seed=seed)
    verts = mesh.vertices
    if len(verts) > 20000:
        verts = verts[rng.choice(len(verts), 20000, replace=False)]
    scores = _mesh_scores(mesh, ms, ts)
    return {
        "chamfer_m": scores.pop("chamfer_m"),
        "chamfer_full_m": chamfer_distance(ms.points, ts.true_pts),
        "shape_error_m": float(np.mean(distance_to_world(ts.scene, verts))),
        **scores,
    }


def touched_area(scene, touched: np.ndarray, radius_m: float, *, seed: int = 0) -> float:
    """Area (m²) of the surface that exists within ``radius_m`` of any of the ``touched``
    points (k, 3) and inside the scene's region: the exposed area times the share of points
    drawn uniformly on it that lie there (its own random draws, so the other metrics do not
    move with it). 0 when nothing was touched."""
    if len(touched) == 0 or not scene.objects:
        return 0.0
    rng = np.random.default_rng([seed, 1])
    exposed = scene.exposed_area(rng)
    pts = scene.sample_surface(rng, 20_000)
    if not len(pts):
        return 0.0
    lo, hi = np.asarray(scene.region_min), np.asarray(scene.region_max)
    inside = np.all((pts >= lo) & (pts <= hi), axis=1)
    return exposed * float(np.mean(inside & _near(pts, touched, radius_m)))


def _true_area(scene) -> float:
    total = 0.0
    for o in scene.objects:
        if hasattr(o, "min"):  # box
            dx, dy, dz = (np.asarray(o.max) - np.asarray(o.min)).tolist()
            total += 2 * (dx * dy + dx * dz + dy * dz)
        elif hasattr(o, "height"):  # cylinder
            total += 2 * math.pi * o.radius * o.height + 2 * math.pi * o.radius**2
        else:
            total += 4 * math.pi * o.radius**2
    return total


def score(
    mesh: SurfaceMesh | None,
    events: Iterable[DetectedEvent],
    truth: dict | None,
    *,
    touched_radius_m: float = 0.5,
) -> dict[str, Any]:
    """Every truth-based metric, or {} when the log has no truth."""
    if not truth or not truth.get("scene"):
        return {}
    events = list(events)
    out = surface_scores(
        mesh, truth, touched_radius_m=touched_radius_m, detected=reported_touches(events, truth)
    )
    out.update(false_positive_scores(events, truth))
    out["phantom_patches"] = patch_sources(out["phantom_patches"], events, truth)
    out["phantom_max_patch_cause"] = (
        out["phantom_patches"][0]["cause"] if out["phantom_patches"] else None
    )
    return out
