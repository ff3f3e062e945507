"""Settings of the pilot path (frozen; validated on construction).

Units: stick values are normalised (-1..1 for roll/pitch/yaw, 0..1 for thrust) wherever a
setting refers to them; times are milliseconds; rates are Hz. ``groundstation.config`` can
build this dataclass from a ``[pilot]`` TOML table (tuples, ``None`` and bools coerce there).
"""

from __future__ import annotations

import dataclasses
import math

from groundstation.errors import ConfigError

#: Stick roles in the order used by :attr:`PilotSettings.axis_map`.
ROLES: tuple[str, str, str, str] = ("roll", "pitch", "yaw", "throttle")
#: Highest allowed MANUAL_CONTROL rate: the issue caps the configurable rate at 50 Hz.
MAX_RATE_HZ = 50.0
#: Default calibration store (one table per device name).
DEFAULT_CALIBRATION_PATH = "~/.config/groundstation/joystick.toml"


@dataclasses.dataclass(frozen=True)
class PilotSettings:
    """How joystick input becomes MANUAL_CONTROL, and when it must stop.

    Attributes
    ----------
    rate_hz : float
        MANUAL_CONTROL send rate, Hz (default 25, at most 50).
    stale_ms : float
        Watchdog: with no "alive" report from the device shell for this long, the station stops
        sending (issue: 200 ms).
    alive_period_ms : float
        Device shell select() timeout, ms: a live character device reports "alive" at least this
        often even when the sticks are still. Must be well under ``stale_ms``.
    deadband : float
        Centre deadband on roll/pitch/yaw, normalised units, rescaled so output stays continuous
        (QGroundControl ``Joystick::_adjustRange``). 0 disables.
    expo : float
        Exponential e in [0, 1]: ``out = e v^3 + (1 - e) v`` (QGroundControl's RC-style expo,
        its slider 0..-50 % is e = 0..0.5). 0 disables.
    slew_per_s : float or None
        Largest change of any shaped axis per second (normalised units / s), None = off.
    axis_map : tuple of int
        Device axes for (roll, pitch, yaw, throttle). Empty: use the mapping stored with the
        device's calibration (written by ``groundstation joystick calibrate``).
    reverse : tuple of str
        Roles whose direction is flipped on top of the calibration's ``reversed`` flag.
    arm_chord : tuple of int
        Buttons that must be held together to arm (two buttons, issue).
    disarm_chord : tuple of int
        Buttons that disarm; empty = the arm chord again (pressed anew).
    estop_button : int
        Emergency-stop button: wins over every other input, latches until released and re-armed.
    centre_tolerance : float
        Arming needs |roll|, |pitch|, |yaw| <= this (normalised, before deadband/expo).
    throttle_low : float
        Arming needs thrust <= this (0..1).
    calibration_path : str
        TOML file of per-device calibrations (``~`` expanded by the shells).
    device_name : str
        Name used when the device cannot report one (FIFO/pipe sources have no ioctls).
    reconnect_min_ms, reconnect_max_ms : float
        Bounded exponential backoff between reopen attempts after device loss.
    target_system : int
        MAVLink system id the MANUAL_CONTROL is addressed to.
    """

    rate_hz: float = 25.0
    stale_ms: float = 200.0
    alive_period_ms: float = 50.0
    deadband: float = 0.05
    expo: float = 0.3
    slew_per_s: float | None = None
    axis_map: tuple[int, ...] = ()
    reverse: tuple[str, ...] = ()
    arm_chord: tuple[int, ...] = (6, 7)
    disarm_chord: tuple[int, ...] = ()
    estop_button: int = 1
    centre_tolerance: float = 0.1
    throttle_low: float = 0.05
    calibration_path: str = DEFAULT_CALIBRATION_PATH
    device_name: str = ""
    reconnect_min_ms: float = 100.0
    reconnect_max_ms: float = 2000.0
    target_system: int = 1

    def __post_init__(self) -> None:
        def bad(name: str, why: str, hint: str | None = None) -> ConfigError:
            return ConfigError(f"pilot.{name} {why}, got {getattr(self, name)!r}", hint=hint)

        for name in ("rate_hz", "stale_ms", "alive_period_ms", "centre_tolerance"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise bad(name, "must be a finite number > 0")
        if self.rate_hz > MAX_RATE_HZ:
            raise bad("rate_hz", f"must be <= {MAX_RATE_HZ:g} Hz", "use 25 Hz (default) to 50 Hz")
        if self.alive_period_ms * 2 > self.stale_ms:
            raise bad(
                "alive_period_ms",
                f"must be at most half of stale_ms ({self.stale_ms:g} ms)",
                "a live idle device must report alive well within the staleness window",
            )
        if not 0 <= self.deadband < 0.5:
            raise bad("deadband", "must be in [0, 0.5)")
        if not 0 <= self.expo <= 1:
            raise bad("expo", "must be in [0, 1] (0 = linear)")
        if self.slew_per_s is not None and not (
            math.isfinite(self.slew_per_s) and self.slew_per_s > 0
        ):
            raise bad("slew_per_s", "must be > 0 or None (off)")
        if self.axis_map and (
            len(self.axis_map) != 4
            or len(set(self.axis_map)) != 4
            or min(self.axis_map) < 0
            or max(self.axis_map) > 255
        ):
            raise bad(
                "axis_map", "must be 4 distinct axis numbers 0..255 (roll, pitch, yaw, throttle)"
            )
        unknown = sorted(set(self.reverse) - set(ROLES))
        if unknown:
            raise bad("reverse", f"has unknown roles {unknown}; known: {list(ROLES)}")
        for name in ("arm_chord", "disarm_chord"):
            chord = getattr(self, name)
            if name == "disarm_chord" and not chord:
                continue
            if len(chord) < 2 or len(set(chord)) != len(chord) or min(chord) < 0:
                raise bad(name, "must be at least two distinct button numbers >= 0")
            if max(chord) > 31:
                raise bad(name, "buttons must be 0..31 (MANUAL_CONTROL carries 32 buttons)")
        if not 0 <= self.estop_button <= 31:
            raise bad("estop_button", "must be a button number 0..31")
        if self.estop_button in self.arm_chord or self.estop_button in self.disarm_chord:
            raise bad("estop_button", "must not be part of the arm or disarm chord")
        if not 0 <= self.throttle_low < 0.5:
            raise bad("throttle_low", "must be in [0, 0.5)")
        if self.centre_tolerance >= 0.5:
            raise bad("centre_tolerance", "must be < 0.5")
        if not 0 < self.reconnect_min_ms <= self.reconnect_max_ms:
            raise bad("reconnect_min_ms", "must be > 0 and <= reconnect_max_ms")
        if not 1 <= self.target_system <= 255:
            raise bad("target_system", "must be a MAVLink system id 1..255")

    @property
    def period_ns(self) -> int:
        """Send period in integer ns."""
        return round(1e9 / self.rate_hz)

    @property
    def stale_ns(self) -> int:
        """Watchdog window in integer ns."""
        return round(self.stale_ms * 1e6)

    @property
    def effective_disarm_chord(self) -> tuple[int, ...]:
        """The disarm chord (the arm chord when none is configured)."""
        return self.disarm_chord or self.arm_chord
