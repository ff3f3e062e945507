"""Joystick piloting: device shell -> pure shaping (value, t) -> explicit mux (e-stop always
wins) -> watchdog -> MANUAL_CONTROL at a fixed rate (STYLE.md item 16).

Pure core: :mod:`.settings`, :mod:`.calibration` (maths; its store is thin file I/O),
:mod:`.shaping`, :mod:`.watchdog`, :mod:`.mux`, :mod:`.commander`, :mod:`.jsevent` (js_event
codec). Shells: :mod:`.jsdev` (Linux joystick reader thread), :mod:`.loop` (fixed-rate tick
loop); ``groundstation joystick calibrate`` is in ``groundstation.cli.calibrate``.
"""

from __future__ import annotations

from groundstation.pilot.calibration import AxisCalibration, CalibrationError, DeviceCalibration
from groundstation.pilot.commander import Commander, InputSnapshot, PilotCommand, RateSchedule, Tick
from groundstation.pilot.mux import ARMED, DISARMED, ESTOP, FAILSAFE, PilotEvent, PilotMux
from groundstation.pilot.settings import PilotSettings
from groundstation.pilot.shaping import Sticks

__all__ = [
    "ARMED",
    "DISARMED",
    "ESTOP",
    "FAILSAFE",
    "AxisCalibration",
    "CalibrationError",
    "Commander",
    "DeviceCalibration",
    "InputSnapshot",
    "PilotCommand",
    "PilotEvent",
    "PilotMux",
    "PilotSettings",
    "RateSchedule",
    "Sticks",
    "Tick",
]
