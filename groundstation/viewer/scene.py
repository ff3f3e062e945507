"""What the viewer draws, built from bus messages with no I/O (the *model* of the viewer).

:class:`ViewModel` ingests the latest mesh, the latest fit (per-observation ``u`` and flags),
observations and poses as plain arrays, and :meth:`ViewModel.scene` returns a frozen
:class:`Scene`: the draw data every sink (Open3D window, offscreen PNG, matplotlib fallback, PLY
files) renders. Model: Open3D's ``examples/python/visualization/online_processing.py``
model/view/controller split (STYLE.md item 15); the view is :mod:`window` or :mod:`headless`,
the controller :mod:`process`.

Conventions
-----------
- Coordinates: the station's world frame (metres, right-handed, z up; ``firmware_bridge.frames``).
- Observation labels (DESIGN.md §3): 0 contact (surface), -1 internal point, +1 external point.
- ``mapper.fit`` flags are bit fields (``|u1``); bit 0 (:data:`FLAG_FALSE_POSITIVE`) marks an
  observation the robust model considers a false-positive contact (large ``u_i``).
- A contact is *trusted* when the latest fit holds it with bit 0 clear, *flagged* when bit 0 is
  set, *awaiting* when bit 1 (:data:`FLAG_AWAITING`) is set too (flagged only because no other
  touch corroborates it: a second touch beside it would keep it), *pending* when no fit has
  included it yet.
- Contacts are counted as the status line counts them (``runtime.status``): contact *events*
  (``contact.event`` begins; without them, the distinct events of the contact points) and the
  events the latest fit flags (its ``flagged_events``; without them, the events of its flagged
  points). The caption gives that first, then the contact *points* by state.
- Memory is bounded: the trajectory is a ring buffer (``trajectory_max_points``, and only the last
  ``trajectory_window_s`` of data time is drawn); observations beyond ``max_observations`` evict
  the oldest, and :attr:`ViewModel.observations_dropped` counts them.
- No clock reads: times come in with the data (pose time for the trajectory window) or from the
  caller (``now_ns`` for the mesh age in the caption).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from firmware_bridge.frames import quat_to_matrix
from groundstation.errors import ConfigError, InputDataError

#: ``mapper.fit`` flag bit: the observation is a flagged false-positive contact.
FLAG_FALSE_POSITIVE = 0x01
#: ``mapper.fit`` flag bit (with bit 0): flagged only for want of a second touch near it.
FLAG_AWAITING = 0x02

#: Contact states (values of :attr:`Scene.contact_state`).
TRUSTED, FLAGGED, PENDING, AWAITING = 0, 1, 2, 3
STATE_NAMES = ("trusted", "flagged", "pending", "awaiting")
#: RGB in [0, 1] per contact state: green trusted, magenta flagged, grey pending, amber
#: awaiting a second touch.
STATE_COLORS = np.array(
    [[0.10, 0.75, 0.20], [0.95, 0.10, 0.75], [0.55, 0.55, 0.55], [1.00, 0.70, 0.00]]
)


def contact_states(flags: np.ndarray) -> np.ndarray:
    """(k,) int8 state of contacts the fit holds, from their flag bits: :data:`TRUSTED`,
    :data:`FLAGGED`, or :data:`AWAITING` (flagged, and bit 1 set)."""
    flags = np.asarray(flags)
    bad = (flags & FLAG_FALSE_POSITIVE) != 0
    waiting = bad & ((flags & FLAG_AWAITING) != 0)
    return np.where(waiting, AWAITING, np.where(bad, FLAGGED, TRUSTED)).astype(np.int8)


INTERNAL_COLOR = np.array([0.20, 0.35, 0.95])
EXTERNAL_COLOR = np.array([0.30, 0.85, 0.95])
TRAJECTORY_COLOR = np.array([1.00, 0.55, 0.00])

_LABEL_CONTACT, _LABEL_INTERNAL, _LABEL_EXTERNAL = 0, -1, 1


class ViewerInputError(InputDataError):
    """A message handed to the viewer model is malformed (shape, NaN, bad index)."""


@dataclasses.dataclass(frozen=True)
class ViewSettings:
    """What the viewer keeps and shows.

    Attributes
    ----------
    trajectory_window_s : float
        Length of the drawn trajectory, seconds of data time.
    trajectory_max_points : int
        Capacity of the pose ring buffer (bounds memory at high pose rates).
    max_observations : int
        Observations kept; older ones are evicted and counted.
    show_internal, show_external : bool
        Also draw internal (-1) / external (+1) points.
    std_range : (float, float) or None
        Fixed colour range of the predictive std; None: ``(0, max std)`` of each mesh.
    triad_size_m : float
        Length of the vehicle's axis triad, metres.
    """

    trajectory_window_s: float = 10.0
    trajectory_max_points: int = 4000
    max_observations: int = 20000
    show_internal: bool = False
    show_external: bool = False
    std_range: tuple[float, float] | None = None
    triad_size_m: float = 0.3

    def __post_init__(self) -> None:
        if not (math.isfinite(self.trajectory_window_s) and self.trajectory_window_s > 0):
            raise ConfigError(f"trajectory_window_s = {self.trajectory_window_s} must be > 0 s")
        for name in ("trajectory_max_points", "max_observations"):
            if int(getattr(self, name)) < 2:
                raise ConfigError(f"{name} = {getattr(self, name)} must be >= 2")
        if self.std_range is not None:
            lo, hi = self.std_range
            if not (math.isfinite(lo) and math.isfinite(hi) and hi > lo):
                raise ConfigError(f"std_range = {self.std_range} needs finite lo < hi")
        if not (math.isfinite(self.triad_size_m) and self.triad_size_m > 0):
            raise ConfigError(f"triad_size_m = {self.triad_size_m} must be > 0 m")


@dataclasses.dataclass(frozen=True, eq=False)
class MeshDraw:
    """The mesh to draw.

    Attributes
    ----------
    vertices : (V, 3) float64, metres
    triangles : (T, 3) int32, vertex indices
    colors : (V, 3) float64 in [0, 1], std colormap (``mapping.surface.STD_COLORMAP``)
    std : (V,) float64, predictive std at the vertices
    std_range : (lo, hi) of the colour legend
    fit_index : int
    stamp_ns : int or None, time the mesh arrived (caller's clock, for its age)
    """

    vertices: np.ndarray
    triangles: np.ndarray
    colors: np.ndarray
    std: np.ndarray
    std_range: tuple[float, float]
    fit_index: int
    stamp_ns: int | None


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """Everything a sink draws, as plain arrays. ``*_version`` counters increase whenever the
    corresponding part changes, so a sink re-uploads only what changed.

    Attributes
    ----------
    mesh : MeshDraw or None
    contacts_xyz : (k, 3) float64, contact points, metres
    contact_state : (k,) int8, :data:`TRUSTED` / :data:`FLAGGED` / :data:`PENDING`
    contacts_rgb : (k, 3) float64, :data:`STATE_COLORS` of the states
    internal_xyz, external_xyz : (i, 3), (e, 3) float64 (empty unless enabled)
    pose_position : (3,) float64 or None, latest valid vehicle position
    pose_rotation : (3, 3) float64 or None, body-to-world rotation of that pose
    trajectory_xyz : (m, 3) float64, positions of the last ``trajectory_window_s``, oldest first
    caption : str, one line (fit index, observations, flagged count, mesh age)
    counts : dict of str to int
    """

    mesh: MeshDraw | None
    mesh_version: int
    contacts_xyz: np.ndarray
    contact_state: np.ndarray
    contacts_rgb: np.ndarray
    internal_xyz: np.ndarray
    external_xyz: np.ndarray
    points_version: int
    pose_position: np.ndarray | None
    pose_rotation: np.ndarray | None
    trajectory_xyz: np.ndarray
    pose_version: int
    caption: str
    counts: dict[str, int]
    triad_size_m: float = 0.3

    def bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Axis-aligned (min, max) of everything drawn, or None when nothing is."""
        parts = [self.contacts_xyz, self.internal_xyz, self.external_xyz, self.trajectory_xyz]
        if self.mesh is not None:
            parts.append(self.mesh.vertices)
        if self.pose_position is not None:
            parts.append(self.pose_position[None, :])
        pts = [p for p in parts if p.size]
        if not pts:
            return None
        allp = np.concatenate(pts, axis=0)
        return allp.min(axis=0), allp.max(axis=0)

    def triad_segments(self) -> tuple[np.ndarray, np.ndarray]:
        """The vehicle's axis triad: ``points`` (4, 3) (origin, x, y, z tips, metres) and
        ``colors`` (3, 3) (red x, green y, blue z) for segments 0-1, 0-2, 0-3. Empty if no pose."""
        if self.pose_position is None or self.pose_rotation is None:
            return np.zeros((0, 3)), np.zeros((0, 3))
        tips = self.pose_position + self.triad_size_m * self.pose_rotation.T  # rows: R e_i
        return np.vstack([self.pose_position, tips]), np.eye(3)


def _vec3(value: Any, what: str) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64).reshape(-1)
    if a.shape != (3,):
        raise ViewerInputError(f"{what} has shape {np.shape(value)}, expected (3,)")
    return a


class ViewModel:
    """Latest state of the map for display (see the module docstring).

    Parameters
    ----------
    settings : ViewSettings
    """

    def __init__(self, settings: ViewSettings | None = None):
        self.settings = settings or ViewSettings()
        s = self.settings
        self.mesh: MeshDraw | None = None
        self.mesh_version = 0
        self.meshes_received = 0
        # observations: ring of slots, id -> slot
        cap = int(s.max_observations)
        self._obs_xyz = np.zeros((cap, 3))
        self._obs_label = np.zeros(cap, dtype=np.int8)
        self._obs_id = np.zeros(cap, dtype=np.int64)
        self._slot_of: dict[int, int] = {}
        self._next_slot = 0
        self._n_obs = 0
        self.observations_total = 0
        self.observations_dropped = 0
        # latest fit, sorted by id for vectorised lookup
        self.fit_index: int | None = None
        self._fit_ids = np.zeros(0, dtype=np.int64)
        self._fit_flags = np.zeros(0, dtype=np.uint8)
        self._fit_u = np.zeros(0)
        self._flagged_events: set[int] | None = None
        self._events_begun: set[int] = set()
        self._obs_event: dict[int, int] = {}  # contact observation id -> event id
        self.points_version = 0
        # poses: ring buffer of (t_ns, xyz)
        tcap = int(s.trajectory_max_points)
        self._traj_t = np.zeros(tcap, dtype=np.int64)
        self._traj_xyz = np.zeros((tcap, 3))
        self._traj_head = 0
        self._traj_n = 0
        self.pose_position: np.ndarray | None = None
        self.pose_rotation: np.ndarray | None = None
        self.pose_version = 0
        self.poses_invalid = 0
        self.rejected: dict[str, int] = {}
        self._points_cache: tuple[int, tuple[np.ndarray, ...]] | None = None

    # -- ingest --------------------------------------------------------------------------------
    def ingest_mesh(
        self,
        vertices: np.ndarray,
        triangles: np.ndarray,
        vertex_std: np.ndarray,
        fit_index: int,
        stamp_ns: int | None = None,
    ) -> MeshDraw:
        """Replace the mesh.

        Parameters
        ----------
        vertices : (V, 3) float, metres
        triangles : (T, 3) int, indices into ``vertices``
        vertex_std : (V,) float, predictive std (finite, >= 0)
        fit_index : int
        stamp_ns : int, optional
            Arrival time on the caller's clock (for the mesh age in the caption).

        Raises
        ------
        ViewerInputError
            On wrong shapes, non-finite values or out-of-range triangle indices.
        """
        v = np.asarray(vertices, dtype=np.float64)
        t = np.asarray(triangles)
        sd = np.asarray(vertex_std, dtype=np.float64)
        if v.ndim != 2 or v.shape[1] != 3:
            raise ViewerInputError(f"mesh vertices have shape {v.shape}, expected (V, 3)")
        if t.ndim != 2 or t.shape[1] != 3 or (t.size and t.dtype.kind not in "iu"):
            raise ViewerInputError(
                f"mesh triangles have shape {t.shape} dtype {t.dtype}, expected (T, 3) int"
            )
        if sd.shape != (v.shape[0],):
            raise ViewerInputError(f"vertex_std has shape {sd.shape}, expected ({v.shape[0]},)")
        if not np.all(np.isfinite(v)):
            raise ViewerInputError(f"mesh has {int(np.sum(~np.isfinite(v)))} non-finite coords")
        if not np.all(np.isfinite(sd)):
            raise ViewerInputError(f"vertex_std has {int(np.sum(~np.isfinite(sd)))} non-finite")
        if t.size and (t.min() < 0 or t.max() >= v.shape[0]):
            raise ViewerInputError(
                f"triangle indices span [{t.min()}, {t.max()}] but there are {v.shape[0]} vertices"
            )
        from groundstation.mapping.surface import std_colors  # lazy: scipy/skimage are slow

        if self.settings.std_range is not None:
            colors, rng = std_colors(sd, self.settings.std_range)
        elif sd.size:
            colors, rng = std_colors(sd)
        else:
            colors, rng = np.zeros((0, 3)), (0.0, 1.0)
        self.mesh = MeshDraw(
            vertices=v,
            triangles=t.astype(np.int32, copy=False),
            colors=colors,
            std=sd,
            std_range=rng,
            fit_index=int(fit_index),
            stamp_ns=None if stamp_ns is None else int(stamp_ns),
        )
        self.mesh_version += 1
        self.meshes_received += 1
        return self.mesh

    def ingest_fit(
        self,
        ids: np.ndarray,
        u: np.ndarray,
        flags: np.ndarray,
        fit_index: int,
        flagged_events=None,
    ) -> None:
        """Replace the per-observation fit results.

        Parameters
        ----------
        ids : (n,) int, observation ids
        u : (n,) float, ``u_i = beta~_i / alpha~_i`` (ALGORITHM.md; larger = less trusted)
        flags : (n,) uint8 bit fields (:data:`FLAG_FALSE_POSITIVE`)
        fit_index : int
        flagged_events : iterable of int, optional
            Contact event ids the fit flags (``mapper.fit`` payload).
        """
        ids = np.asarray(ids).reshape(-1)
        u = np.asarray(u, dtype=np.float64).reshape(-1)
        flags = np.asarray(flags).reshape(-1)
        if not (ids.shape == u.shape == flags.shape):
            raise ViewerInputError(
                f"fit arrays differ in length: ids {ids.shape}, u {u.shape}, flags {flags.shape}"
            )
        if ids.size and ids.dtype.kind not in "iu":
            raise ViewerInputError(f"fit ids have dtype {ids.dtype}, expected integers")
        order = np.argsort(ids, kind="stable")
        self._fit_ids = ids[order].astype(np.int64)
        self._fit_u = u[order]
        self._fit_flags = flags[order].astype(np.uint8)
        self.fit_index = int(fit_index)
        self._flagged_events = None if flagged_events is None else {int(e) for e in flagged_events}
        self.points_version += 1

    def ingest_event(self, event_id: int, state: str) -> None:
        """A ``contact.event`` message (begins are counted as contacts)."""
        if state == "begin":
            self._events_begun.add(int(event_id))

    def ingest_observation(
        self, obs_id: int, label: int, x_m: np.ndarray, event_id: int | None = None
    ) -> None:
        """Add one observation (DESIGN.md §3 labels: 0 contact, -1 internal, +1 external);
        ``event_id``: the contact event of a contact point.

        A repeated id replaces the earlier point. Beyond ``max_observations`` the oldest is
        evicted and counted in :attr:`observations_dropped`.
        """
        x = _vec3(x_m, "observation x_m")
        if not np.all(np.isfinite(x)):
            raise ViewerInputError(f"observation {obs_id} has a non-finite position {x.tolist()}")
        if label not in (_LABEL_CONTACT, _LABEL_INTERNAL, _LABEL_EXTERNAL):
            raise ViewerInputError(f"observation {obs_id} has label {label!r}, not -1, 0 or 1")
        obs_id = int(obs_id)
        slot = self._slot_of.get(obs_id)
        if slot is None:
            slot = self._next_slot
            cap = self._obs_xyz.shape[0]
            if self._n_obs == cap:
                del self._slot_of[int(self._obs_id[slot])]
                self.observations_dropped += 1
            else:
                self._n_obs += 1
            self._next_slot = (slot + 1) % cap
            self._slot_of[obs_id] = slot
            self.observations_total += 1
        self._obs_xyz[slot] = x
        self._obs_label[slot] = label
        self._obs_id[slot] = obs_id
        if label == _LABEL_CONTACT and event_id is not None and int(event_id) >= 0:
            self._obs_event[obs_id] = int(event_id)
        self.points_version += 1

    def ingest_pose(
        self, t_ns: int, position_m: np.ndarray, q_wxyz: np.ndarray, valid: bool = True
    ) -> bool:
        """Add one vehicle pose; returns False (and counts it) when it is invalid or NaN.

        A time earlier than the newest kept pose (a new replay, a restarted source) clears the
        trajectory instead of drawing a line back in time.
        """
        p = _vec3(position_m, "pose position_m")
        q = np.asarray(q_wxyz, dtype=np.float64).reshape(-1)
        if q.shape != (4,):
            raise ViewerInputError(f"pose q_wxyz has shape {np.shape(q_wxyz)}, expected (4,)")
        if not valid or not (np.all(np.isfinite(p)) and np.all(np.isfinite(q))):
            self.poses_invalid += 1
            return False
        if not np.linalg.norm(q) > 1e-9:
            self.poses_invalid += 1
            return False
        t_ns = int(t_ns)
        cap = self._traj_t.shape[0]
        if self._traj_n and t_ns < self._traj_t[(self._traj_head - 1) % cap]:
            self._traj_n = 0
        self._traj_t[self._traj_head] = t_ns
        self._traj_xyz[self._traj_head] = p
        self._traj_head = (self._traj_head + 1) % cap
        self._traj_n = min(self._traj_n + 1, cap)
        self.pose_position = p
        self.pose_rotation = quat_to_matrix(q)
        self.pose_version += 1
        return True

    def ingest_message(
        self,
        topic: str,
        payload: Mapping[str, Any],
        arrays: Mapping[str, np.ndarray],
        *,
        source_ns: int,
        recv_ns: int = 0,
    ) -> bool:
        """Dispatch one bus message (already decoded to plain values) by topic.

        Bad messages raise :class:`ViewerInputError` and are counted in :attr:`rejected`
        per topic; unknown topics are ignored (returns False).
        """
        try:
            if topic == "mesh":
                self.ingest_mesh(
                    arrays["vertices"],
                    arrays["triangles"],
                    arrays["vertex_std"],
                    payload["fit_index"],
                    stamp_ns=recv_ns or None,
                )
            elif topic == "mapper.fit":
                self.ingest_fit(
                    arrays["ids"],
                    arrays["u"],
                    arrays["flags"],
                    payload["fit_index"],
                    payload.get("flagged_events"),
                )
            elif topic == "observations":
                self.ingest_observation(
                    payload["id"], payload["label"], arrays["x_m"], payload.get("event_id")
                )
            elif topic == "contact.event":
                self.ingest_event(payload["id"], payload["state"])
            elif topic == "samples.pose":
                t = payload.get("t_station_ns")
                self.ingest_pose(
                    source_ns if t is None else t,
                    arrays["position_m"],
                    arrays["q_wxyz"],
                    valid=bool(payload.get("valid", True)),
                )
            else:
                return False
        except (KeyError, TypeError, ValueError) as exc:
            self.rejected[topic] = self.rejected.get(topic, 0) + 1
            if isinstance(exc, ViewerInputError):
                raise
            raise ViewerInputError(f"{topic} message is malformed: {exc!r}") from exc
        return True

    # -- output --------------------------------------------------------------------------------
    def _points(self) -> tuple[np.ndarray, ...]:
        if self._points_cache is not None and self._points_cache[0] == self.points_version:
            return self._points_cache[1]
        n = self._n_obs
        xyz, label, ids = self._obs_xyz[:n], self._obs_label[:n], self._obs_id[:n]
        if n == self._obs_xyz.shape[0]:  # ring is full: oldest first
            roll = -self._next_slot
            xyz, label, ids = (np.roll(a, roll, axis=0) for a in (xyz, label, ids))
        is_c = label == _LABEL_CONTACT
        c_ids = ids[is_c]
        state = np.full(c_ids.shape, PENDING, dtype=np.int8)
        if self._fit_ids.size and c_ids.size:
            pos = np.clip(np.searchsorted(self._fit_ids, c_ids), 0, self._fit_ids.size - 1)
            found = self._fit_ids[pos] == c_ids
            state[found] = contact_states(self._fit_flags[pos][found])
        internal = (
            xyz[label == _LABEL_INTERNAL] if self.settings.show_internal else np.zeros((0, 3))
        )
        external = (
            xyz[label == _LABEL_EXTERNAL] if self.settings.show_external else np.zeros((0, 3))
        )
        out = (xyz[is_c].copy(), state, STATE_COLORS[state], internal.copy(), external.copy())
        self._points_cache = (self.points_version, out)
        return out

    def trajectory(self) -> np.ndarray:
        """(m, 3) positions within ``trajectory_window_s`` of the newest pose, oldest first."""
        n, cap = self._traj_n, self._traj_t.shape[0]
        if n == 0:
            return np.zeros((0, 3))
        idx = (self._traj_head - n + np.arange(n)) % cap
        t = self._traj_t[idx]
        keep = t >= t[-1] - int(self.settings.trajectory_window_s * 1e9)
        return self._traj_xyz[idx[keep]].copy()

    @property
    def flagged_count(self) -> int:
        """Observations flagged as false positives in the latest fit."""
        return int(np.count_nonzero(self._fit_flags & FLAG_FALSE_POSITIVE))

    def fit_covers(self, fit_index: int) -> bool:
        """True when the latest ``mapper.fit`` is at least ``fit_index`` and every id it lists
        has its observation here (or the ring has evicted points, so absence proves nothing).

        The mapper publishes ``mesh`` before ``mapper.fit`` and observations travel on other
        sockets, so a mesh can arrive before the fit and the points it was made from.
        """
        if self.fit_index is None or self.fit_index < int(fit_index):
            return False
        if self.observations_dropped or not self._fit_ids.size:
            return True
        return bool(np.isin(self._fit_ids, self._obs_id[: self._n_obs]).all())

    def event_counts(self) -> tuple[int, int | None]:
        """(contact events, events the latest fit flags or None before a fit), counted as the
        status line counts them (module docstring)."""
        events = len(self._events_begun or set(self._obs_event.values()))
        if self.fit_index is None:
            return events, None
        if self._flagged_events is not None:
            return events, len(self._flagged_events)
        bad = self._fit_ids[(self._fit_flags & FLAG_FALSE_POSITIVE) != 0].tolist()
        return events, len({self._obs_event[i] for i in bad if i in self._obs_event})

    def scene(self, now_ns: int | None = None) -> Scene:
        """Draw data for the current state.

        Parameters
        ----------
        now_ns : int, optional
            Current time on the clock of the mesh ``stamp_ns`` (for the mesh age).
        """
        cxyz, state, crgb, internal, external = self._points()
        counts = {
            "observations": self._n_obs,
            "observations_total": self.observations_total,
            "observations_dropped": self.observations_dropped,
            "contacts": int(state.size),
            "trusted": int(np.count_nonzero(state == TRUSTED)),
            "flagged": int(np.count_nonzero((state == FLAGGED) | (state == AWAITING))),
            "awaiting": int(np.count_nonzero(state == AWAITING)),
            "pending": int(np.count_nonzero(state == PENDING)),
            "fit_flagged": self.flagged_count,
            "events": self.event_counts()[0],
            "events_flagged": self.event_counts()[1],
            "meshes": self.meshes_received,
            "rejected": sum(self.rejected.values()),
        }
        return Scene(
            mesh=self.mesh,
            mesh_version=self.mesh_version,
            contacts_xyz=cxyz,
            contact_state=state,
            contacts_rgb=crgb,
            internal_xyz=internal,
            external_xyz=external,
            points_version=self.points_version,
            pose_position=self.pose_position,
            pose_rotation=self.pose_rotation,
            trajectory_xyz=self.trajectory(),
            pose_version=self.pose_version,
            caption=self.caption(counts, now_ns),
            counts=counts,
            triad_size_m=self.settings.triad_size_m,
        )

    def caption(self, counts: Mapping[str, int], now_ns: int | None = None) -> str:
        """One line: fit index, observations, contact states, mesh size, age and std range."""
        fit = "-" if self.fit_index is None else str(self.fit_index)
        obs = f"{counts['observations']} obs"
        if counts["observations_dropped"]:
            obs += f" (+{counts['observations_dropped']} older not kept)"
        flagged = counts.get("events_flagged")
        parts = [
            f"fit {fit}",
            f"contacts {counts.get('events', 0)}"
            + ("" if flagged is None else f" ({flagged} flagged)"),
            obs,
            f"contact points {counts['contacts']}: {counts['trusted']} trusted, "
            f"{counts['flagged']} flagged"
            + (f" ({counts['awaiting']} awaiting a second touch)" if counts.get("awaiting") else "")
            + f", {counts['pending']} pending",
        ]
        m = self.mesh
        if m is None:
            parts.append("no mesh yet")
        else:
            text = f"mesh #{m.fit_index} {m.triangles.shape[0]} tri"
            if now_ns is not None and m.stamp_ns is not None:
                text += f", age {max(0, now_ns - m.stamp_ns) / 1e9:.1f} s"
            text += f", std {m.std_range[0]:.3g}-{m.std_range[1]:.3g}"
            parts.append(text)
        return " | ".join(parts)
