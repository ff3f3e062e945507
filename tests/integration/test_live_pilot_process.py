"""The pilot process alone, over a real FIFO and real ZeroMQ: ``pilot.command`` only while ARMED
(never in DISARMED / FAILSAFE / ESTOP, not even on the e-stop tick), every js_event byte on
``raw.pilot`` exactly as written (for the recording), mux and device events on ``pilot.event``,
a loud ``status``, and a clean exit on SIGINT. Counts and contents, never timing."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zmq

from groundstation.bus.pubsub import Subscriber
from groundstation.pilot.jsevent import (
    JS_EVENT_AXIS,
    JS_EVENT_BUTTON,
    JsEvent,
    encode_events,
    init_burst,
)
from groundstation.runtime.session import Session, new_session_id
from tests.integration.test_pilot_sitl import PAD, write_calibration
from tests.unit.pilot.fifo_joystick import FULL

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.timeout(120)


class Writer:
    """Writes js_event bytes into the FIFO and keeps a copy of everything written."""

    def __init__(self, path: Path):
        self.fd = os.open(path, os.O_WRONLY)  # blocks until the pilot process opens it
        self.sent = bytearray()
        self.axes = [0, 0, 0, FULL]  # centred, throttle low (reversed axis)
        self.buttons = [False] * 8
        self.write(init_burst(self.axes, self.buttons, 0))

    def write(self, data: bytes) -> None:
        os.write(self.fd, data)
        self.sent += data

    def stream(self, seconds: float, period: float = 0.01) -> None:
        """Repeat the axes (a FIFO must keep talking to stay fresh)."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.write(
                encode_events(JsEvent(1, v, JS_EVENT_AXIS, n) for n, v in enumerate(self.axes))
            )
            time.sleep(period)

    def press(self, pressed: dict[int, bool]) -> None:
        self.write(
            encode_events(JsEvent(1, int(v), JS_EVENT_BUTTON, n) for n, v in pressed.items())
        )

    def close(self) -> None:
        os.close(self.fd)


def test_pilot_process_publishes_commands_only_while_armed_and_every_raw_byte(tmp_path):
    cal = write_calibration(tmp_path / "joystick.toml")
    fifo = tmp_path / "js0"
    os.mkfifo(fifo)
    session = Session(new_session_id(), ("pilot",))
    ctx = zmq.Context()
    sub = Subscriber(
        session.subscribe_endpoints(),
        ["pilot.command", "pilot.event", "raw.pilot", "status"],
        context=ctx,
    )
    got: list = []
    done = threading.Event()

    def collect() -> None:
        while not done.is_set():
            env = sub.recv(100)
            if env is not None:
                got.append(env)

    proc = subprocess.Popen(
        [sys.executable, "-m", "groundstation.runtime.workers.pilot", *session.as_args(),
         "--device", str(fifo), "--rate", "50", "--wait-subscribers", "1",
         "--set", f"pilot.device_name={PAD}", "--set", f"pilot.calibration_path={cal}"],
        cwd=ROOT, stdin=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    rx = threading.Thread(target=collect, daemon=True)
    rx.start()
    try:
        w = Writer(fifo)
        w.stream(0.6)  # healthy, not armed: nothing to send
        w.press({6: True, 7: True})
        w.stream(0.3)
        w.press({6: False, 7: False})
        w.stream(1.0)  # armed: 50 Hz of commands
        w.press({1: True})  # e-stop
        w.stream(0.6)
        w.close()  # device lost
        time.sleep(0.5)
    finally:
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(30)
        time.sleep(0.3)
        done.set()
        rx.join(5)
        sub.close()
        ctx.term()
    assert rc == 0, proc.stderr.read()[-2000:]

    by = lambda topic: [e for e in got if e.topic == topic]  # noqa: E731
    events = by("pilot.event")
    kinds = [e.payload["event"] for e in events]
    assert "device_opened" in kinds and "armed" in kinds and "estop" in kinds, kinds
    assert "device_device_lost" in kinds, kinds
    armed_ns = next(e.header.source_ns for e in events if e.payload["event"] == "armed")
    estop_ns = next(e.header.source_ns for e in events if e.payload["event"] == "estop")
    cmds = by("pilot.command")
    # at most one command per 50 Hz tick of the pilot's own armed window (~1.3 s of the writer's
    # clock; a pilot starved of CPU reads the FIFO's backlog late, and its window shrinks)
    ticks_armed = (estop_ns - armed_ns) / 1e9 * 50
    assert 1 <= len(cmds) <= ticks_armed + 2, (len(cmds), ticks_armed)
    assert all(armed_ns <= c.header.source_ns < estop_ns for c in cmds)
    assert all(c.payload["enabled"] and c.payload["z"] == 0 for c in cmds)
    assert [c.header.seq for c in cmds] == list(range(len(cmds)))
    raw = b"".join(bytes(e.arrays["data"]) for e in by("raw.pilot"))
    assert raw == bytes(w.sent)  # every byte, in order, as written
    texts = [e.payload.get("text", "") for e in by("status")]
    assert any("EMERGENCY STOP" in t for t in texts), texts
    assert by("status")[-1].payload["state"] == "stopped"
    ticks = [e.payload["topics"]["loop"]["ticks"] for e in by("status")]
    assert ticks == sorted(ticks) and ticks[-2] > 50  # live counts while running (50 Hz)
