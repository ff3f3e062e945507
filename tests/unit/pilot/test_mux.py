"""The mux: e-stop precedence from every state, faults, chords and every arm condition."""

from __future__ import annotations

import pytest

from groundstation.pilot.mux import (
    ARMED,
    DISARMED,
    ESTOP,
    FAILSAFE,
    STATES,
    MuxInput,
    PilotMux,
    status_line,
)
from groundstation.pilot.settings import PilotSettings
from groundstation.pilot.shaping import Sticks
from groundstation.pilot.watchdog import Health

S = PilotSettings()  # arm chord (6, 7), e-stop 1, centre tolerance 0.1, throttle low 0.05
CHORD = (1 << 6) | (1 << 7)
ESTOP_BIT = 1 << 1
CENTRED = Sticks(0.0, 0.0, 0.0, 0.0)
OK = Health(True, None, 0)


class Driver:
    def __init__(self, settings: PilotSettings = S):
        self.mux = PilotMux(settings)
        self.t = 0
        self.events = []

    def step(self, buttons=0, sticks=CENTRED, health=OK, calibrated=True):
        self.t += 20_000_000
        ev = self.mux.step(MuxInput(self.t, health, calibrated, sticks, buttons))
        self.events.extend(ev)
        return ev

    def press_chord(self, **kw):
        """Release, then press the chord (a rising edge), then release."""
        self.step(0, **kw)
        ev = self.step(CHORD, **kw)
        self.step(0, **kw)
        return ev

    def arm(self):
        self.press_chord()
        assert self.mux.state == ARMED
        return self


def to_state(state: str) -> Driver:
    d = Driver()
    d.step()
    if state == ARMED:
        d.arm()
    elif state == FAILSAFE:
        d.arm().step(health=Health(False, "stale", 300_000_000))
    elif state == ESTOP:
        d.step(ESTOP_BIT)
        d.step(0)
    assert d.mux.state == state
    return d


def test_starts_disarmed_and_arms_on_chord_edge_only():
    d = Driver()
    assert d.mux.state == DISARMED and not d.mux.sending
    d.step(CHORD)  # held from the start: not a press seen after a release
    assert d.mux.state == DISARMED
    d.step(0)
    [ev] = d.step(CHORD)
    assert ev.kind == "armed" and d.mux.state == ARMED and d.mux.sending
    d.step(CHORD)  # still held: no disarm
    assert d.mux.state == ARMED
    d.step(0)
    [ev] = d.step(CHORD)
    assert ev.kind == "disarmed" and d.mux.state == DISARMED


def test_one_button_of_the_chord_does_nothing():
    d = Driver()
    for b in (1 << 6, 1 << 7, 0, 1 << 6):
        d.step(b)
    assert d.mux.state == DISARMED


@pytest.mark.parametrize("state", STATES)
@pytest.mark.parametrize(
    "others",
    [
        dict(),
        dict(buttons_extra=CHORD),
        dict(health=Health(False, "device_lost")),
        dict(health=Health(False, "stale", 10**9)),
        dict(calibrated=False),
        dict(sticks=Sticks(1.0, -1.0, 1.0, 1.0)),
    ],
)
def test_estop_wins_from_every_state_whatever_else_is_true(state, others):
    d = to_state(state)
    kw = dict(others)
    extra = kw.pop("buttons_extra", 0)
    d.step(ESTOP_BIT | extra, **kw)
    assert d.mux.state == ESTOP and not d.mux.sending
    if state != ESTOP:
        assert d.events[-1].kind == "estop" and d.events[-1].previous == state


def test_estop_latches_until_released_and_rearmed_with_all_conditions():
    d = to_state(ARMED)
    d.step(ESTOP_BIT)
    d.step(ESTOP_BIT | CHORD)  # chord while e-stop held: nothing
    assert d.mux.state == ESTOP
    d.step(0)
    for _ in range(5):
        d.step(0)
    assert d.mux.state == ESTOP  # release alone does not resume
    off = Sticks(0.5, 0, 0, 0)
    ev = d.press_chord(sticks=off)
    assert d.mux.state == ESTOP and ev[0].kind == "arm_refused"
    d.press_chord()
    assert d.mux.state == ARMED


@pytest.mark.parametrize(
    "kw, blocker",
    [
        (dict(sticks=Sticks(0.2, 0, 0, 0)), "sticks_not_centred:roll"),
        (dict(sticks=Sticks(0, -0.2, 0, 0)), "sticks_not_centred:pitch"),
        (dict(sticks=Sticks(0, 0, 0.11, 0)), "sticks_not_centred:yaw"),
        (dict(sticks=Sticks(0, 0, float("nan"), 0)), "sticks_not_centred:yaw"),
        (dict(sticks=Sticks(0, 0, 0, 0.06)), "throttle_not_low"),
        (dict(sticks=None), "no_stick_values"),
        (dict(calibrated=False), None),
        (dict(health=Health(False, "stale", 10**9)), None),
        (dict(health=Health(False, "device_lost")), None),
        (dict(health=Health(False, "read_error")), None),
    ],
)
def test_each_missing_arm_condition_prevents_arming(kw, blocker):
    d = Driver()
    d.press_chord(**kw)
    assert d.mux.state in (DISARMED, FAILSAFE) and not d.mux.sending
    if blocker is not None:
        refused = [e for e in d.events if e.kind == "arm_refused"]
        assert refused and blocker in refused[0].text
    # and the same pilot, with everything in order, does arm
    d.press_chord()
    assert d.mux.state == ARMED


def test_estop_held_prevents_arming():
    d = Driver()
    d.step(ESTOP_BIT)
    d.step(ESTOP_BIT | CHORD)
    assert d.mux.state == ESTOP


def test_within_tolerance_arms():
    d = Driver()
    d.press_chord(sticks=Sticks(0.1, -0.1, 0.09, 0.05))
    assert d.mux.state == ARMED


@pytest.mark.parametrize("reason", ["device_lost", "read_error", "stale", "no_input"])
def test_fault_while_armed_is_failsafe_with_loud_reason(reason):
    d = to_state(ARMED)
    [ev] = d.step(health=Health(False, reason))
    assert d.mux.state == FAILSAFE and ev.kind == "failsafe" and ev.reason == reason
    assert "NOT SENDING" in ev.text and "!!!" in status_line(FAILSAFE, reason)


def test_uncalibrated_is_failsafe():
    d = to_state(ARMED)
    [ev] = d.step(calibrated=False)
    assert d.mux.state == FAILSAFE and ev.reason == "uncalibrated"


def test_no_resume_without_centred_sticks_low_throttle_and_chord():
    d = to_state(ARMED)
    d.step(health=Health(False, "device_lost"))
    # device back, sticks off-centre: input restored, still failsafe, never sending
    [ev] = d.step(sticks=Sticks(0.5, 0, 0, 0))
    assert ev.kind == "input_restored" and d.mux.state == FAILSAFE
    d.press_chord(sticks=Sticks(0.5, 0, 0, 0))
    assert d.mux.state == FAILSAFE
    d.press_chord(sticks=Sticks(0, 0, 0, 0.5))  # centred but throttle high
    assert d.mux.state == FAILSAFE
    for _ in range(10):  # centred and low, no chord
        d.step()
    assert d.mux.state == FAILSAFE and not d.mux.sending
    d.press_chord()
    assert d.mux.state == ARMED


def test_chord_held_through_a_loss_does_not_arm_on_return():
    d = to_state(ARMED)
    d.step(CHORD)  # chord held, still armed (no new press)
    d.step(CHORD, health=Health(False, "device_lost"))
    for _ in range(5):
        d.step(CHORD)  # device back (e.g. INIT burst) with the chord held, all else fine
    assert d.mux.state == FAILSAFE
    d.step(0)
    d.step(CHORD)
    assert d.mux.state == ARMED


def test_failsafe_reason_changes_are_events_and_distinct_disarm_chord_acknowledges():
    s = PilotSettings(arm_chord=(6, 7), disarm_chord=(4, 5))
    d = Driver(s)
    d.press_chord()
    assert d.mux.state == ARMED
    d.step(health=Health(False, "read_error"))
    d.step(health=Health(False, "device_lost"))
    assert [e.kind for e in d.events[-2:]] == ["failsafe", "failsafe_reason"]
    d.step()
    d.step((1 << 4) | (1 << 5))
    assert d.mux.state == DISARMED and d.events[-1].kind == "disarmed"


def test_event_records_are_plain_dicts():
    d = Driver()
    d.press_chord()
    rec = d.events[-1].to_dict()
    assert rec["kind"] == "armed" and rec["state"] == ARMED and rec["previous"] == DISARMED
    assert d.events[-1].to_payload() == {"event": "armed", "text": rec["text"]}
