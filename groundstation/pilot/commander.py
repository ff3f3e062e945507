"""MANUAL_CONTROL at a fixed rate from the latest input and the mux (pure: times are arguments).

Per tick (STYLE.md item 16: device shell -> pure shaping (value, t) -> explicit mux where e-stop
always wins -> watchdog)::

    snapshot (from the device shell) --watchdog.assess(t)--> Health
    raw axes --calibration--> Sticks --mux.step--> state --(ARMED only)--> shape + slew(t)
         --> PilotCommand (x forward/pitch, y right/roll, z thrust, r yaw, buttons)

Every command and every mux event is a small record with ``to_dict()`` for the recorder and
``to_payload()`` for the ``pilot.command`` / ``pilot.event`` bus topics.
:class:`RateSchedule` gives the process shell absolute deadlines at ``rate_hz`` (no drift, no
catch-up bursts after a late wake-up).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from groundstation.pilot.calibration import CalibrationError, DeviceCalibration
from groundstation.pilot.mux import MuxInput, PilotEvent, PilotMux, status_line
from groundstation.pilot.settings import PilotSettings
from groundstation.pilot.shaping import (
    SlewLimiter,
    Sticks,
    calibrated_sticks,
    shape,
    to_manual_units,
)
from groundstation.pilot.watchdog import Health, assess


@dataclasses.dataclass(frozen=True)
class InputSnapshot:
    """The device shell's latest view of the joystick, copied under its lock.

    Attributes
    ----------
    name : str
        Device name (``JSIOCGNAME``, or the configured name for FIFO sources).
    connected : bool
        The device is open.
    alive_ns : int or None
        Last "alive" report, ns monotonic (see :mod:`groundstation.pilot.watchdog`).
    fault : str or None
        "device_lost" / "read_error" since the last alive report.
    axes : mapping of int to int
        Latest raw value per axis (-32767..32767).
    buttons : int
        Bit n set = button n held.
    generation : int
        Incremented on every (re)open of the device.
    """

    name: str
    connected: bool
    alive_ns: int | None
    fault: str | None
    axes: Mapping[int, int]
    buttons: int
    generation: int = 0


@dataclasses.dataclass(frozen=True)
class PilotCommand:
    """One MANUAL_CONTROL to send, in MAVLink units, with its provenance.

    x (pitch, + forward), y (roll, + right), r (yaw, + right) in -1000..1000; z (thrust) in
    0..1000; ``buttons`` 32-bit mask; ``t_ns`` the tick time and ``alive_ns`` the alive report
    the input was judged fresh on (``t_ns - alive_ns < stale_ns`` always holds).
    """

    t_ns: int
    seq: int
    x: int
    y: int
    z: int
    r: int
    buttons: int
    target_system: int
    alive_ns: int

    def to_dict(self) -> dict[str, Any]:
        """Full record for the session recording."""
        return dataclasses.asdict(self)

    def to_payload(self) -> dict[str, Any]:
        """Payload of the ``pilot.command`` bus topic."""
        return {
            "x": self.x, "y": self.y, "z": self.z, "r": self.r,
            "buttons": self.buttons, "enabled": True,
        }  # fmt: skip

    def to_manual_control(self) -> Any:
        """The ``firmware_bridge.mavlink.messages.ManualControl`` record (imported lazily)."""
        return to_manual_control(self, self.target_system)


def to_manual_control(command: PilotCommand, target_system: int) -> Any:
    """Build the firmware bridge's MANUAL_CONTROL record from a command."""
    from firmware_bridge.mavlink.messages import ManualControl

    return ManualControl(
        x=command.x,
        y=command.y,
        z=command.z,
        r=command.r,
        buttons=command.buttons,
        target_system=target_system,
    )


@dataclasses.dataclass(frozen=True)
class Tick:
    """Outcome of one commander tick: the command (None = send nothing) and the events."""

    t_ns: int
    state: str
    reason: str | None
    health: Health
    command: PilotCommand | None
    events: tuple[PilotEvent, ...]
    status: str


class Commander:
    """Builds MANUAL_CONTROL commands from input snapshots at given tick times.

    Parameters
    ----------
    settings : PilotSettings
        Shaping, mux and watchdog settings.
    calibrations : mapping of str to DeviceCalibration, or DeviceCalibration, or None
        Stored calibrations by device name; a device whose name has none does not fly.
    """

    def __init__(
        self,
        settings: PilotSettings,
        calibrations: Mapping[str, DeviceCalibration] | DeviceCalibration | None,
    ):
        self.settings = settings
        if calibrations is None:
            calibrations = {}
        elif isinstance(calibrations, DeviceCalibration):
            calibrations = {calibrations.name: calibrations}
        self._calibrations: dict[str, DeviceCalibration | None] = {}
        for name, cal in calibrations.items():
            try:
                self._calibrations[name] = cal.with_overrides(settings.axis_map, settings.reverse)
            except CalibrationError:
                self._calibrations[name] = None  # axis_map names an axis this device lacks
        self.mux = PilotMux(settings)
        self._slew = SlewLimiter(settings.slew_per_s)
        self._seq = 0

    @property
    def state(self) -> str:
        return self.mux.state

    def calibration_for(self, name: str) -> DeviceCalibration | None:
        """The (override-applied) calibration of device ``name``, or None."""
        return self._calibrations.get(name)

    def tick(self, t_ns: int, snap: InputSnapshot) -> Tick:
        """One control tick at time ``t_ns`` (ns, monotonic; the snapshot's clock)."""
        s = self.settings
        health = assess(
            t_ns,
            alive_ns=snap.alive_ns,
            connected=snap.connected,
            fault=snap.fault,
            stale_ns=s.stale_ns,
        )
        cal = self.calibration_for(snap.name)
        sticks: Sticks | None = None
        calibrated = cal is not None
        if cal is not None and health.ok:
            sticks = calibrated_sticks(snap.axes, cal)
            if sticks is None:
                calibrated = False  # a mapped axis is missing on this device
        buttons = int(snap.buttons) & 0xFFFFFFFF
        events = self.mux.step(MuxInput(t_ns, health, calibrated, sticks, buttons))
        command = None
        if self.mux.sending and sticks is not None and snap.alive_ns is not None:
            shaped = self._slew.step(t_ns, shape(sticks, s.deadband, s.expo))
            x, y, z, r = to_manual_units(shaped)
            command = PilotCommand(
                t_ns, self._seq, x, y, z, r, buttons, s.target_system, snap.alive_ns
            )
            self._seq += 1
        else:
            self._slew.reset()
        return Tick(
            t_ns,
            self.mux.state,
            self.mux.reason,
            health,
            command,
            tuple(events),
            status_line(self.mux.state, self.mux.reason),
        )


class RateSchedule:
    """Absolute tick deadlines ``t0 + k * period`` (integer ns).

    After a late wake-up the next deadline is the first grid point after the tick time: missed
    ticks are counted, never sent in a burst.
    """

    def __init__(self, period_ns: int, t0_ns: int):
        if period_ns <= 0:
            raise ValueError(f"period_ns must be > 0, got {period_ns!r}")
        self.period_ns = int(period_ns)
        self.t0_ns = int(t0_ns)
        self.k = 0
        self.missed = 0

    @property
    def next_ns(self) -> int:
        """The next deadline, ns."""
        return self.t0_ns + self.k * self.period_ns

    def advance(self, t_ns: int) -> int:
        """Record a tick done at ``t_ns``; returns the next deadline (> ``t_ns``)."""
        k_next = (t_ns - self.t0_ns) // self.period_ns + 1
        self.missed += max(0, k_next - self.k - 1)
        self.k = max(k_next, self.k + 1)
        return self.next_ns
