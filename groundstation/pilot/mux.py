"""Arm / disarm / e-stop / failsafe state machine (pure: time and inputs come in per step).

States and what the commander sends in each:

==========  ===========  =====================================================================
state       sends        left by
==========  ===========  =====================================================================
DISARMED    nothing      arm chord (pressed anew) with every arm condition met -> ARMED
ARMED       MANUAL_CTRL  disarm chord -> DISARMED; input fault -> FAILSAFE; e-stop -> ESTOP
FAILSAFE    nothing      arm chord with every arm condition met -> ARMED; a distinct disarm
                         chord (fault cleared) -> DISARMED
ESTOP       nothing      e-stop released, then arm chord with every arm condition -> ARMED
==========  ===========  =====================================================================

Precedence, checked in this order on every step: **e-stop** (from any state, even with stale or
lost input: its last known press is honoured) > input fault (device lost, read error, stale, no
input, uncalibrated) > chords.

E-stop decision: nothing at all is sent in ESTOP -- not even a final zero-thrust command. What a
zero-thrust MANUAL_CONTROL means depends on the vehicle's mode (PX4 position mode and our SITL
read z = 0 as "descend at full rate", manual/stabilised as motors-to-idle, i.e. fall), so it is
not a safe universal stop; silence makes the vehicle's own failsafe act, exactly as for a lost
joystick. The "estop" event is recorded and published so the link process can add a real kill
(MAV_CMD_COMPONENT_ARM_DISARM force / flight termination) where the operator configured one.

Arm conditions (each missing one refuses, with the reasons in an ``arm_refused`` event):
input healthy, device calibrated, e-stop released, roll/pitch/yaw within ``centre_tolerance``,
thrust <= ``throttle_low``, and the arm chord **pressed anew** (a rising edge: all chord buttons
held now, not all held on the previous step). After any fault the chords are treated as held
until seen released, so a chord held through a device loss, or replayed by the kernel's INIT
burst on reconnect, never arms by itself.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from groundstation.pilot.settings import PilotSettings
from groundstation.pilot.shaping import Sticks
from groundstation.pilot.watchdog import Health

DISARMED, ARMED, FAILSAFE, ESTOP = "DISARMED", "ARMED", "FAILSAFE", "ESTOP"
STATES = (DISARMED, ARMED, FAILSAFE, ESTOP)

_REASON_TEXT = {
    "device_lost": "JOYSTICK LOST",
    "read_error": "JOYSTICK READ ERROR",
    "stale": "JOYSTICK INPUT STALE",
    "no_input": "NO JOYSTICK INPUT",
    "uncalibrated": "JOYSTICK NOT CALIBRATED",
}


@dataclasses.dataclass(frozen=True)
class MuxInput:
    """Everything the state machine looks at on one step.

    Attributes
    ----------
    t_ns : int
        Step (tick) time, ns, monotonic.
    health : Health
        Watchdog verdict at ``t_ns``.
    calibrated : bool
        A calibration for this device (by name) covering the mapped axes exists.
    sticks : Sticks or None
        Calibrated, unshaped sticks (None when unknown).
    buttons : int
        Button bit mask (bit n = button n held).
    """

    t_ns: int
    health: Health
    calibrated: bool
    sticks: Sticks | None
    buttons: int


@dataclasses.dataclass(frozen=True)
class PilotEvent:
    """A pilot-path event for the recorder, the bus (``pilot.event``) and the status line.

    ``kind``: "armed", "disarmed", "failsafe", "failsafe_reason", "input_restored", "estop",
    "arm_refused".
    """

    t_ns: int
    kind: str
    state: str
    previous: str
    reason: str | None = None
    text: str = ""

    def to_dict(self) -> dict[str, Any]:
        """Full record for the session recording."""
        return dataclasses.asdict(self)

    def to_payload(self) -> dict[str, Any]:
        """Payload of the ``pilot.event`` bus topic (time travels in the header's source_ns)."""
        return {"event": self.kind, "text": self.text}


def status_line(state: str, reason: str | None) -> str:
    """One loud line for the terminal status: what the pilot path is doing and why."""
    if state == ARMED:
        return "PILOT: ARMED - sending MANUAL_CONTROL"
    if state == DISARMED:
        return "PILOT: disarmed - not sending"
    if state == ESTOP:
        extra = f" ({_REASON_TEXT.get(reason, reason)})" if reason else ""
        return f"!!! PILOT: EMERGENCY STOP{extra} - NOT SENDING - release e-stop and re-arm !!!"
    if reason:
        return (
            f"!!! PILOT FAILSAFE: {_REASON_TEXT.get(reason, reason)} - NOT SENDING - "
            "vehicle failsafe in charge !!!"
        )
    return "!!! PILOT FAILSAFE: input back - centre sticks, throttle low, press arm chord !!!"


class PilotMux:
    """The explicit mux: e-stop always wins, then input faults, then the arm/disarm chords."""

    def __init__(self, settings: PilotSettings):
        self.settings = settings
        self.state = DISARMED
        self.reason: str | None = None  # fault currently holding FAILSAFE (None = cleared)
        # Treat the chords as held at start: they must be seen released before they count.
        self._arm_prev = True
        self._disarm_prev = True

    @property
    def sending(self) -> bool:
        """True only in ARMED."""
        return self.state == ARMED

    def _held(self, buttons: int, chord: tuple[int, ...]) -> bool:
        return all(buttons >> b & 1 for b in chord)

    def arm_blockers(self, inp: MuxInput, fault: str | None) -> list[str]:
        """Reasons arming is not allowed now (empty = allowed)."""
        s = self.settings
        out: list[str] = []
        if fault is not None:
            out.append(fault)
        if inp.buttons >> s.estop_button & 1:
            out.append("estop_held")
        if inp.sticks is None:
            if fault is None:
                out.append("no_stick_values")
            return out
        off = [
            n
            for n in ("roll", "pitch", "yaw")
            if not abs(getattr(inp.sticks, n)) <= s.centre_tolerance  # NaN counts as off-centre
        ]
        if off:
            out.append("sticks_not_centred:" + ",".join(off))
        if not inp.sticks.throttle <= s.throttle_low:
            out.append("throttle_not_low")
        return out

    def step(self, inp: MuxInput) -> list[PilotEvent]:
        """Advance one step; returns the events it caused (state changes and refusals)."""
        s = self.settings
        events: list[PilotEvent] = []

        def go(state: str, kind: str, reason: str | None, text: str) -> None:
            events.append(PilotEvent(inp.t_ns, kind, state, self.state, reason, text))
            self.state = state

        fault = inp.health.reason if not inp.health.ok else None
        if fault is None and not inp.calibrated:
            fault = "uncalibrated"
        estop = bool(inp.buttons >> s.estop_button & 1)
        arm_held = self._held(inp.buttons, s.arm_chord)
        disarm_held = self._held(inp.buttons, s.effective_disarm_chord)
        arm_edge = arm_held and not self._arm_prev and fault is None
        disarm_edge = disarm_held and not self._disarm_prev and fault is None
        same_chord = tuple(sorted(s.arm_chord)) == tuple(sorted(s.effective_disarm_chord))

        def try_arm() -> None:
            blockers = self.arm_blockers(inp, fault)
            if blockers:
                events.append(
                    PilotEvent(
                        inp.t_ns, "arm_refused", self.state, self.state, blockers[0],
                        "arm refused: " + ", ".join(blockers),
                    )
                )  # fmt: skip
            else:
                self.reason = None
                go(ARMED, "armed", None, "armed: sending MANUAL_CONTROL")

        if estop:
            if self.state != ESTOP:
                self.reason = fault
                go(ESTOP, "estop", fault, "EMERGENCY STOP pressed: MANUAL_CONTROL stopped")
        elif fault is not None:
            if self.state in (DISARMED, ARMED):
                self.reason = fault
                go(FAILSAFE, "failsafe", fault, status_line(FAILSAFE, fault))
            elif self.state == FAILSAFE and fault != self.reason:
                self.reason = fault
                go(FAILSAFE, "failsafe_reason", fault, status_line(FAILSAFE, fault))
            elif self.state == ESTOP:
                self.reason = fault
        else:
            if self.state == FAILSAFE and self.reason is not None:
                self.reason = None
                go(FAILSAFE, "input_restored", None, status_line(FAILSAFE, None))
            elif self.state == ESTOP:
                self.reason = None
            if self.state == ARMED:
                if disarm_edge:
                    go(DISARMED, "disarmed", None, "disarmed by chord")
            elif arm_edge:
                try_arm()
            elif disarm_edge and not same_chord and self.state == FAILSAFE:
                go(DISARMED, "disarmed", None, "failsafe acknowledged: disarmed")

        if fault is not None:
            # Chords must be seen released after a fault before they count again.
            self._arm_prev = self._disarm_prev = True
        else:
            self._arm_prev, self._disarm_prev = arm_held, disarm_held
        return events
