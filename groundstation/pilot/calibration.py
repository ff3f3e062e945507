"""Per-device joystick calibration (pure maths) and its TOML store (thin file I/O).

Raw Linux joystick axis values are signed 16-bit (-32767..32767). A calibrated axis maps its
recorded (min, centre, max) onto -1..1 piecewise linearly on each side of the centre, like
QGroundControl ``Joystick::_adjustRange`` (without its deadband, which lives in
:mod:`groundstation.pilot.shaping`), and onto 0..1 linearly for a down-zero throttle.

The store is one TOML file with a table per device name (the name reported by the
``JSIOCGNAME`` ioctl), written by ``groundstation joystick calibrate``::

    [devices."Logitech Gamepad F310"]
    roll = 3
    pitch = 4
    yaw = 0
    throttle = 1

    [devices."Logitech Gamepad F310".axes.0]
    min = -32767
    centre = 0
    max = 32767
    reversed = false
"""

from __future__ import annotations

import dataclasses
import math
import os
import tempfile
import tomllib
from collections.abc import Mapping
from pathlib import Path

from groundstation.errors import ConfigError
from groundstation.pilot.settings import ROLES

#: Linux joystick axis range (``js_event.value`` is __s16; the kernel reports -32767..32767).
RAW_MIN, RAW_MAX = -32768, 32767


class CalibrationError(ConfigError):
    """A calibration is missing, inconsistent, or its file cannot be read/written."""


@dataclasses.dataclass(frozen=True)
class AxisCalibration:
    """One axis' recorded extremes and centre (raw units) and its direction.

    Parameters
    ----------
    min, centre, max : int
        Raw values at the low extreme, at rest, and at the high extreme; ``min < centre < max``.
    reversed : bool
        Flip the sign of the normalised value (e.g. Linux reports stick-forward as negative Y).
    """

    min: int
    centre: int
    max: int
    reversed: bool = False

    def __post_init__(self) -> None:
        for name in ("min", "centre", "max"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not RAW_MIN <= v <= RAW_MAX:
                raise CalibrationError(
                    f"axis calibration {name} must be an integer in {RAW_MIN}..{RAW_MAX}, got {v!r}"
                )
        if not self.min < self.centre < self.max:
            raise CalibrationError(
                f"axis calibration needs min < centre < max, got "
                f"min={self.min}, centre={self.centre}, max={self.max}",
                hint="re-run 'groundstation joystick calibrate' and move every stick to both ends",
            )
        if not isinstance(self.reversed, bool):
            raise CalibrationError(
                f"axis calibration reversed must be true/false, got {self.reversed!r}"
            )

    def signed(self, raw: float) -> float:
        """Raw value -> -1..1: centre -> 0, max -> +1, min -> -1, clamped; sign flipped if reversed.

        Piecewise linear on each side of the centre (QGroundControl ``_adjustRange``).
        """
        if not math.isfinite(raw):
            return 0.0
        if raw >= self.centre:
            v = (raw - self.centre) / (self.max - self.centre)
        else:
            v = -(self.centre - raw) / (self.centre - self.min)
        v = max(-1.0, min(1.0, v))
        return -v if self.reversed else v

    def unit(self, raw: float) -> float:
        """Raw value -> 0..1 linearly from min to max (max to min if reversed), clamped.

        Down-zero throttle: the stick's low end is zero thrust whether or not it self-centres;
        the centre is not used (QGroundControl ``ThrottleModeDownZero`` with the centre at the
        midpoint).
        """
        if not math.isfinite(raw):
            return 0.0
        v = (raw - self.min) / (self.max - self.min)
        v = max(0.0, min(1.0, v))
        return 1.0 - v if self.reversed else v

    def flipped(self) -> AxisCalibration:
        """The same axis with the opposite direction."""
        return dataclasses.replace(self, reversed=not self.reversed)


@dataclasses.dataclass(frozen=True)
class DeviceCalibration:
    """Calibration of one joystick: per-axis calibrations and which axis flies which role.

    Parameters
    ----------
    name : str
        Device name (``JSIOCGNAME``); the store's key.
    axes : mapping of int to AxisCalibration
        Calibrated device axes.
    roles : mapping of str to int
        Device axis for each of "roll", "pitch", "yaw", "throttle".
    """

    name: str
    axes: Mapping[int, AxisCalibration]
    roles: Mapping[str, int]

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.strip():
            raise CalibrationError(
                f"calibration device name must be a non-empty string, got {self.name!r}"
            )
        missing = [r for r in ROLES if r not in self.roles]
        if missing or set(self.roles) - set(ROLES):
            raise CalibrationError(
                f"calibration of {self.name!r} must map exactly the roles {list(ROLES)}, "
                f"got {sorted(self.roles)}"
            )
        used = [self.roles[r] for r in ROLES]
        if len(set(used)) != 4:
            raise CalibrationError(
                f"calibration of {self.name!r} maps two roles to one axis: {dict(self.roles)}"
            )
        for role in ROLES:
            if self.roles[role] not in self.axes:
                raise CalibrationError(
                    f"calibration of {self.name!r}: {role} is axis {self.roles[role]}, "
                    f"which has no calibration (calibrated axes: {sorted(self.axes)})"
                )
        object.__setattr__(self, "axes", dict(self.axes))
        object.__setattr__(self, "roles", {r: int(self.roles[r]) for r in ROLES})

    def with_overrides(
        self, axis_map: tuple[int, ...] = (), reverse: tuple[str, ...] = ()
    ) -> DeviceCalibration:
        """Apply ``PilotSettings.axis_map`` / ``reverse`` on top of the stored calibration."""
        roles = dict(zip(ROLES, axis_map, strict=True)) if axis_map else dict(self.roles)
        axes = dict(self.axes)
        for role in reverse:
            if roles[role] in axes:
                axes[roles[role]] = axes[roles[role]].flipped()
        return DeviceCalibration(self.name, axes, roles)  # validates an overridden axis_map

    def to_toml_table(self) -> dict[str, object]:
        """Plain-dict form as stored under ``[devices."<name>"]``."""
        table: dict[str, object] = {r: self.roles[r] for r in ROLES}
        table["axes"] = {
            str(k): {"min": a.min, "centre": a.centre, "max": a.max, "reversed": a.reversed}
            for k, a in sorted(self.axes.items())
        }
        return table

    @classmethod
    def from_toml_table(cls, name: str, table: Mapping[str, object]) -> DeviceCalibration:
        """Inverse of :meth:`to_toml_table`; raises :class:`CalibrationError` naming the bad key."""
        where = f"calibration of {name!r}"
        try:
            roles = {r: table[r] for r in ROLES}
            raw_axes = table["axes"]
        except KeyError as exc:
            raise CalibrationError(f"{where}: missing key {exc.args[0]!r}") from None
        if not isinstance(raw_axes, Mapping):
            raise CalibrationError(f"{where}: 'axes' must be a table, got {raw_axes!r}")
        axes: dict[int, AxisCalibration] = {}
        for key, a in raw_axes.items():
            if not str(key).isdigit() or not isinstance(a, Mapping):
                raise CalibrationError(f"{where}: bad axis entry {key!r} = {a!r}")
            try:
                axes[int(key)] = AxisCalibration(
                    a["min"], a["centre"], a["max"], a.get("reversed", False)
                )
            except KeyError as exc:
                raise CalibrationError(f"{where}: axis {key} lacks {exc.args[0]!r}") from None
            except CalibrationError as exc:
                raise CalibrationError(f"{where}: axis {key}: {exc.message}", exc.hint) from None
        for r, v in roles.items():
            if isinstance(v, bool) or not isinstance(v, int):
                raise CalibrationError(f"{where}: {r} must be an axis number, got {v!r}")
        return cls(name, axes, roles)


def _toml_str(s: str) -> str:
    """A TOML basic string (escapes backslash, quote and control characters)."""
    out = []
    for ch in s:
        if ch in ('"', "\\"):
            out.append("\\" + ch)
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04x}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def dumps(calibrations: Mapping[str, DeviceCalibration]) -> str:
    """Render calibrations as the TOML store text (stable order: by device name)."""
    lines = [
        "# Joystick calibrations, one table per device name.",
        "# Written by 'groundstation joystick calibrate'.",
        "",
    ]
    for name in sorted(calibrations):
        cal = calibrations[name]
        key = f"devices.{_toml_str(name)}"
        lines.append(f"[{key}]")
        lines.extend(f"{r} = {cal.roles[r]}" for r in ROLES)
        lines.append("")
        for k, a in sorted(cal.axes.items()):
            lines.append(f"[{key}.axes.{k}]")
            lines.append(f"min = {a.min}")
            lines.append(f"centre = {a.centre}")
            lines.append(f"max = {a.max}")
            lines.append(f"reversed = {'true' if a.reversed else 'false'}")
            lines.append("")
    return "\n".join(lines)


def loads(text: str, source: str = "<string>") -> dict[str, DeviceCalibration]:
    """Parse the TOML store text; raises :class:`CalibrationError` naming the source."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationError(f"calibration file {source} is not valid TOML: {exc}") from None
    devices = doc.get("devices", {})
    if not isinstance(devices, Mapping):
        raise CalibrationError(f"calibration file {source}: 'devices' must be a table")
    return {name: DeviceCalibration.from_toml_table(name, t) for name, t in devices.items()}


def load_calibrations(path: str | os.PathLike[str]) -> dict[str, DeviceCalibration]:
    """Read the store; a missing file is an empty store."""
    p = Path(path).expanduser()
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        return {}
    except OSError as exc:
        raise CalibrationError(f"cannot read calibration file {str(p)!r}: {exc.strerror}") from None
    return loads(text, repr(str(p)))


def find_calibration(path: str | os.PathLike[str], name: str) -> DeviceCalibration | None:
    """The stored calibration of device ``name``, or None (an uncalibrated device does not fly)."""
    return load_calibrations(path).get(name)


def save_calibration(path: str | os.PathLike[str], calibration: DeviceCalibration) -> Path:
    """Insert/replace one device's calibration in the store, atomically (temp file + rename)."""
    p = Path(path).expanduser()
    store = load_calibrations(p)
    store[calibration.name] = calibration
    text = dumps(store)
    loads(text, "<about to be written>")  # never write a file we could not read back
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".joystick-", suffix=".toml", dir=p.parent)
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, p)
    except OSError as exc:
        raise CalibrationError(
            f"cannot write calibration file {str(p)!r}: {exc.strerror}"
        ) from None
    return p
