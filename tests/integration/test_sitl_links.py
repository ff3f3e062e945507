"""``groundstation sitl`` as a real process, read by the station's links over a real pseudo-terminal
and real UDP loopback: no lost frames at 1x and 5x, commands answered, NatNet 4.1 decodes,
corrupted bytes injected on the pty path are counted and skipped, pymavlink's mavutil sees it.

Rates are checked by counting frames and their source timestamps, never by wall-clock time.
"""

from __future__ import annotations

import json
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest

from firmware_bridge.link import open_link
from firmware_bridge.mavlink import MavlinkCodec
from firmware_bridge.mavlink.messages import (
    CommandAck,
    Heartbeat,
    ImuSample,
    ManualControl,
    SetMessageInterval,
    Timesync,
)
from firmware_bridge.natnet import FrameOfData, parse_packet

ROOT = Path(__file__).resolve().parents[2]
# these tests read the SITL's stream without a station: it must not wait for one
SITL = [sys.executable, "-m", "groundstation.cli", "sitl", "--no-wait-for-station"]
IMU_PERIOD_NS = 5_000_000

pytestmark = pytest.mark.timeout(120)


@contextmanager
def sitl(*args: str):
    """Run ``groundstation sitl ARGS``; stopped with SIGTERM (then SIGKILL) on exit."""
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        SITL + list(args), cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True,
    )  # fmt: skip
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(5)
        proc.stdout.close()
        proc.stderr.close()


def first_line(proc: subprocess.Popen, prefix: str, timeout_s: float = 30.0) -> str:
    """The first stdout line starting with ``prefix`` (the SITL prints its device/target)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        ready, _, _ = select.select([proc.stdout], [], [], 0.5)
        if ready:
            line = proc.stdout.readline()
            if line.startswith(prefix):
                return line.strip()
            if not line and proc.poll() is not None:
                break
    raise AssertionError(f"SITL did not print {prefix!r}: {proc.stderr.read()[-2000:]}")


class Reader(threading.Thread):
    """Reads a link until stopped, decoding MAVLink (or keeping raw NatNet datagrams)."""

    def __init__(self, link, mavlink: bool = True):
        super().__init__(daemon=True)
        self.link = link
        self.codec = MavlinkCodec() if mavlink else None
        self.records: list = []
        self.datagrams: list[tuple[int, bytes]] = []
        self.last_data = time.monotonic()
        self._halt = threading.Event()

    def run(self) -> None:
        while not self._halt.is_set():
            data = self.link.read(0.1)
            if not data:
                continue
            now = time.monotonic_ns()
            self.last_data = time.monotonic()
            if self.codec is not None:
                self.records.extend(self.codec.decode(data, now))
            else:
                self.datagrams.append((now, data))

    def stop(self) -> None:
        self._halt.set()
        self.join(5)

    def of(self, kind: type) -> list:
        return [r for r in list(self.records) if isinstance(r, kind)]


def wait_done(proc: subprocess.Popen, readers: list[Reader], timeout_s: float) -> str:
    """Wait for the SITL to finish and its last bytes to be read; return its stderr."""
    proc.wait(timeout_s)
    end = time.monotonic() + 5.0
    while time.monotonic() < end and any(time.monotonic() - r.last_data < 0.3 for r in readers):
        time.sleep(0.05)
    for r in readers:
        r.stop()
    return proc.stderr.read()


def assert_continuous(imu: list[ImuSample]) -> np.ndarray:
    """HIGHRES_IMU time_usec advances by exactly 5 ms from the first frame to the last."""
    t = np.array([r.time_source_ns for r in imu], dtype=np.int64)
    assert len(t) > 10
    gaps = np.flatnonzero(np.diff(t) != IMU_PERIOD_NS)
    assert gaps.size == 0, f"{gaps.size} gaps, first at {t[gaps[0]]} ns: {np.diff(t)[gaps[:5]]}"
    return t


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize("speed", ["1", "5"])
def test_pty_stream_has_no_lost_frames(speed):
    seconds = "5" if speed == "1" else "10"
    with sitl("--link", "pty", "--pilot", "script:survey", "--scene", "wall", "--speed", speed,
              "--duration", seconds, "--seed", "1") as proc:  # fmt: skip
        path = first_line(proc, "SITL MAVLink on ").rsplit(" ", 1)[1]
        assert path.startswith("/dev/")
        link = open_link(f"serial://{path}?baud=921600")
        reader = Reader(link)
        reader.start()
        try:
            err = wait_done(proc, [reader], 60)
        finally:
            link.close()
    assert proc.returncode == 0, err
    t = assert_continuous(reader.of(ImuSample))
    # Everything from the moment the station opened the device to the end arrived.
    assert t[-1] == int(seconds) * 1_000_000_000
    assert len(t) >= int(seconds) * 200 - 300  # bytes written before the open are flushed
    assert reader.codec.stats.crc_errors <= 1  # at most a frame cut by the open-time flush
    assert "dropped 0 frames" in err


@pytest.mark.parametrize("speed", ["1", "5"])
def test_udp_stream_and_natnet_have_no_lost_frames(speed):
    seconds = 5 if speed == "1" else 10
    link = open_link("udp://127.0.0.1:0?mode=listen")
    mocap = open_link("natnet://127.0.0.1:0")
    port, mport = link.local_address[1], mocap.local_address[1]
    readers = [Reader(link), Reader(mocap, mavlink=False)]
    for r in readers:
        r.start()
    try:
        with sitl("--link", f"udp://127.0.0.1:{port}", "--mocap", f"udp://127.0.0.1:{mport}",
                  "--mocap-drop", "0", "--pilot", "script:survey", "--scene", "pillar",
                  "--speed", speed, "--duration", str(seconds), "--seed", "2") as proc:  # fmt: skip
            err = wait_done(proc, readers, 60)
    finally:
        link.close()
        mocap.close()
    assert proc.returncode == 0, err
    mav, nat = readers
    t = assert_continuous(mav.of(ImuSample))
    assert len(t) == 200 * seconds and t[0] == IMU_PERIOD_NS
    assert len(mav.of(Heartbeat)) == seconds
    assert mav.codec.stats.crc_errors == 0 and mav.codec.stats.lost == 0
    frames = [parse_packet(d, (4, 1)) for _, d in nat.datagrams]
    assert all(isinstance(f, FrameOfData) for f in frames)
    assert [f.frame_id for f in frames] == list(range(1, 200 * seconds + 1))
    body = frames[0].rigid_body(1)
    assert body is not None and body.tracking_valid
    # Motive Y-up: height is +y; the pillar scene starts 1 m up.
    assert body.position[1] == pytest.approx(1.0, abs=0.05)


def test_udp_commands_interval_ack_timesync_manual_control():
    link = open_link("udp://127.0.0.1:0?mode=listen")
    reader = Reader(link)
    reader.start()
    gcs = MavlinkCodec(system_id=255, component_id=190)
    try:
        with sitl("--link", f"udp://127.0.0.1:{link.local_address[1]}", "--pilot", "manual",
                  "--speed", "4", "--duration", "8", "--gust-rate", "0") as proc:  # fmt: skip
            end = time.monotonic() + 30
            while not reader.of(Heartbeat) and time.monotonic() < end:
                time.sleep(0.05)
            assert reader.of(Heartbeat), "no HEARTBEAT from the SITL"
            link.write(gcs.encode(SetMessageInterval(105, 10_000)))  # HIGHRES_IMU at 100 Hz
            link.write(gcs.encode(Timesync(tc1=0, ts1=42_000_000)))
            for _ in range(10):
                link.write(gcs.encode(ManualControl(0, 0, 900, 0)))  # climb
                time.sleep(0.05)
            err = wait_done(proc, [reader], 60)
    finally:
        link.close()
    assert proc.returncode == 0, err
    acks = reader.of(CommandAck)
    assert [(a.command, a.result) for a in acks] == [(511, 0)]
    ts = reader.of(Timesync)
    assert len(ts) == 1 and ts[0].ts1 == 42_000_000 and ts[0].tc1 > 0
    t = np.array([r.time_source_ns for r in reader.of(ImuSample)])
    d = np.diff(t)
    assert set(d[:20]) == {5_000_000} and set(d[-20:]) == {10_000_000}
    assert np.count_nonzero((d != 5_000_000) & (d != 10_000_000)) <= 1  # the switch itself
    assert "manual 10" in err


def test_mavutil_sees_heartbeat_and_highres_imu():
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    port = _free_udp_port()
    conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}")
    counts = {"HEARTBEAT": 0, "HIGHRES_IMU": 0}
    first_usec = last_usec = None
    try:
        with sitl("--link", f"udp://127.0.0.1:{port}", "--pilot", "script:hover", "--speed", "1",
                  "--duration", "3") as proc:  # fmt: skip
            while True:
                msg = conn.recv_match(type=list(counts), blocking=True, timeout=1.0)
                if msg is None:
                    if proc.poll() is not None:
                        break
                    continue
                counts[msg.get_type()] += 1
                if msg.get_type() == "HIGHRES_IMU":
                    first_usec = first_usec if first_usec is not None else msg.time_usec
                    last_usec = msg.time_usec
            assert proc.wait(10) == 0
    finally:
        conn.close()
    span_s = (last_usec - first_usec) / 1e6
    assert counts["HEARTBEAT"] in (2, 3, 4)
    assert counts["HIGHRES_IMU"] / (span_s + 0.005) == pytest.approx(200, rel=0.02)
    assert counts["HIGHRES_IMU"] >= 570


def test_corrupted_bytes_on_the_pty_path_are_counted_and_skipped():
    """A relay between the SITL's pty and a second pty flips and inserts bytes."""
    with sitl("--link", "pty", "--pilot", "script:hover", "--speed", "4", "--duration", "8",
              "--seed", "3") as proc:  # fmt: skip
        path = first_line(proc, "SITL MAVLink on ").rsplit(" ", 1)[1]
        upstream = open_link(f"serial://{path}?baud=921600")
        master, slave = os.openpty()
        import tty

        tty.setraw(slave)
        station = open_link(f"serial://{os.ttyname(slave)}?baud=921600")
        reader = Reader(station)
        reader.start()
        flips = inserted = 0
        total = 0
        garbage = bytes(range(0x20, 0x30))  # 16 bytes, no MAVLink start byte
        rng = np.random.default_rng(0)
        next_flip = 3000
        try:
            while proc.poll() is None or time.monotonic() - reader.last_data < 0.3:
                data = bytearray(upstream.read(0.1))
                if not data and proc.poll() is not None:
                    break
                out = bytearray()
                for i in range(len(data)):
                    if total + i == next_flip:
                        data[i] ^= 0x55
                        flips += 1
                        if flips % 2 == 0:
                            out += garbage
                            inserted += len(garbage)
                        next_flip += 3000 + int(rng.integers(0, 100))
                    out.append(data[i])
                total += len(data)
                if out:
                    os.write(master, bytes(out))
            time.sleep(0.3)
            reader.stop()
        finally:
            upstream.close()
            station.close()
            os.close(master)
            os.close(slave)
    assert proc.returncode == 0
    st = reader.codec.stats
    assert flips >= 20
    # Each flipped byte damages exactly one frame (flips are > 1 frame apart).
    assert flips - 1 <= st.crc_errors <= flips + 1
    assert st.garbage_bytes >= inserted
    imu = reader.of(ImuSample)
    gaps = np.diff([r.time_source_ns for r in imu]) // IMU_PERIOD_NS - 1
    assert gaps.min() >= 0
    assert gaps.sum() <= flips  # only damaged frames are missing; the rest decode
    assert len(imu) > 1000


def test_sigusr1_shows_the_stacks_and_sigterm_stops_cleanly_and_writes_truth(tmp_path):
    truth = tmp_path / "truth.json"
    with sitl("--link", "pty", "--pilot", "script:survey", "--scene", "pillar", "--speed", "4",
              "--truth", str(truth), "--gust-rate", "30") as proc:  # fmt: skip
        first_line(proc, "SITL MAVLink on ")
        time.sleep(0.5)
        proc.send_signal(signal.SIGUSR1)  # every command: the stacks to stderr, then go on
        time.sleep(1.0)
        assert proc.poll() is None
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(15) == 0
        err = proc.stderr.read()
    assert "stopped (SIGTERM)" in err
    assert "Current thread" in err and 'File "' in err and "groundstation" in err, err[-2000:]
    doc = json.loads(truth.read_text())
    assert doc["vehicle"] == {**doc["vehicle"], "radius": 0.2, "height": 0.1}
    assert doc["duration"] > 1.0
    assert doc["scene"]["name"] == "pillar"


@pytest.mark.soak
@pytest.mark.timeout(200)
def test_soak_pty_60s_realtime_no_lost_frames():
    with sitl("--link", "pty", "--pilot", "script:survey", "--scene", "paper", "--speed", "1",
              "--duration", "60", "--seed", "5") as proc:  # fmt: skip
        path = first_line(proc, "SITL MAVLink on ").rsplit(" ", 1)[1]
        link = open_link(f"serial://{path}?baud=921600")
        reader = Reader(link)
        reader.start()
        try:
            err = wait_done(proc, [reader], 120)
        finally:
            link.close()
    assert proc.returncode == 0, err
    t = assert_continuous(reader.of(ImuSample))
    assert t[-1] == 60_000_000_000 and len(t) >= 60 * 200 - 300


def test_pty_never_blocks_and_drops_whole_frames_when_nobody_reads():
    from firmware_bridge.sitl.transport import PtyTransport

    tx = PtyTransport()
    enc = MavlinkCodec(system_id=1, component_id=1)
    try:
        frames = [
            enc.encode(ImuSample((0.0, 0.0, -9.8), (0.0, 0.0, 0.0), time_source_ns=i * 5_000_000))
            for i in range(1, 3001)
        ]
        for f in frames:
            tx.send(f)  # returns at once even though the reader is absent
        assert tx.stats.frames_dropped > 0
        assert tx.stats.frames_sent + tx.stats.frames_dropped == len(frames)
        fd = os.open(tx.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        station = MavlinkCodec()
        got = []
        try:
            for _ in range(200):
                tx.flush()
                try:
                    data = os.read(fd, 65536)
                except BlockingIOError:
                    if not tx.pending_bytes:
                        break
                    time.sleep(0.01)
                    continue
                got += station.decode(data, 0)
        finally:
            os.close(fd)
    finally:
        tx.close()
    assert station.stats.crc_errors == 0  # only whole frames were dropped
    assert len(got) == tx.stats.frames_sent
