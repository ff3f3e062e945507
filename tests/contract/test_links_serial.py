"""SerialLink over real pseudo-terminals: data both ways, damage mid-stream, unplug/replug."""

from __future__ import annotations

import os
import select
import threading
import tty

import pytest

from firmware_bridge.link import open_link
from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import AttitudeSample, Heartbeat, ImuSample

pytestmark = pytest.mark.timeout(60)


class Device:
    """The far end of a serial cable: a pty master whose slave is reached through a symlink."""

    def __init__(self, link_path: str) -> None:
        self.link_path = link_path
        self.master = -1
        self.plug()

    def plug(self) -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        self.master, self._slave = master, slave
        tmp = self.link_path + ".tmp"
        os.symlink(os.ttyname(slave), tmp)
        os.replace(tmp, self.link_path)  # atomic re-point

    def release_slave(self) -> None:
        """Close our own handle on the slave once the link has opened it."""
        if self._slave >= 0:
            os.close(self._slave)
            self._slave = -1

    def unplug(self) -> None:
        self.release_slave()
        os.close(self.master)
        self.master = -1

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self.master, view) :]

    def read(self, timeout_s: float) -> bytes:
        ready, _, _ = select.select([self.master], [], [], timeout_s)
        return os.read(self.master, 4096) if ready else b""


class Reader:
    """A reader thread decoding everything the link delivers."""

    def __init__(self, link) -> None:
        self.link, self.codec, self.records = link, MavlinkCodec(), []
        self.got = threading.Condition()
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            data = self.link.read(0.05)
            if data:
                recs = self.codec.decode(data, 0)
                with self.got:
                    self.records += recs
                    self.got.notify_all()

    def wait_for(self, n: int, timeout_s: float = 10.0) -> int:
        with self.got:
            self.got.wait_for(lambda: len(self.records) >= n, timeout_s)
            return len(self.records)

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(5)


@pytest.fixture
def device(tmp_path):
    dev = Device(str(tmp_path / "ttyVEHICLE"))
    yield dev
    if dev.master >= 0:
        dev.unplug()


def frames(codec: MavlinkCodec, n: int, t0: int = 0) -> list[bytes]:
    """IMU + attitude frame pairs at 200 Hz source time; no 0xFD/0xFE byte after the start byte
    (so damage accounting is exact), sequence numbers contiguous."""
    out = []
    for i in range(n):
        for make in (
            lambda t: ImuSample((0.5, 0.25, -9.75), (0.125, 0.0625, 0.5), time_source_ns=t),
            lambda t: AttitudeSample((1, 0, 0, 0), (0.25, 0.5, 0.125), time_source_ns=t),
        ):
            t = (t0 + i) * 5_000_000
            while True:
                f = codec.encode(make(t))
                if 0xFD not in f[1:] and 0xFE not in f[1:]:
                    break
                codec._tx.seq = (codec._tx.seq - 1) & 0xFF
                t += 1_000_000  # nudge the timestamp by 1 ms and retry
            out.append(f)
    return out


def test_bytes_flow_both_ways(device):
    link = open_link(f"serial://{device.link_path}?baud=921600")
    device.release_slave()
    try:
        reader = Reader(link)
        tx = MavlinkCodec(1, 1)
        device.write(b"".join(frames(tx, 50)))
        assert reader.wait_for(100) == 100
        reader.stop()
        hb = MavlinkCodec().encode(Heartbeat(6, 8, 0, 0, 4))
        link.write(hb)
        got = b""
        while len(got) < len(hb):
            chunk = device.read(5.0)
            assert chunk, "nothing arrived on the device side"
            got += chunk
        assert got == hb
        assert reader.codec.stats.lost == 0 and reader.codec.stats.crc_errors == 0
    finally:
        link.close()
    assert [e.kind for e in link.events][-1] == "closed"


def test_damage_mid_stream_is_counted_and_later_frames_decode(device):
    link = open_link(f"serial://{device.link_path}")
    device.release_slave()
    reader = Reader(link)
    try:
        tx = MavlinkCodec(1, 1)
        good = frames(tx, 20)
        assert not any(0xFD in f[1:] or 0xFE in f[1:] for f in good)
        flipped = bytearray(good[11])
        flipped[20] ^= 0x40
        stream = (
            b"".join(good[:10])
            + bytes([0x01, 0x02, 0x03, 0x55] * 16)  # 64 bytes of noise
            + good[10]
            + bytes(flipped)  # CRC error
            + good[12][:15]  # truncated
            + b"".join(good[13:])
        )
        device.write(stream)
        expected = len(good) - 2
        assert reader.wait_for(expected) == expected
        st = reader.codec.stats
        assert st.crc_errors == 2
        assert st.garbage_bytes == 64 + len(flipped) + 15
        assert st.lost == 2
    finally:
        reader.stop()
        link.close()


def test_unplug_replug_same_link_object(device):
    link = open_link(
        f"serial://{device.link_path}?baud=921600&reconnect_min_s=0.02&reconnect_max_s=0.2"
    )
    device.release_slave()
    reader = Reader(link)
    try:
        tx = MavlinkCodec(1, 1)
        device.write(b"".join(frames(tx, 10)))
        assert reader.wait_for(20) == 20

        device.unplug()
        assert link.wait_for_event("disconnected", 10.0) is not None
        assert not link.connected
        assert link.write(b"while unplugged") is False  # dropped, not raised
        assert link.dropped_writes >= 1
        assert link.wait_for_event("reconnect_failed", 10.0) is not None  # the path is dead

        device.plug()  # a new pty behind the same symlink
        assert link.wait_for_event("reconnected", 10.0) is not None
        device.release_slave()
        device.write(b"".join(frames(tx, 10, t0=10)))
        assert reader.wait_for(40) == 40
        assert reader.records[-1].time_source_ns // 5_000_000 == 19
        hb = MavlinkCodec().encode(Heartbeat(6, 8, 0, 0, 4))
        link.write(hb)
        assert device.read(5.0).startswith(hb[:1])
        assert reader.thread.is_alive() and link.reconnects == 1
    finally:
        reader.stop()
        link.close()
    kinds = [e.kind for e in link.events]
    assert kinds.index("disconnected") < kinds.index("reconnected")
