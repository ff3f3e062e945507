"""End to end with real threads: FIFO -> device shell -> fixed-rate loop -> commands.

Checks, counting commands (never timing them): sending stops after the writer goes silent or
closes (no command is built from input >= 200 ms past its last alive report, and only a loose
number after the last byte), no resume without centred sticks + low throttle + a fresh chord
(including a chord replayed by the INIT burst on reconnect), and e-stop precedence.
"""

from __future__ import annotations

import math
import os
import threading

import pytest

from groundstation.pilot.calibration import AxisCalibration, DeviceCalibration
from groundstation.pilot.commander import Commander, Tick
from groundstation.pilot.jsdev import JoystickDevice
from groundstation.pilot.loop import run_pilot_loop
from groundstation.pilot.mux import ARMED, ESTOP, FAILSAFE
from groundstation.pilot.settings import PilotSettings
from tests.unit.pilot.fifo_joystick import FULL, FifoJoystick

pytestmark = pytest.mark.timeout(90)

NAME = "Fifo Pad"
SETTINGS = PilotSettings(rate_hz=50, device_name=NAME, reconnect_min_ms=10, reconnect_max_ms=80)
CAL = DeviceCalibration(
    NAME,
    {
        0: AxisCalibration(-FULL, 0, FULL),
        1: AxisCalibration(-FULL, 0, FULL, reversed=True),
        2: AxisCalibration(-FULL, 0, FULL),
        3: AxisCalibration(-FULL, 0, FULL, reversed=True),
    },
    {"roll": 0, "pitch": 1, "yaw": 2, "throttle": 3},
)
LOW = FULL  # throttle axis is reversed (Linux: up is negative): +FULL is stick down
CHORD = {6: True, 7: True}
UNCHORD = {6: False, 7: False}


class Sink:
    """Collects ticks; tests wait on it by counting ticks, with a generous timeout."""

    def __init__(self):
        self.ticks: list[Tick] = []
        self.cond = threading.Condition()

    def __call__(self, tick: Tick) -> None:
        with self.cond:
            self.ticks.append(tick)
            self.cond.notify_all()

    def wait(self, pred, timeout: float = 10.0) -> Tick:
        with self.cond:
            ok = self.cond.wait_for(lambda: self.ticks and pred(self.ticks[-1]), timeout)
            assert ok, f"timed out; last status: {self.ticks[-1].status if self.ticks else None}"
            return self.ticks[-1]

    def more(self, n: int, timeout: float = 10.0) -> list[Tick]:
        """Wait for n more ticks and return them."""
        with self.cond:
            start = len(self.ticks)
            assert self.cond.wait_for(lambda: len(self.ticks) >= start + n, timeout)
            return self.ticks[start : start + n]

    def events(self, since: int = 0):
        with self.cond:
            return [e for t in self.ticks[since:] for e in t.events]

    def commands(self, since: int = 0):
        with self.cond:
            return [t.command for t in self.ticks[since:] if t.command is not None]


@pytest.fixture
def rig(tmp_path):
    path = str(tmp_path / "js0")
    os.mkfifo(path)
    device = JoystickDevice(
        path, name=NAME, alive_period_ms=SETTINGS.alive_period_ms, reconnect_min_ms=10,
        reconnect_max_ms=80,
    )  # fmt: skip
    device.start()
    sink = Sink()
    stop = threading.Event()
    commander = Commander(SETTINGS, CAL)
    loop = threading.Thread(
        target=run_pilot_loop, args=(device.snapshot, commander, sink, stop), daemon=True
    )
    loop.start()
    writers: list[FifoJoystick] = []

    def new_writer(axes=(0, 0, 0, LOW), buttons=None) -> FifoJoystick:
        w = FifoJoystick(path, n_axes=4, n_buttons=8)
        w.axes[:] = list(axes)
        for n, v in (buttons or {}).items():
            w.buttons[n] = v
        writers.append(w)
        w.open()
        w.start_heartbeat(0.01)
        return w

    yield device, sink, new_writer
    stop.set()
    loop.join(5)
    for w in writers:
        w.close()
    device.stop()
    assert not loop.is_alive()


def settle(device, sink, n=3):
    """All bytes written so far are applied, and the loop has ticked on them."""
    assert device.barrier(5)
    return sink.more(n)


def press_chord(w, device, sink):
    w.buttons_to(UNCHORD)
    settle(device, sink)
    w.buttons_to(CHORD)
    settle(device, sink)
    w.buttons_to(UNCHORD)
    settle(device, sink)


def arm(w, device, sink):
    sink.wait(lambda t: t.health.ok)
    press_chord(w, device, sink)
    sink.wait(lambda t: t.state == ARMED)
    assert sink.commands()


def assert_every_command_fresh(sink):
    for tk in sink.ticks:
        if tk.command is not None:
            assert tk.health.ok and tk.t_ns - tk.command.alive_ns < SETTINGS.stale_ns


def max_after_loss() -> int:
    """Loose bound on commands after the last byte: the 200 ms window at 50 Hz, plus slack."""
    return math.ceil(SETTINGS.stale_ms / 1000 * SETTINGS.rate_hz) + 3


def test_silent_writer_stops_sending_within_the_stale_window(rig):
    device, sink, new_writer = rig
    w = new_writer()
    arm(w, device, sink)
    w.set_axes(a0=16384)  # roll right: commands follow the stick
    settle(device, sink)
    assert sink.commands()[-1].y > 300
    n0 = len(sink.ticks)
    last_write = w.stop_heartbeat()  # the FIFO stays open but says nothing more
    tk = sink.wait(lambda t: t.state == FAILSAFE)
    assert tk.reason == "stale" and "STALE" in tk.status and "NOT SENDING" in tk.status
    after = [c for c in sink.commands(n0) if c.t_ns > last_write]
    assert len(after) <= max_after_loss()
    quiet = sink.more(10)
    assert all(t.command is None for t in quiet)
    assert_every_command_fresh(sink)
    fs = [e for e in sink.events(n0) if e.kind == "failsafe"]
    assert len(fs) == 1 and fs[0].reason == "stale"


def test_device_loss_then_no_resume_without_centre_low_throttle_and_fresh_chord(rig):
    device, sink, new_writer = rig
    w = new_writer()
    arm(w, device, sink)
    n0 = len(sink.ticks)
    last_write = w.close()  # EOF: device lost
    tk = sink.wait(lambda t: t.state == FAILSAFE)
    assert tk.reason == "device_lost" and "JOYSTICK LOST" in tk.status
    assert len([c for c in sink.commands(n0) if c.t_ns > last_write]) <= max_after_loss()

    # back, with the chord held in the INIT burst and the sticks off-centre
    w = new_writer(axes=(12000, 0, 0, LOW), buttons=CHORD)
    sink.wait(lambda t: t.health.ok)
    n1 = len(sink.ticks)
    assert "input_restored" in [e.kind for e in sink.events(n0)]
    settle(device, sink, 5)
    assert sink.ticks[-1].state == FAILSAFE  # a chord replayed on reconnect never arms
    w.buttons_to(UNCHORD)
    settle(device, sink)
    w.buttons_to(CHORD)
    settle(device, sink)
    w.buttons_to(UNCHORD)
    settle(device, sink)
    refused = [e for e in sink.events(n1) if e.kind == "arm_refused"]
    assert refused and "sticks_not_centred:roll" in refused[-1].text

    w.set_axes(a0=0, a3=-FULL)  # centred, throttle HIGH
    settle(device, sink)
    press_chord(w, device, sink)
    refused = [e for e in sink.events(n1) if e.kind == "arm_refused"]
    assert "throttle_not_low" in refused[-1].text

    w.set_axes(a3=LOW)  # centred and low, but no chord
    settle(device, sink, 10)
    assert all(t.state == FAILSAFE and t.command is None for t in sink.ticks[n1:])

    press_chord(w, device, sink)
    sink.wait(lambda t: t.state == ARMED and t.command is not None)
    assert_every_command_fresh(sink)


def test_estop_wins_and_latches_until_released_and_rearmed(rig):
    device, sink, new_writer = rig
    w = new_writer()
    arm(w, device, sink)
    w.set_axes(a1=-FULL, a3=-FULL)  # full forward, full thrust
    settle(device, sink)
    w.buttons_to({1: True})
    sink.wait(lambda t: t.state == ESTOP)
    n0 = len(sink.ticks)
    w.buttons_to({1: True, 6: True, 7: True})  # chord while e-stop held
    settle(device, sink, 5)
    w.buttons_to({1: False, 6: False, 7: False})  # released: still latched
    settle(device, sink, 5)
    assert all(t.state == ESTOP and t.command is None for t in sink.ticks[n0:])
    press_chord(w, device, sink)  # sticks still deflected: refused
    assert sink.ticks[-1].state == ESTOP
    w.set_axes(a1=0, a3=LOW)
    settle(device, sink)
    press_chord(w, device, sink)
    tk = sink.wait(lambda t: t.state == ARMED and t.command is not None)
    assert (tk.command.x, tk.command.z) == (0, 0)
    kinds = [e.kind for e in sink.events()]
    assert kinds.count("estop") == 1 and kinds[-1] == "armed"
