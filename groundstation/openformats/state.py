"""Display state shared by the Foxglove translator and the Rerun sink (pure, bounded).

- :class:`ContactBook`: every contact point (label 0 observation) with its event, ``p_false``
  when the detector gave one, and its state after the latest fit: *trusted* (held, flag bit 0
  clear), *flagged* (bit 0 set) or *pending* (no fit has held it yet), as in
  ``viewer.scene``. Contact *events* are counted the way the status line counts them: begin
  messages, and the fit's ``flagged_events`` (or, without it, the events of flagged points).
- :class:`Trajectory`: the flown path, kept as points at least ``spacing_m`` apart; when it
  grows past ``max_points`` the spacing doubles and the path is thinned, so a long flight
  costs a bounded message.
"""

from __future__ import annotations

import math

import numpy as np

from groundstation.viewer.scene import AWAITING, FLAGGED, PENDING, TRUSTED, contact_states

__all__ = ["AWAITING", "FLAGGED", "PENDING", "TRUSTED", "ContactBook", "Trajectory"]


class ContactBook:
    """Contact points, their states and the contact-event counts (module docstring)."""

    def __init__(self) -> None:
        self._ids: list[int] = []
        self._xyz: list[np.ndarray] = []
        self._event: list[int] = []
        self._p_obs: list[float] = []
        self._index: dict[int, int] = {}
        self._fit_ids = np.zeros(0, dtype=np.int64)
        self._fit_u = np.zeros(0)
        self._fit_flags = np.zeros(0, dtype=np.uint8)
        self._event_p: dict[int, float] = {}
        self.fit_index: int | None = None
        self.events_begun: set[int] = set()
        self._flagged_events: set[int] | None = None
        self.version = 0

    # -- ingest --------------------------------------------------------------------------------
    def add_observation(
        self, obs_id: int, label: int, x_m: np.ndarray, event_id: int = -1, p_false=None
    ) -> bool:
        """Keep a contact point (label 0); other labels are ignored (returns False)."""
        if int(label) != 0:
            return False
        x = np.asarray(x_m, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(x)):
            return False
        obs_id = int(obs_id)
        p = math.nan if p_false is None else float(p_false)
        if obs_id in self._index:
            i = self._index[obs_id]
            self._xyz[i], self._event[i], self._p_obs[i] = x, int(event_id), p
        else:
            self._index[obs_id] = len(self._ids)
            self._ids.append(obs_id)
            self._xyz.append(x)
            self._event.append(int(event_id))
            self._p_obs.append(p)
        self.version += 1
        return True

    def add_event(self, event_id: int, state: str, p_false=None) -> None:
        """A ``contact.event`` message: counts begins, keeps the event's ``p_false``."""
        if state == "begin":
            self.events_begun.add(int(event_id))
        if p_false is not None and math.isfinite(float(p_false)):
            self._event_p[int(event_id)] = float(p_false)
            self.version += 1

    def apply_fit(
        self,
        ids: np.ndarray,
        u: np.ndarray,
        flags: np.ndarray,
        fit_index: int,
        flagged_events=None,
    ) -> None:
        """The latest ``mapper.fit``: per-observation ``u`` and flag bits."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        order = np.argsort(ids, kind="stable")
        self._fit_ids = ids[order]
        self._fit_u = np.asarray(u, dtype=np.float64).reshape(-1)[order]
        self._fit_flags = np.asarray(flags, dtype=np.uint8).reshape(-1)[order]
        self.fit_index = int(fit_index)
        self._flagged_events = None if flagged_events is None else {int(e) for e in flagged_events}
        self.version += 1

    # -- output --------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._ids)

    def arrays(self) -> dict[str, np.ndarray]:
        """``xyz`` (k, 3) m, ``state`` (k,) int8, ``p_false`` (k,), ``u`` (k,) (NaN when not
        in the fit), ``event_id`` (k,) int32, ``id`` (k,) int64."""
        k = len(self._ids)
        ids = np.asarray(self._ids, dtype=np.int64)
        xyz = np.asarray(self._xyz, dtype=np.float64).reshape(k, 3)
        event = np.asarray(self._event, dtype=np.int32)
        p = np.asarray(self._p_obs, dtype=np.float64)
        if self._event_p:
            from_event = np.array([self._event_p.get(int(e), math.nan) for e in event])
            p = np.where(np.isnan(p), from_event, p)
        state = np.full(k, PENDING, dtype=np.int8)
        u = np.full(k, math.nan)
        if self._fit_ids.size and k:
            pos = np.clip(np.searchsorted(self._fit_ids, ids), 0, self._fit_ids.size - 1)
            found = self._fit_ids[pos] == ids
            state[found] = contact_states(self._fit_flags[pos][found])
            u[found] = self._fit_u[pos][found]
        return {"xyz": xyz, "state": state, "p_false": p, "u": u, "event_id": event, "id": ids}

    @property
    def events(self) -> int:
        """Contact events begun (the status line's ``contacts``)."""
        return len(self.events_begun)

    def flagged_events(self) -> int | None:
        """Contact events the latest fit flags (the status line's ``flagged``); None before a
        fit."""
        if self.fit_index is None:
            return None
        if self._flagged_events is not None:
            return len(self._flagged_events)
        a = self.arrays()
        flagged = (FLAGGED, AWAITING)
        return len({int(e) for e, s in zip(a["event_id"], a["state"], strict=True) if s in flagged})


class Trajectory:
    """The flown path, thinned by distance (module docstring).

    Parameters
    ----------
    spacing_m : float
        Smallest distance between kept points, metres.
    max_points : int
        Beyond this, the spacing doubles and the path is thinned again.
    """

    def __init__(self, spacing_m: float = 0.05, max_points: int = 2000) -> None:
        if not spacing_m > 0 or max_points < 2:
            raise ValueError(f"spacing_m={spacing_m} must be > 0 and max_points={max_points} >= 2")
        self.spacing_m = float(spacing_m)
        self.max_points = int(max_points)
        self._pts: list[np.ndarray] = []
        self._last_t: int | None = None
        self.version = 0

    def add(self, t_ns: int, xyz: np.ndarray) -> bool:
        """Add a position (metres); returns True when it was kept. Time going backwards (a new
        replay) starts a new path."""
        p = np.asarray(xyz, dtype=np.float64).reshape(3)
        if not all(math.isfinite(v) for v in p.tolist()):
            return False
        if self._last_t is not None and t_ns < self._last_t:
            self._pts = []
        self._last_t = int(t_ns)
        if self._pts and math.dist(p.tolist(), self._pts[-1].tolist()) < self.spacing_m:
            return False
        self._pts.append(p)
        if len(self._pts) > self.max_points:
            self.spacing_m *= 2
            kept = [self._pts[0]]
            for q in self._pts[1:]:
                if np.linalg.norm(q - kept[-1]) >= self.spacing_m:
                    kept.append(q)
            self._pts = kept
        self.version += 1
        return True

    def __len__(self) -> int:
        """Kept positions (without building :meth:`points`)."""
        return len(self._pts)

    def points(self) -> np.ndarray:
        """(m, 3) kept positions, metres, oldest first."""
        return np.asarray(self._pts, dtype=np.float64).reshape(-1, 3)
