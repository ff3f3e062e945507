"""The device shell over a real FIFO: INIT burst, events, loss, staleness rule, reconnect."""

from __future__ import annotations

import os
import threading

import pytest

from groundstation.pilot.jsdev import JoystickDevice, JsEvent, encode_events, init_burst
from tests.unit.pilot.fifo_joystick import FifoJoystick

pytestmark = pytest.mark.timeout(60)


def wait_until(pred, timeout=5.0, step=0.005) -> bool:
    ev = threading.Event()
    for _ in range(int(timeout / step)):
        if pred():
            return True
        ev.wait(step)
    return pred()


@pytest.fixture
def fifo(tmp_path):
    path = str(tmp_path / "js0")
    os.mkfifo(path)
    return path


def dev(path, **kw):
    kw.setdefault("name", "Fifo Pad")
    kw.setdefault("reconnect_min_ms", 10)
    kw.setdefault("reconnect_max_ms", 80)
    return JoystickDevice(path, **kw)


def test_init_burst_and_events_reach_the_snapshot(fifo):
    w = FifoJoystick(fifo, n_axes=4, n_buttons=8)
    w.axes[:] = [100, -200, 300, 32767]
    w.buttons[2] = True
    with dev(fifo) as d:
        w.open()
        assert d.wait_connected(5)
        assert d.barrier(5)
        s = d.snapshot()
        assert s.name == "Fifo Pad" and d.n_axes is None  # FIFO: no ioctls, name from setting
        assert s.axes == {0: 100, 1: -200, 2: 300, 3: 32767} and s.buttons == 1 << 2
        w.set_axes(a1=5000)
        w.buttons_to({2: False, 6: True})
        assert d.barrier(5)
        s = d.snapshot()
        assert s.axes[1] == 5000 and s.buttons == 1 << 6
        raw = b"".join(c for _, c in d.drain_raw())
        assert len(raw) == 8 * (12 + 3)  # the INIT burst: 8 buttons + 4 axes, then 3 events
        assert raw[4:8] == init_burst([], [False])[4:8]  # first: button 0 released, INIT
        assert d.stats.events == 15 and d.stats.bad_events == 0
        w.close()


def test_partial_writes_and_corrupt_types_are_survived_and_counted(fifo):
    with dev(fifo) as d:
        w = FifoJoystick(fifo).open()
        data = encode_events(
            [JsEvent(1, 1234, 0x02, 0), JsEvent(2, 7, 0x40, 9), JsEvent(3, 1, 0x01, 3)]
        )
        for i in range(0, len(data), 5):
            os.write(w.fd, data[i : i + 5])
            assert d.barrier(5)
        s = d.snapshot()
        assert s.axes[0] == 1234 and s.buttons & (1 << 3)
        assert d.stats.bad_events == 1 and s.connected and s.fault is None
        w.close()


def test_fifo_writer_that_stops_is_not_alive_but_a_live_idle_chardev_is(fifo):
    with dev(fifo) as d:
        w = FifoJoystick(fifo).open()
        assert d.wait_connected(5) and d.barrier(5)
        last = d.snapshot().alive_ns
        t0 = d.stats.timeouts
        assert wait_until(lambda: d.stats.timeouts >= t0 + 3)  # three quiet select timeouts
        assert d.snapshot().alive_ns == last  # FIFO rule: only bytes prove life
        w.close()
    with dev(fifo, idle_is_alive=True) as d:  # the character-device rule, forced
        w = FifoJoystick(fifo).open()
        assert d.wait_connected(5) and d.barrier(5)
        last = d.snapshot().alive_ns
        t0 = d.stats.timeouts
        assert wait_until(lambda: d.stats.timeouts >= t0 + 3)
        assert d.snapshot().alive_ns > last
        w.close()


def test_writer_close_is_device_loss_then_reconnect_with_fresh_state(fifo):
    with dev(fifo) as d:
        w = FifoJoystick(fifo)
        w.axes[0] = 9000
        w.open()
        assert d.wait_connected(5) and d.barrier(5)
        gen = d.snapshot().generation
        w.close()
        assert wait_until(lambda: d.snapshot().fault == "device_lost")
        s = d.snapshot()
        assert not s.connected and d.stats.losses >= 1
        w2 = FifoJoystick(fifo)
        w2.axes[0] = -700
        w2.open()
        assert wait_until(lambda: d.snapshot().connected and d.snapshot().alive_ns is not None)
        assert d.barrier(5)
        s = d.snapshot()
        assert s.fault is None and s.generation > gen and s.axes[0] == -700
        kinds = [n.kind for n in d.drain_notices()]
        assert "opened" in kinds and "device_lost" in kinds
        w2.close()


def test_missing_device_is_retried_with_bounded_backoff_until_it_appears(tmp_path):
    path = str(tmp_path / "later")
    with dev(path) as d:
        assert wait_until(lambda: d.stats.open_attempts >= 3)
        s = d.snapshot()
        assert s.fault == "device_lost" and not s.connected
        assert any(n.kind == "open_failed" for n in d.drain_notices())
        os.mkfifo(path)
        w = FifoJoystick(path).open()
        assert d.wait_connected(5)
        w.close()


def test_non_joystick_character_device_falls_back_gracefully():
    with dev("/dev/null", name="Null Pad") as d:  # ioctls fail (ENOTTY); reads give EOF
        assert wait_until(lambda: d.stats.opens >= 1 and d.snapshot().fault == "device_lost")
        assert d.snapshot().name == "Null Pad" and d.n_axes is None
