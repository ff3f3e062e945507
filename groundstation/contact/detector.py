"""Contact detection from the drone's own accelerometer (pure; time comes with the data).

Pipeline per IMU sample (DESIGN.md §3):

1. ``earth_acceleration``: gravity-compensated acceleration in the world frame from the IMU's
   specific force (body FRD) and the firmware attitude (body FRD → local NED): a = R f + g.
2. A named low-pass filter on the acceleration vector (real propellers vibrate).
3. Threshold ``|a| > a0`` (0.6 G) with hysteresis (release below ``release_ratio * a0``) and a
   refractory time after each contact, so one bump is one event.
4. While in contact, at most ``contact_rate_hz``: a contact observation (y = 0) at the contact point
   ``x_c`` and an internal one (y = -1) at ``x_c - d_in n``, with the outward normal
   ``n = a / |a|``; ``x_c = x - r n`` when the horizontal part of n dominates, else ``x - h n``.
5. While not in contact (and quiet for ``quiet_s``): an external observation (y = +1) at the
   vehicle position every ``1 / external_rate_hz`` of data time (the paper's 0.5 Hz), and
   also whenever the vehicle has moved ``external_spacing_m`` from the last one (the flown
   path is what refutes a false contact; see ``ContactSettings``).

Samples without a pose (mocap gap) still drive the filter and the contact state machine, but no
observation can be placed: they are counted in ``stats.no_pose``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from firmware_bridge.frames import ned_to_enu, quat_to_matrix
from groundstation.contact.filters import make_filter
from groundstation.contact.settings import ContactSettings, G

LABEL_INSIDE, LABEL_SURFACE, LABEL_OUTSIDE = -1.0, 0.0, 1.0


def earth_acceleration(specific_force_frd, quaternion_frd_ned) -> np.ndarray:
    """Gravity-compensated acceleration in the station's world frame (ENU, z up), m/s².

    Parameters
    ----------
    specific_force_frd : (3,) array
        Accelerometer reading (specific force, gravity included), body FRD, m/s². A level
        vehicle at rest reads about (0, 0, -9.81).
    quaternion_frd_ned : (4,) array
        Attitude (w, x, y, z), body FRD → local NED, as MAVLink reports it.
    """
    f = np.asarray(specific_force_frd, dtype=float)
    a_ned = quat_to_matrix(quaternion_frd_ned) @ f + np.array([0.0, 0.0, G])  # a = R f + g
    return ned_to_enu(a_ned)


@dataclasses.dataclass(frozen=True, slots=True)
class Observation:
    """One training datum for the map.

    Attributes
    ----------
    id : int
        Unique, increasing.
    t_ns : int
        Data time (station axis) of the sample that produced it.
    position : (3,) ndarray
        World frame, metres.
    label : float
        -1 inside, 0 surface (contact), +1 outside.
    normal : (3,) ndarray
        Outward normal for contact/internal points; zeros for external points.
    event_id : int
        Contact event it belongs to, or -1 for external points.
    accel_g : float
        Filtered |a| in G at emission (impulse detector: the impulse's peak residual).
    p_false : float
        Probability from the contact's physics that its event is false (impulse detector;
        NaN: no evidence, e.g. the threshold detector or an external point).
    dv_mps : float
        Impulse per unit mass of its event along the normal, m/s (NaN: not measured).
    rebound : bool
        The vehicle approached before the event and moved away after it.
    sigma_m : float
        Placement uncertainty of a contact point, metres (NaN: unknown).
    """

    id: int
    t_ns: int
    position: np.ndarray
    label: float
    normal: np.ndarray
    event_id: int
    accel_g: float
    p_false: float = math.nan
    dv_mps: float = math.nan
    rebound: bool = False
    sigma_m: float = math.nan


@dataclasses.dataclass
class ContactEvent:
    """One detected contact (threshold: crossing to release; impulse: onset to release).

    ``p_false``, ``features`` (:class:`~groundstation.contact.evidence.ImpulseFeatures`) and
    ``rejected`` (too likely false to make observations, or begun at the floor) come from the
    impulse detector; ``p_false_impulse`` is the evidence model's value on the impulse alone
    (``p_false`` adds the burst context, ``contact.burst_odds``); ``floor_clearance_m`` is the
    height of the body's lowest point above the configured floor at the onset (NaN without a
    floor, pose or attitude) and ``at_floor`` whether that rejected it (``contact.floor_z_m``);
    ``tilt_deg`` is the body's tilt at the onset (NaN without an attitude) and ``upset`` whether
    that rejected it (``contact.reject_tilt_deg``).
    """

    id: int
    t_start_ns: int
    t_end_ns: int = -1
    peak_g: float = 0.0
    normal: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    position: np.ndarray | None = None
    observations: int = 0
    p_false: float = math.nan
    features: object = None
    rejected: bool = False
    p_false_impulse: float = math.nan
    floor_clearance_m: float = math.nan
    at_floor: bool = False
    tilt_deg: float = math.nan
    upset: bool = False


@dataclasses.dataclass
class DetectorStats:
    samples: int = 0
    rejected: int = 0  # non-finite input
    no_pose: int = 0  # observations that could not be placed
    left_contact: int = 0  # later samples of a push dropped: the vehicle had flown off
    tilted: int = 0  # free-space samples not taken: the body was tilted past the limit
    contacts: int = 0  # contact events started
    observations: int = 0


def contact_point(position: np.ndarray, normal: np.ndarray, s: ContactSettings) -> np.ndarray:
    """The paper's cylinder rule: x - r n if the horizontal part of n dominates, else x - h n."""
    horizontal = np.hypot(normal[0], normal[1]) >= abs(normal[2])
    return position - (s.drone_radius_m if horizontal else s.drone_height_m) * normal


class ContactDetector:
    """Stateful contact detector; feed samples in time order with :meth:`update`.

    Parameters
    ----------
    settings : ContactSettings
    first_id : int
        Id of the first observation (so a restarted detector does not reuse ids).
    """

    def __init__(self, settings: ContactSettings | None = None, first_id: int = 0):
        self.settings = settings or ContactSettings()
        s = self.settings
        self._filter = make_filter(s.filter, s.window_s, s.cutoff_hz)
        self._next_id = int(first_id)
        self._event: ContactEvent | None = None
        self._next_event_id = 0
        self._refractory_until = -(2**62)
        self._last_contact_ns = -(2**62)
        self._last_contact_emit = -(2**62)
        self._last_external_emit = -(2**62)
        self._last_external_pos: np.ndarray | None = None
        self._last_t: int | None = None
        self.events: list[ContactEvent] = []
        self.stats = DetectorStats()
        self.last_accel_g = 0.0

    @property
    def in_contact(self) -> bool:
        return self._event is not None

    @property
    def open_event(self) -> ContactEvent | None:
        """The contact event in progress (None when not in contact)."""
        return self._event

    def _observe(self, t_ns, position, label, normal, event_id, accel_g) -> Observation:
        obs = Observation(self._next_id, t_ns, position, label, normal, event_id, accel_g)
        self._next_id += 1
        self.stats.observations += 1
        return obs

    def update(self, t_ns: int, accel_world, position=None) -> list[Observation]:
        """Process one sample.

        Parameters
        ----------
        t_ns : int
            Data time of the sample (station axis), ns; must increase.
        accel_world : (3,) array
            Gravity-compensated acceleration, world frame, m/s² (see :func:`earth_acceleration`).
        position : (3,) array or None
            Vehicle position at ``t_ns`` (world, m), or None when there is no pose.

        Returns
        -------
        list of Observation
            Zero, one (external) or two (contact + internal) observations.
        """
        s = self.settings
        self.stats.samples += 1
        a = np.asarray(accel_world, dtype=float)
        if (
            a.shape != (3,)
            or not np.isfinite(a).all()
            or (self._last_t is not None and t_ns <= self._last_t)
        ):
            self.stats.rejected += 1
            return []
        self._last_t = t_ns
        pos = None
        if position is not None:
            pos = np.asarray(position, dtype=float)
            if pos.shape != (3,) or not np.isfinite(pos).all():
                pos = None
        af = self._filter.update(t_ns, a)
        mag = float(np.linalg.norm(af))
        g = mag / G
        self.last_accel_g = g
        out: list[Observation] = []

        armed = self._filter.ready and t_ns >= self._refractory_until
        if self._event is None and g > s.threshold_g and armed:
            self._event = ContactEvent(self._next_event_id, t_ns, position=pos)
            self._next_event_id += 1
            self.stats.contacts += 1
            self._last_contact_emit = -(2**62)
        elif self._event is not None and g < s.release_ratio * s.threshold_g:
            self._event.t_end_ns = t_ns
            self.events.append(self._event)
            self._event = None
            self._refractory_until = t_ns + int(s.refractory_s * 1e9)
            self._last_contact_ns = t_ns

        ev = self._event
        if ev is not None:
            self._last_contact_ns = t_ns
            normal = af / mag
            if g > ev.peak_g:
                ev.peak_g, ev.normal = g, normal
            if t_ns - self._last_contact_emit >= int(1e9 / s.contact_rate_hz):
                if pos is None:
                    self.stats.no_pose += 1
                else:
                    self._last_contact_emit = t_ns
                    xc = contact_point(pos, normal, s)
                    xin = xc - s.internal_depth_m * normal
                    out.append(self._observe(t_ns, xc, LABEL_SURFACE, normal, ev.id, g))
                    out.append(self._observe(t_ns, xin, LABEL_INSIDE, normal, ev.id, g))
                    ev.observations += 2
        elif t_ns - self._last_contact_ns >= int(s.quiet_s * 1e9):
            due = t_ns - self._last_external_emit >= int(1e9 / s.external_rate_hz)
            if pos is None:
                self.stats.no_pose += due
            elif due or self._moved(pos):
                self._last_external_emit = t_ns
                self._last_external_pos = pos.copy()
                out.append(self._observe(t_ns, pos.copy(), LABEL_OUTSIDE, np.zeros(3), -1, g))
        return out

    def _moved(self, pos: np.ndarray) -> bool:
        """Whether ``pos`` is ``external_spacing_m`` or more from the last external point."""
        spacing = self.settings.external_spacing_m
        last = self._last_external_pos
        return spacing > 0 and last is not None and float(np.linalg.norm(pos - last)) >= spacing
