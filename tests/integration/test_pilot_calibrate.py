"""``groundstation joystick calibrate`` end to end: scripted stdin + a FIFO of js_events."""

from __future__ import annotations

import os
import queue
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from groundstation.cli.calibrate import deflection, extremes, pick_axis
from groundstation.pilot.calibration import load_calibrations
from groundstation.pilot.commander import Commander, InputSnapshot
from groundstation.pilot.jsdev import JS_EVENT_AXIS, JsEvent, encode_events
from groundstation.pilot.settings import PilotSettings
from tests.unit.pilot.fifo_joystick import FULL, FifoJoystick

pytestmark = pytest.mark.timeout(90)
ROOT = Path(__file__).resolve().parents[2]
NAME = "Fifo Gamepad"
# Gamepad layout (Linux xpad-like): 0 left X (yaw), 1 left Y (throttle, up negative),
# 2 left trigger (rests at -FULL), 3 right X (roll), 4 right Y (pitch, forward negative), 5 trigger
REST = [0, 0, -FULL, 250, -120, -FULL]


class Cli:
    def __init__(self, fifo: str, out: Path, *extra: str):
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "groundstation.cli", "joystick", "calibrate",
             "--device", fifo, "--name", NAME, "--out", str(out), "--timeout", "20", *extra],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True, cwd=ROOT, env=env,
        )  # fmt: skip
        self.lines: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        threading.Thread(target=self._pump, daemon=True).start()

    def _pump(self) -> None:
        for line in self.proc.stdout:
            self.lines.put(line)
        self.lines.put("")

    def expect(self, text: str, timeout: float = 30.0) -> str:
        while True:
            line = self.lines.get(timeout=timeout)
            self.seen.append(line)
            if line == "":
                raise AssertionError(f"CLI ended before {text!r}: {''.join(self.seen)}")
            if text in line:
                return line

    def enter(self, text: str = "") -> None:
        self.proc.stdin.write(text + "\n")
        self.proc.stdin.flush()

    def finish(self, timeout: float = 30.0) -> tuple[int, str]:
        try:
            self.proc.stdin.close()
        except BrokenPipeError:
            pass
        rc = self.proc.wait(timeout)
        return rc, self.proc.stderr.read()


@pytest.fixture
def fifo(tmp_path):
    path = str(tmp_path / "js0")
    os.mkfifo(path)
    return path


def open_writer(fifo: str) -> FifoJoystick:
    w = FifoJoystick(fifo, n_axes=6, n_buttons=11)
    w.axes[:] = REST
    return w.open(timeout=30)


def sweep(w: FifoJoystick, axes) -> None:
    """Move each axis through both ends and back (several intermediate events)."""
    for a in axes:
        for v in (-8000, -20000, -FULL, -30000, 0, 15000, FULL, 31000, REST[a]):
            w.set_axes(**{f"a{a}": v})


def test_calibrate_walks_through_and_stores_by_device_name(fifo, tmp_path):
    out = tmp_path / "cfg" / "joystick.toml"
    cli = Cli(fifo, out)
    w = open_writer(fifo)
    cli.expect("[step 1/6]")
    w.set_axes(a3=250, a4=-120)  # resting sticks (slightly off zero)
    cli.enter()
    cli.expect("[step 2/6]")
    sweep(w, (0, 1, 3, 4))
    cli.enter()
    moved = cli.expect("axes that moved")
    assert "[0, 1, 3, 4]" in moved
    pushes = [("roll", {"a3": FULL}), ("pitch", {"a4": -FULL}), ("yaw", {"a0": FULL}),
              ("throttle", {"a1": -FULL})]  # fmt: skip
    for k, (role, push) in enumerate(pushes, start=3):
        cli.expect(f"[step {k}/6]")
        w.set_axes(a0=REST[0], a1=REST[1], a3=REST[3], a4=REST[4])  # let go of the last one
        w.set_axes(**push)
        cli.enter()
        assert role in cli.expect(f"  {role}:")
    cli.expect("save to")
    cli.enter("y")
    rc, err = cli.finish()
    w.close()
    assert rc == 0, err
    cal = load_calibrations(out)[NAME]
    assert cal.roles == {"roll": 3, "pitch": 4, "yaw": 0, "throttle": 1}
    assert cal.axes[3].centre == 250 and cal.axes[4].centre == -120
    assert (cal.axes[3].min, cal.axes[3].max) == (-FULL, FULL)
    assert cal.axes[4].reversed and cal.axes[1].reversed
    assert not cal.axes[3].reversed and not cal.axes[0].reversed
    assert cal.axes[1].centre == 0  # throttle: midpoint of its travel (down-zero)

    # The stored calibration flies the right way: forward -> +x, right -> +y, up -> thrust.
    c = Commander(PilotSettings(deadband=0, expo=0), load_calibrations(out))
    centred = {0: 0, 1: FULL, 2: -FULL, 3: 250, 4: -120, 5: -FULL}
    c.tick(0, InputSnapshot(NAME, True, 0, None, centred, 0))
    c.tick(1, InputSnapshot(NAME, True, 0, None, centred, (1 << 6) | (1 << 7)))
    assert c.state == "ARMED"
    axes = {**centred, 4: -FULL, 3: FULL, 1: -FULL, 0: -FULL}
    cmd = c.tick(2, InputSnapshot(NAME, True, 0, None, axes, 0)).command
    assert (cmd.x, cmd.y, cmd.z, cmd.r) == (1000, 1000, 1000, -1000)


def test_end_of_input_aborts_without_writing(fifo, tmp_path):
    out = tmp_path / "joystick.toml"
    cli = Cli(fifo, out)
    w = open_writer(fifo)
    cli.expect("[step 1/6]")
    cli.enter()
    cli.expect("[step 2/6]")
    rc, err = cli.finish()  # stdin closed mid-way
    w.close()
    assert rc == 1 and "end of input" in err and not out.exists()


def test_too_few_axes_moved_is_a_clear_error(fifo, tmp_path):
    out = tmp_path / "joystick.toml"
    cli = Cli(fifo, out)
    w = open_writer(fifo)
    cli.expect("[step 1/6]")
    cli.enter()
    cli.expect("[step 2/6]")
    sweep(w, (0, 1))
    cli.enter()
    rc, err = cli.finish()
    w.close()
    assert rc == 2 and "only 2 axes moved" in err and "hint:" in err and not out.exists()


def test_missing_device_times_out_with_a_hint(tmp_path):
    cli = Cli(str(tmp_path / "nope"), tmp_path / "j.toml", "--timeout", "0.3")
    rc, err = cli.finish()
    assert rc == 2 and "no joystick input" in err and "hint:" in err


def test_pure_helpers():
    chunk = encode_events(JsEvent(0, v, JS_EVENT_AXIS, 2) for v in (5, -900, 700))
    lo, hi = extremes([chunk[:11], chunk[11:]], {2: 0, 4: 10})
    assert (lo[2], hi[2], lo[4], hi[4]) == (-900, 700, 10, 10)
    assert deflection(350, 0, -900, 700) == pytest.approx(0.5)
    assert deflection(-900, 0, -900, 700) == -1.0
    values, centre = {0: 0, 1: -800, 2: 400}, {0: 0, 1: 0, 2: 0}
    lo, hi = {0: -1000, 1: -1000, 2: -1000}, {0: 1000, 1: 1000, 2: 1000}
    assert pick_axis(values, centre, lo, hi, [0, 1, 2]) == (1, True)
    assert pick_axis(values, centre, lo, hi, [0, 2]) is None  # 0.4 < half travel
