"""Commander + watchdog with explicit times: the 200 ms rule, records, rate schedule, settings."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from groundstation.errors import ConfigError
from groundstation.pilot.calibration import AxisCalibration, DeviceCalibration
from groundstation.pilot.commander import Commander, InputSnapshot, RateSchedule
from groundstation.pilot.mux import ARMED, FAILSAFE
from groundstation.pilot.settings import PilotSettings
from groundstation.pilot.watchdog import assess

MS = 1_000_000
NAME = "Test Pad"
CAL = DeviceCalibration(
    NAME,
    {
        0: AxisCalibration(-32767, 0, 32767),
        1: AxisCalibration(-32767, 0, 32767, reversed=True),
        2: AxisCalibration(-32767, 0, 32767),
        3: AxisCalibration(-32767, 0, 32767, reversed=True),
    },
    {"roll": 0, "pitch": 1, "yaw": 2, "throttle": 3},
)
CENTRED = {0: 0, 1: 0, 2: 0, 3: 32767}  # throttle axis reversed: +32767 is stick down
CHORD = (1 << 6) | (1 << 7)


def snap(alive_ns, axes=CENTRED, buttons=0, connected=True, fault=None, name=NAME):
    return InputSnapshot(name, connected, alive_ns, fault, dict(axes), buttons)


DEFAULT = PilotSettings()


def armed_commander(s: PilotSettings = DEFAULT, t0: int = 0) -> Commander:
    c = Commander(s, CAL)
    c.tick(t0, snap(t0))
    c.tick(t0 + 1, snap(t0, buttons=CHORD))
    assert c.state == ARMED
    return c


def test_watchdog_rule_at_the_boundary():
    kw = dict(connected=True, fault=None, stale_ns=200 * MS)
    assert assess(199 * MS, alive_ns=0, **kw).ok
    h = assess(200 * MS, alive_ns=0, **kw)
    assert not h.ok and h.reason == "stale" and h.age_ns == 200 * MS
    assert assess(5, alive_ns=None, **kw).reason == "no_input"
    assert assess(5, alive_ns=4, connected=False, fault=None, stale_ns=10).reason == "device_lost"
    assert (
        assess(5, alive_ns=4, connected=True, fault="read_error", stale_ns=10).reason
        == "read_error"
    )


def test_commands_stop_exactly_at_200_ms_after_the_last_alive_report():
    c = armed_commander()
    out = [c.tick(t, snap(0)) for t in range(2 * MS, 400 * MS, 5 * MS)]
    sent = [tk.t_ns for tk in out if tk.command is not None]
    assert sent and max(sent) < 200 * MS
    assert all(tk.command is None for tk in out if tk.t_ns >= 200 * MS)
    fs = [e for tk in out for e in tk.events if e.kind == "failsafe"]
    assert len(fs) == 1 and fs[0].reason == "stale" and fs[0].t_ns == 202 * MS
    assert c.state == FAILSAFE and "STALE" in out[-1].status


@settings(max_examples=200, deadline=None)
@given(
    alive_gaps=st.lists(st.integers(1, 400), min_size=1, max_size=40),
    tick_ms=st.integers(20, 40),
)
def test_no_command_is_ever_built_from_input_staler_than_stale_ms(alive_gaps, tick_ms):
    """Random alive reports (gaps 1..400 ms), ticks at 25-50 Hz: every command is fresh."""
    c = armed_commander()
    alive = [0]
    for g in alive_gaps:
        alive.append(alive[-1] + g * MS)
    i = 0
    t = 2 * MS
    while t < alive[-1] + 300 * MS:
        while i + 1 < len(alive) and alive[i + 1] <= t:
            i += 1
        tk = c.tick(t, snap(alive[i]))
        if tk.command is not None:
            assert t - alive[i] < 200 * MS and tk.command.alive_ns == alive[i]
        if t - alive[i] >= 200 * MS:
            assert tk.command is None and tk.state == FAILSAFE
        t += tick_ms * MS
    assert c.state == FAILSAFE  # the stream ended: never silently resumes


@pytest.mark.parametrize(
    "bad",
    [
        dict(connected=False),
        dict(fault="device_lost"),
        dict(fault="read_error"),
        dict(name="Other"),
    ],
)
def test_device_loss_read_error_or_unknown_device_stops_sending_at_once(bad):
    c = armed_commander()
    tk = c.tick(10 * MS, snap(9 * MS, **bad))
    assert tk.command is None and tk.state == FAILSAFE
    expected = {"connected": "device_lost", "fault": bad.get("fault"), "name": "uncalibrated"}
    assert tk.reason == expected[next(iter(bad))]


def test_uncalibrated_device_never_flies():
    c = Commander(PilotSettings(), None)
    ticks = [c.tick(t * MS, snap(t * MS, buttons=CHORD if t % 2 else 0)) for t in range(50)]
    assert all(tk.command is None for tk in ticks) and c.state == FAILSAFE
    assert ticks[-1].reason == "uncalibrated"


def test_command_mapping_pitch_forward_roll_right_thrust_yaw():
    c = armed_commander(PilotSettings(deadband=0.0, expo=0.0))
    # Linux: roll right +, pitch forward -, yaw right +, throttle up -
    tk = c.tick(10 * MS, snap(9 * MS, {0: 16384, 1: -32767, 2: -32767, 3: -32767}, buttons=1 << 3))
    cmd = tk.command
    assert (cmd.x, cmd.y, cmd.z, cmd.r) == (1000, 500, 1000, -1000)
    assert cmd.buttons == 1 << 3 and cmd.target_system == 1
    assert cmd.to_payload() == {
        "x": 1000, "y": 500, "z": 1000, "r": -1000, "buttons": 8, "enabled": True,
    }  # fmt: skip
    mc = cmd.to_manual_control()
    assert (mc.x, mc.y, mc.z, mc.r, mc.buttons, mc.target_system) == (1000, 500, 1000, -1000, 8, 1)
    assert cmd.to_dict()["seq"] == 1  # the arming tick sent seq 0


def test_slew_limit_applies_between_ticks():
    c = armed_commander(PilotSettings(deadband=0.0, expo=0.0, slew_per_s=2.0))
    full = {0: 32767, 1: 0, 2: 0, 3: 32767}
    ys = [c.tick(t * MS, snap(t * MS, full)).command.y for t in range(40, 1000, 40)]
    assert ys[0] == 80 and ys[1] == 160  # 2 /s * 40 ms = 0.08 per tick
    assert ys[-1] == 1000 and all(b - a <= 80 for a, b in zip(ys, ys[1:], strict=False))


def test_records_fit_the_bus_topic_table():
    topics = pytest.importorskip("groundstation.bus.topics")
    c = Commander(PilotSettings(), CAL)
    ticks = [c.tick(0, snap(0)), c.tick(MS, snap(MS, buttons=CHORD)), c.tick(2 * MS, snap(2 * MS))]
    events = [e for tk in ticks for e in tk.events]
    assert events and ticks[-1].command is not None
    for e in events:
        topics.get_topic("pilot.event").validate(e.to_payload(), {})
    topics.get_topic("pilot.command").validate(ticks[-1].command.to_payload(), {})


def test_rate_schedule_is_drift_free_and_skips_missed_deadlines():
    r = RateSchedule(40 * MS, 1000)
    assert r.next_ns == 1000
    assert r.advance(1000 + 3 * MS) == 1000 + 40 * MS
    assert r.advance(1000 + 41 * MS) == 1000 + 80 * MS
    assert r.advance(1000 + 205 * MS) == 1000 + 240 * MS and r.missed == 3
    assert r.advance(1000 + 239 * MS) == 1000 + 280 * MS  # early wake: still moves on
    with pytest.raises(ValueError):
        RateSchedule(0, 0)


@pytest.mark.parametrize(
    "kw, word",
    [
        (dict(rate_hz=60), "<= 50"),
        (dict(rate_hz=0), "rate_hz"),
        (dict(stale_ms=float("nan")), "stale_ms"),
        (dict(alive_period_ms=150), "half of stale_ms"),
        (dict(deadband=0.6), "deadband"),
        (dict(expo=-0.1), "expo"),
        (dict(slew_per_s=0.0), "slew_per_s"),
        (dict(axis_map=(0, 1, 1, 2)), "axis_map"),
        (dict(reverse=("roll", "elevator")), "elevator"),
        (dict(arm_chord=(6,)), "arm_chord"),
        (dict(arm_chord=(6, 40)), "0..31"),
        (dict(estop_button=6), "estop_button"),
        (dict(throttle_low=0.7), "throttle_low"),
        (dict(target_system=0), "target_system"),
    ],
)
def test_settings_validation_names_the_setting(kw, word):
    with pytest.raises(ConfigError, match=word):
        PilotSettings(**kw)


def test_settings_defaults_and_config_loader_round_trip():
    s = PilotSettings()
    assert s.rate_hz == 25 and s.stale_ms == 200 and s.period_ns == 40 * MS
    assert s.effective_disarm_chord == s.arm_chord
    assert PilotSettings(rate_hz=50).period_ns == 20 * MS
    from groundstation.config import _build

    built = _build(
        PilotSettings, {"rate_hz": "50", "axis_map": "0,1,3,2", "slew_per_s": "none"}, "pilot."
    )
    assert built.rate_hz == 50.0 and built.axis_map == (0, 1, 3, 2) and built.slew_per_s is None
